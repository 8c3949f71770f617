"""The learned simulator: one-step predictions and rollouts, as pure cores and host conveniences.

Units are normalised (positions and radii divided by the length scale ``L``;
the box is ``model_config.bounds``, by default ``[-1, 1]^D``) and frames (one
frame = one time unit, 1.5 ms in the paper's data).

One step, for the last ``C`` positions ``x_{t-C+1} .. x_t`` of every particle:

1. radius graph at ``x_t`` (:mod:`dispgns.graph`), node and edge features
   (:mod:`dispgns.features`), velocity features standardised with
   ``params["normalization"]``;
2. network output ``y`` (:mod:`dispgns.model`), acceleration
   ``acc = (y * acceleration_std + acceleration_mean) * a_i``;
3. ``v_new = (x_t - x_{t-1}) + acc``, ``x_new = x_t + v_new``.

**Pure cores** work under ``jit``, ``vmap``, ``grad`` and ``lax.scan``. The
graph capacity is a static argument and an overflow is a returned flag
(the outputs of an overflowing step are NaN, never silently wrong):
:func:`predict_step`, :func:`predict_step_batch` and :func:`rollout_scan`.
Size the capacity on the host with :func:`fit_capacity` (with head-room for
a rollout under ``jit``, where it cannot grow), or take
:func:`dispgns.graph.full_capacity`, which never overflows.

**Host conveniences** take concrete arrays, size the capacity from the data,
and grow it and redo the work after an overflow (:func:`dispgns.capacity.drive`):
:func:`predict_acceleration`, :func:`predict_position`, :func:`rollout`,
:func:`rollout_batch`. Their result is that of a graph without any size
limit. Called with traced arrays they raise and name the pure core.

Padding particles (``mask == False``) never influence real ones; their
outputs are zero accelerations and unchanged positions.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import ArrayLike, Bool, Float

from dispgns import features as features_lib
from dispgns import graph as graph_lib
from dispgns.arrays import (
    BatchFrame,
    BatchMask,
    BatchPositions,
    BatchRadii,
    BatchWindow,
    Count,
    Flag,
    Frame,
    Params,
    ParticleMask,
    Positions,
    PositionWindow,
    Radii,
    host_array,
)
from dispgns.capacity import Attempt, drive
from dispgns.graph import Graph, GraphCapacity
from dispgns.model import ModelConfig, apply_network
from dispgns.tuning import jitted
from dispgns.validation import check_particles

# Shapes (jaxtyping, no runtime check) of one trajectory's arrays or a batch's (leading B).
_Frames = Float[ArrayLike, "*B N D"]
_Flags = Bool[ArrayLike, "*B"]
_Window = Float[ArrayLike, "*B C N D"]
_StepPositions = Float[ArrayLike, "L *B N D"]
_AnyFrames = Float[ArrayLike, "*frames N D"]
_AnyMask = Bool[ArrayLike, "*frames N"]

__all__ = [
    "PredictedStep",
    "acceleration_from_output",
    "build_graph",
    "fit_capacity",
    "floor_symmetries",
    "network_output",
    "network_output_batch",
    "next_position_batch",
    "predict_acceleration",
    "predict_position",
    "predict_step",
    "predict_step_batch",
    "rollout",
    "rollout_batch",
    "rollout_scan",
    "sanitize",
    "steps_until_overflow",
]


class PredictedStep(NamedTuple):
    """One learned step (a pytree).

    Attributes:
      acceleration: ``(..., N, D)`` in normalised units per frame^2.
      position: ``(..., N, D)`` of the next frame.
      overflow: ``()`` (or ``(B,)``) bool: the graph missed edges, and both
        arrays are NaN.
    """

    acceleration: _Frames
    position: _Frames
    overflow: _Flags


# ----------------------------------------------------------------------------- the pieces of one step


def as_capacity(capacity: GraphCapacity | int | None) -> GraphCapacity:
    """A :class:`GraphCapacity` from a capacity or an int (ordered pairs ``s != r``, all-pairs search)."""
    if isinstance(capacity, GraphCapacity):
        return capacity
    if capacity is None:
        raise ValueError(
            "a pure core needs a graph capacity: dispgns.fit_capacity(positions, model_config) on the host, "
            "or dispgns.graph.full_capacity(N), which never overflows"
        )
    return GraphCapacity(edges=int(capacity))


def sanitize(
    position_seq: PositionWindow, radius: Radii, mask: ParticleMask, model_config: ModelConfig
) -> tuple[PositionWindow, Radii]:
    """Padding rows replaced by parked positions and unit radii (finite features, no edges to real particles)."""
    position_seq = graph_lib.park_padding(
        position_seq, mask, connectivity_radius=model_config.connectivity_radius, bounds=model_config.bounds
    )
    radius = jnp.where(mask, radius, jnp.ones_like(radius))
    return position_seq, radius


def build_graph(position: Frame, mask: ParticleMask, capacity: GraphCapacity, model_config: ModelConfig) -> Graph:
    """The radius graph of ``position`` ``(N, D)`` for ``model_config`` (see :func:`dispgns.graph.radius_graph`)."""
    return graph_lib.radius_graph(
        position,
        mask,
        connectivity_radius=model_config.connectivity_radius,
        capacity=capacity,
        bounds=model_config.bounds,
    )


def _standardized_nodes(position_seq, radius, norm, c: ModelConfig):
    nodes = features_lib.node_features(position_seq, radius, bounds=c.bounds, boundary_clip=c.boundary_clip)
    n_vel = (c.input_sequence_length - 1) * c.dim
    mean = jnp.tile(norm["velocity_mean"], c.input_sequence_length - 1).astype(nodes.dtype)
    std = jnp.tile(norm["velocity_std"], c.input_sequence_length - 1).astype(nodes.dtype)
    return jnp.concatenate([(nodes[:, :n_vel] - mean) / std, nodes[:, n_vel:]], axis=-1)


def network_output(
    params: Params, position_seq: PositionWindow, radius: Radii, graph: Graph, *, model_config: ModelConfig
) -> Frame:
    """Standardised network output ``(N, D)`` for sanitised inputs and a graph (what the loss compares).

    Args:
      params: from :func:`dispgns.init_params`.
      position_seq: ``(C, N, D)``, padding rows sanitised (:func:`sanitize`).
      radius: ``(N,)``, padding radii > 0.
      graph: from :func:`build_graph` on ``position_seq[-1]``.
    """
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    nodes = _standardized_nodes(position_seq, radius, norm, model_config)
    edges = features_lib.edge_features(position_seq, radius, graph.senders, graph.receivers)
    return apply_network(params["network"], nodes, edges, graph.senders, graph.receivers, model_config=model_config)


def network_output_batch(
    params: Params,
    position_seq: BatchWindow,
    radius: BatchRadii,
    graphs: Graph,
    *,
    model_config: ModelConfig,
    edge_budget: int | None = None,
) -> BatchFrame:
    """:func:`network_output` for ``B`` examples at once, as one disjoint graph.

    Merging the examples (rather than vmapping the network) keeps gathers
    and scatters plain and the per-edge matmuls large. Each example gets one
    extra dummy node that absorbs its unused edge slots, so receivers stay
    sorted and every index is in range (see :func:`dispgns.graph.merge_graphs`).

    Args:
      position_seq: ``(B, C, N, D)`` sanitised inputs; radius: ``(B, N)``.
      graphs: :class:`Graph` with ``(B, E)`` arrays (e.g. vmapped :func:`build_graph`).
      edge_budget: static total edge slots of the merged graph (``None``:
        ``B E``); the caller checks :func:`dispgns.graph.merged_edge_count` against it.

    Returns:
      ``(B, N, D)`` standardised network output.
    """
    c = model_config
    b, steps, n, dim = position_seq.shape
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    nodes = jax.vmap(lambda x, a: _standardized_nodes(x, a, norm, c))(position_seq, radius)
    nodes = jnp.concatenate([nodes, jnp.zeros((b, 1, nodes.shape[-1]), nodes.dtype)], axis=1)
    senders, receivers = graph_lib.merge_graphs(graphs, n, edge_budget)
    # Edge features on the merged node arrays (dummy nodes: position 0, radius 1: finite features).
    flat_x = jnp.concatenate([position_seq, jnp.zeros((b, steps, 1, dim), position_seq.dtype)], axis=2)
    flat_x = jnp.moveaxis(flat_x, 1, 0).reshape(steps, b * (n + 1), dim)
    flat_a = jnp.concatenate([radius, jnp.ones((b, 1), radius.dtype)], axis=1).reshape(b * (n + 1))
    edges = features_lib.edge_features(flat_x, flat_a, senders, receivers)
    out = apply_network(params["network"], nodes.reshape(b * (n + 1), -1), edges, senders, receivers, model_config=c)
    return out.reshape(b, n + 1, -1)[:, :n]


def acceleration_from_output(params: Params, output: Frame, radius: Radii) -> Frame:
    """De-standardise the network output: ``(y * std + mean) * a_i``, ``(N, D)`` in normalised units / frame^2."""
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    return (output * norm["acceleration_std"] + norm["acceleration_mean"]) * radius[:, None]


@functools.cache
def floor_symmetries(dim: int) -> tuple[tuple[tuple[int, ...], tuple[float, ...]], ...]:
    """The symmetries of a square box floor: signed permutations of the horizontal axes, the vertical kept.

    Element ``(perm, signs)`` maps a vector ``v`` ``(..., D)`` to ``g(v)[..., d] = signs[d] *
    v[..., perm[d]]``: exact in floating point (swaps and sign changes only). The identity comes
    first. ``D = 3``: the 8 symmetries of the square (4 quarter turns about the vertical, each
    with or without a mirror image); ``D = 2``: the identity and the mirror image in ``x``.
    """
    import itertools

    if dim < 2:
        raise ValueError(f"floor_symmetries needs dim >= 2 (the last axis is vertical), got {dim}")
    out = []
    for perm in itertools.permutations(range(dim - 1)):
        for signs in itertools.product((1.0, -1.0), repeat=dim - 1):
            out.append((tuple(perm) + (dim - 1,), tuple(signs) + (1.0,)))
    return tuple(out)


def _transform(v, perm, signs):
    return v[..., list(perm)] * jnp.asarray(signs, v.dtype)


def _untransform(w, perm, signs):
    """The inverse of :func:`_transform`: ``_untransform(_transform(v, g), g) == v``."""
    return (w * jnp.asarray(signs, w.dtype))[..., list(np.argsort(perm))]


def _symmetrized(params, x, a, graphs, model_config: ModelConfig, edge_budget: int | None = None):
    """``mean_g g^-1 acc(g x)`` over :func:`floor_symmetries`, ``(B, N, D)``, for sanitised ``x`` ``(B, C, N, D)``.

    The graph is not rebuilt: the symmetries keep every distance, so ``x``'s graph is every ``g x``'s
    graph. The ``G B`` inputs are evaluated as one disjoint graph (:func:`network_output_batch`), as a
    training batch is: cheaper on a CPU than vmapping the network over the ``G`` copies.
    """
    group = floor_symmetries(model_config.dim)
    g, b = len(group), x.shape[0]
    moved = jnp.concatenate([_transform(x, p, s) for p, s in group])  # (G B, C, N, D), symmetry-major
    radius = jnp.tile(a, (g, 1))
    copies = jax.tree_util.tree_map(lambda t: jnp.tile(t, (g,) + (1,) * (t.ndim - 1)), graphs)
    budget = None if edge_budget is None else g * edge_budget
    output = network_output_batch(params, moved, radius, copies, model_config=model_config, edge_budget=budget)
    acc = jax.vmap(lambda y, r: acceleration_from_output(params, y, r))(output, radius).reshape((g, b) + x.shape[2:])
    return sum(_untransform(acc[k], p, s) for k, (p, s) in enumerate(group)) / g


def _constrain(position, radius, model_config: ModelConfig):
    """``position`` ``(..., N, D)`` moved onto the wall contact positions where beyond them (if asked)."""
    if not model_config.keep_inside_box:
        return position
    b = graph_lib.bounds_array(model_config.bounds, position.dtype)
    a = jnp.asarray(radius, position.dtype)[..., None]
    return jnp.clip(position, b[:, 0] + a, b[:, 1] - a)


def next_position_batch(
    position_seq: BatchWindow,
    acceleration: BatchFrame,
    radius: BatchRadii,
    mask: BatchMask,
    *,
    model_config: ModelConfig,
) -> BatchFrame:
    """The frame after ``B`` windows: ``x + (x - x_prev) + acc`` (pure, differentiable).

    Args:
      position_seq: ``(B, C, N, D)`` positions (normalised units).
      acceleration: ``(B, N, D)`` per frame^2 (normalised units), e.g.
        :func:`acceleration_from_output`; padding rows are ignored.
      radius, mask: ``(B, N)``; padding particles stay where they are.
      model_config: static; with ``keep_inside_box`` a particle beyond its
        wall contact position is moved back onto it.

    Returns:
      ``(B, N, D)`` next positions.
    """
    acc = jnp.where(mask[..., None], acceleration, 0.0).astype(position_seq.dtype)
    last = position_seq[:, -1]
    moved = _constrain(last + (last - position_seq[:, -2]) + acc, radius, model_config)
    return jnp.where(mask[..., None], moved, last)


def _poisoned(x, overflow):
    """``x`` with NaN where ``overflow`` (broadcast over trailing axes): never silently wrong."""
    flag = jnp.reshape(overflow, jnp.shape(overflow) + (1,) * (x.ndim - jnp.ndim(overflow)))
    return jnp.where(flag, jnp.asarray(jnp.nan, x.dtype), x)


def _inputs(position_seq, radius, mask):
    position_seq = jnp.asarray(position_seq)
    if not jnp.issubdtype(position_seq.dtype, jnp.floating):
        position_seq = position_seq.astype(jnp.float32)
    radius = jnp.asarray(radius, position_seq.dtype)
    mask = jnp.ones(radius.shape, bool) if mask is None else jnp.asarray(mask, bool)
    return position_seq, radius, mask


# ----------------------------------------------------------------------------- pure cores


def predict_step(
    params: Params,
    position_seq: PositionWindow,
    radius: Radii,
    *,
    model_config: ModelConfig,
    capacity: GraphCapacity | int,
    mask: ParticleMask | None = None,
) -> PredictedStep:
    """One learned step with a fixed graph capacity (pure: ``jit``, ``vmap``, ``grad``, ``lax.scan``).

    Args:
      params: ``{"network", "normalization"}`` from :func:`dispgns.init_params`.
      position_seq: ``(C, N, D)`` last ``C`` positions, oldest first (normalised units).
      radius: ``(N,)`` radii (normalised units, > 0 for real particles).
      model_config: static :class:`ModelConfig`.
      capacity: static :class:`GraphCapacity` (or an int: ordered pairs, all-pairs search).
      mask: optional ``(N,)`` bool, ``False`` for padding particles.

    Returns:
      :class:`PredictedStep`; with ``overflow`` True the graph missed edges and
      ``acceleration`` and ``position`` are NaN.
    """
    capacity = as_capacity(capacity)
    position_seq, radius, mask = _inputs(position_seq, radius, mask)
    x, a = sanitize(position_seq, radius, mask, model_config)
    graph = build_graph(x[-1], mask, capacity, model_config)
    if model_config.symmetrize:
        one = jax.tree_util.tree_map(lambda t: t[None], graph)
        acc = _symmetrized(params, x[None], a[None], one, model_config)[0]
    else:
        acc = acceleration_from_output(params, network_output(params, x, a, graph, model_config=model_config), a)
    acc = jnp.where(mask[:, None], acc, 0.0).astype(position_seq.dtype)
    last = position_seq[-1]
    velocity = last - position_seq[-2] + acc
    nxt = jnp.where(mask[:, None], _constrain(last + velocity, radius, model_config), last)
    return PredictedStep(_poisoned(acc, graph.overflow), _poisoned(nxt, graph.overflow), graph.overflow)


def predict_step_batch(
    params: Params,
    position_seq: BatchWindow,
    radius: BatchRadii,
    *,
    model_config: ModelConfig,
    capacity: GraphCapacity | int,
    mask: BatchMask | None = None,
    edge_budget: int | None = None,
) -> PredictedStep:
    """:func:`predict_step` for ``B`` trajectories at once, evaluated as one disjoint graph (pure).

    Args:
      position_seq: ``(B, C, N, D)``; radius, mask: ``(B, N)``.
      capacity: static, per trajectory.
      edge_budget: static total edge slots of the merged graph (see
        :func:`dispgns.graph.merge_graphs`); exceeding it sets every overflow flag.

    Returns:
      :class:`PredictedStep` with ``(B, N, D)`` arrays and ``overflow`` ``(B,)``.
    """
    capacity = as_capacity(capacity)
    position_seq, radius, mask = _inputs(position_seq, radius, mask)
    x, a = jax.vmap(lambda p, r, m: sanitize(p, r, m, model_config))(position_seq, radius, mask)
    graphs = jax.vmap(lambda p, m: build_graph(p, m, capacity, model_config))(x[:, -1], mask)
    if model_config.symmetrize:
        acc = _symmetrized(params, x, a, graphs, model_config, edge_budget)
    else:
        output = network_output_batch(params, x, a, graphs, model_config=model_config, edge_budget=edge_budget)
        acc = jax.vmap(lambda y, r: acceleration_from_output(params, y, r))(output, a)
    nxt = next_position_batch(position_seq, acc, radius, mask, model_config=model_config)
    overflow = graphs.overflow
    if edge_budget is not None:
        overflow = overflow | (graph_lib.merged_edge_count(graphs, x.shape[2]) > edge_budget)
    return PredictedStep(_poisoned(acc, overflow), _poisoned(nxt, overflow), overflow)


def rollout_scan(
    params: Params,
    initial_positions: PositionWindow,
    radius: Radii,
    n_steps: int,
    *,
    model_config: ModelConfig,
    capacity: GraphCapacity | int,
    mask: ParticleMask | None = None,
) -> tuple[Positions, Flag]:
    """Autoregressive rollout as one ``lax.scan`` with a fixed graph capacity (pure).

    Works under ``jit``, ``vmap`` (over trajectories of equal padded size) and
    ``grad`` (with respect to ``params``, positions and radii). The graph is
    rebuilt at every step; it cannot grow here, so size ``capacity`` for the
    whole rollout (``fit_capacity(truth, model_config)`` when a ground truth
    exists, else ``fit_capacity(initial_positions[-1], model_config, margin=0.5)``)
    and check the flags.

    Args:
      initial_positions: ``(C, N, D)`` first ``C`` frames (normalised units).
      radius: ``(N,)``; mask: optional ``(N,)`` bool.
      n_steps: static, frames to predict.
      capacity: static :class:`GraphCapacity` (or an int).

    Returns:
      ``(positions (n_steps, N, D), overflow (n_steps,) bool)``: frames ``C ..
      C + n_steps - 1``; ``overflow[k]`` says some step up to ``k`` overflowed,
      and every frame from the first overflowing step on is NaN.
    """
    capacity = as_capacity(capacity)
    window, radius, mask = _inputs(initial_positions, radius, mask)

    def body(carry, _):
        window, overflow = carry
        step = predict_step(params, window, radius, model_config=model_config, capacity=capacity, mask=mask)
        overflow = overflow | step.overflow
        return (jnp.concatenate([window[1:], step.position[None]], axis=0), overflow), (step.position, overflow)

    _, (positions, flags) = lax.scan(body, (window, jnp.zeros((), bool)), None, length=n_steps)
    return _poisoned(positions, flags), flags


# ----------------------------------------------------------------------------- host conveniences


def fit_capacity(
    position: _AnyFrames, model_config: ModelConfig, *, mask: _AnyMask | None = None, margin: float = 0.05
) -> GraphCapacity:
    """:func:`dispgns.graph.fit_capacity` with the model's radius and box: fits every frame of ``position``.

    Args:
      position: concrete ``(..., N, D)`` positions (normalised units).
      mask: ``None`` or bool broadcastable to ``position.shape[:-1]``.
      margin: relative head-room (``0.5`` for a rollout under ``jit`` from its initial frames).
    """
    return graph_lib.fit_capacity(
        position,
        mask,
        connectivity_radius=model_config.connectivity_radius,
        bounds=model_config.bounds,
        margin=margin,
    )


def _grower(model_config: ModelConfig, mask):
    """``(capacity, window) -> larger capacity`` fitted at the window's last frame (``axis``: frames)."""

    def grow(capacity, window):
        last = np.asarray(window)[..., -1, :, :]
        return graph_lib.grow_capacity(
            capacity,
            last.shape[-2],
            last,
            mask,
            connectivity_radius=model_config.connectivity_radius,
            bounds=model_config.bounds,
        )

    return grow


def _host_inputs(
    position_seq, radius, mask, model_config: ModelConfig, *, batched: bool, pure: str, validate: bool = True
):
    """Concrete, validated inputs of a host convenience: float positions, radius in their dtype, bool mask."""
    x = host_array(position_seq, "positions", pure=pure)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float32)
    c, d = model_config.input_sequence_length, model_config.dim
    lead = "(B, " if batched else "("
    if x.ndim != 3 + batched or x.shape[batched] != c or x.shape[-1] != d:
        raise ValueError(
            f"positions must have shape {lead}{c}, N, {d}) (C = input_sequence_length = {c}, D = dim), got {x.shape}"
        )
    n = x.shape[-2]
    if n == 0:
        raise ValueError(f"positions hold no particles: shape {x.shape}")
    particles = x.shape[:1] + (n,) if batched else (n,)
    a = host_array(radius, "radius", pure=pure).astype(x.dtype)
    if a.shape != particles:
        raise ValueError(f"radius must have shape {particles}, got {a.shape}")
    m = np.ones(particles, bool) if mask is None else host_array(mask, "mask", pure=pure).astype(bool)
    if m.shape != particles:
        raise ValueError(f"mask must have shape {particles}, got {m.shape}")
    if validate:
        # Cheap host checks (dispgns.validation): the pure cores would return NaN or plausible nonsense.
        check_particles(
            x,
            a,
            mask=m,
            bounds=model_config.bounds,
            box="the model's bounds",
            position_name="positions",
            # The network takes any configuration (overlaps only change its features); the physics does not.
            overlaps=False,
            model_connectivity_radius=model_config.connectivity_radius,
        )
    return x, a, m


def _check_steps(n_steps):
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}")


def _predict_once(params, position_seq, radius, mask, capacity, model_config, compiler_options) -> PredictedStep:
    x, a, m = _host_inputs(position_seq, radius, mask, model_config, batched=False, pure="dispgns.predict_step")
    capacity = fit_capacity(x[-1], model_config, mask=m) if capacity is None else as_capacity(capacity)
    step = jitted(predict_step, compiler_options, static_argnames=("model_config", "capacity"))

    def attempt(window, capacity, _):
        out = step(params, window, a, model_config=model_config, capacity=capacity, mask=m)
        if bool(out.overflow):
            return Attempt(window, None, 0, True)
        return Attempt(window, out, 1, False)

    _, (out,), _ = drive(attempt, x, capacity, _grower(model_config, m))
    return out


def predict_acceleration(
    params: Params,
    position_seq: PositionWindow,
    radius: Radii,
    *,
    model_config: ModelConfig,
    mask: ParticleMask | None = None,
    capacity: GraphCapacity | int | None = None,
    compiler_options: Mapping[str, Any] | None = None,
) -> Frame:
    """Predicted acceleration of every particle for one step (host; see :func:`predict_step` for the pure core).

    Args:
      params: ``{"network", "normalization"}`` from :func:`dispgns.init_params`.
      position_seq: concrete ``(C, N, D)`` last ``C`` positions, oldest first (normalised units).
      radius: ``(N,)`` radii (normalised units).
      model_config: :class:`ModelConfig`.
      mask: optional ``(N,)`` bool, ``False`` for padding particles.
      capacity: the first graph capacity to try (``None``: fitted to the positions); grown if too small.
      compiler_options: XLA options for the compiled step (e.g.
        :func:`dispgns.tuning.network_compiler_options`).

    Returns:
      ``(N, D)`` acceleration in normalised units per frame^2 (the change of
      velocity over the next frame); zero for padding particles.
    """
    return _predict_once(params, position_seq, radius, mask, capacity, model_config, compiler_options).acceleration


def predict_position(
    params: Params,
    position_seq: PositionWindow,
    radius: Radii,
    *,
    model_config: ModelConfig,
    mask: ParticleMask | None = None,
    capacity: GraphCapacity | int | None = None,
    compiler_options: Mapping[str, Any] | None = None,
) -> Frame:
    """Predicted next position ``x_t + (x_t - x_{t-1}) + acc``, ``(N, D)`` (host).

    Arguments as :func:`predict_acceleration`; padding particles keep their last position.
    """
    return _predict_once(params, position_seq, radius, mask, capacity, model_config, compiler_options).position


def steps_until_overflow(
    step: Callable[[_Window], tuple[_Frames, Flag]], window: _Window, limit: Count, *, length: int, axis: int
) -> tuple[_Window, _StepPositions, Count, Flag]:
    """Up to ``limit`` steps of ``step(window) -> (next frame, overflow ())``, stopping after an overflowing one.

    ``window`` holds the last ``C`` frames along ``axis`` (0 for one
    trajectory ``(C, N, D)``, 1 for a batch ``(B, C, N, D)``); ``limit`` is
    traced (at most the static ``length``), so one compilation serves every
    chunk of a host loop. Pure (a ``lax.while_loop``).

    Returns:
      ``(window, positions (length, ...), steps taken (), overflow ())``; when
      ``overflow`` is True the last step taken overflowed: its position is
      wrong and ``window`` is the one before it, to go on from. Positions
      beyond the steps taken are zeros.
    """
    frame_shape = window.shape[:axis] + window.shape[axis + 1 :]
    limit = jnp.minimum(limit, length)

    def cond(carry):
        taken, _, _, overflow = carry
        return (taken < limit) & ~overflow

    def body(carry):
        taken, window, positions, _ = carry
        nxt, overflow = step(window)
        positions = lax.dynamic_update_index_in_dim(positions, nxt, taken, 0)
        shifted = jnp.concatenate([lax.slice_in_dim(window, 1, None, axis=axis), jnp.expand_dims(nxt, axis)], axis=axis)
        return taken + 1, jnp.where(overflow, window, shifted), positions, overflow

    start = (jnp.zeros((), jnp.int32), window, jnp.zeros((length,) + frame_shape, window.dtype), jnp.zeros((), bool))
    taken, window, positions, overflow = lax.while_loop(cond, body, start)
    return window, positions, taken, overflow


def _rollout_chunk(params, window, radius, mask, limit, *, length: int, capacity: GraphCapacity, model_config):
    """Up to ``limit`` steps of one trajectory, stopping at an overflow (see :func:`steps_until_overflow`)."""

    def step(w):
        out = predict_step(params, w, radius, model_config=model_config, capacity=capacity, mask=mask)
        return out.position, out.overflow

    return steps_until_overflow(step, window, limit, length=length, axis=0)


def _rollout_chunk_batch(
    params, windows, radius, mask, limit, *, length: int, capacity: GraphCapacity, model_config, axis_name=None
):
    """:func:`_rollout_chunk` of ``B`` windows ``(B, C, N, D)``; positions ``(length, B, N, D)``.

    With ``axis_name`` (inside ``shard_map``, the trajectories split over a
    mesh axis) an overflow on any device stops every device at that step.
    """

    def step(w):
        out = predict_step_batch(params, w, radius, model_config=model_config, capacity=capacity, mask=mask)
        overflow = jnp.any(out.overflow)
        if axis_name is not None:
            overflow = lax.psum(overflow.astype(jnp.int32), axis_name) > 0
        return out.position, overflow

    return steps_until_overflow(step, windows, limit, length=length, axis=1)


def _sharded_chunk_batch(params, windows, radius, mask, limit, *, length: int, capacity, model_config, mesh):
    """:func:`_rollout_chunk_batch` with the trajectories split over the 1-D ``mesh``'s axis (one per device)."""
    (axis,) = mesh.axis_names
    chunk = functools.partial(
        _rollout_chunk_batch, length=length, capacity=capacity, model_config=model_config, axis_name=axis
    )
    split = jax.sharding.PartitionSpec(axis)
    whole = jax.sharding.PartitionSpec()
    sharded = jax.shard_map(
        chunk,
        mesh=mesh,
        in_specs=(whole, split, split, split, whole),
        out_specs=(split, jax.sharding.PartitionSpec(None, axis), whole, whole),
        check_vma=False,  # the overflow flags are summed over the axis in the step itself
    )
    return sharded(params, windows, radius, mask, limit)


def _host_rollout(params, initial_positions, radius, n_steps, model_config: ModelConfig, settings, *, batched: bool):
    """The host loop of :func:`rollout` and :func:`rollout_batch`: compiled chunks driven by :func:`drive`.

    ``settings``: their ``(mask, capacity, chunk_size, compiler_options,
    progress, mesh)``. Returns positions ``(n_steps, ...)`` (steps first, also for a batch).
    """
    mask, capacity, chunk_size, compiler_options, progress, mesh = settings
    pure = "jax.vmap(dispgns.rollout_scan)" if batched else "dispgns.rollout_scan"
    window, a, m = _host_inputs(initial_positions, radius, mask, model_config, batched=batched, pure=pure)
    _check_steps(n_steps)
    if capacity is None:
        capacity = fit_capacity(window[..., -1, :, :], model_config, mask=m, margin=0.1)
    length = math.ceil(n_steps / math.ceil(n_steps / max(1, chunk_size)))
    static = {"length": length, "model_config": model_config}
    if mesh is not None:
        if window.shape[0] % mesh.devices.size:
            raise ValueError(
                f"{window.shape[0]} trajectories do not split over the mesh's {mesh.devices.size} devices: "
                "pad the batch to a multiple of the device count (e.g. with repeats)"
            )
        chunk, static["mesh"] = _sharded_chunk_batch, mesh
        # The trajectories split over the mesh's axis, the parameters on every device.
        split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(*mesh.axis_names))
        window, a, m = (jax.device_put(x, split) for x in (window, a, m))
        params = jax.device_put(params, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    else:
        chunk = _rollout_chunk_batch if batched else _rollout_chunk
    run_chunk = jitted(chunk, compiler_options, static_argnames=(*static, "capacity"))

    def attempt(window, capacity, remaining):
        limit = jnp.int32(min(length, remaining))
        new_window, positions, taken, overflow = run_chunk(params, window, a, m, limit, capacity=capacity, **static)
        taken, overflow = int(taken), bool(overflow)
        kept = taken - 1 if overflow else taken
        # After an overflow the window is the one before the overflowing step: go on from it.
        return Attempt(new_window, positions[:kept] if kept else None, kept, overflow)

    _, chunks, _ = drive(
        attempt, window, as_capacity(capacity), _grower(model_config, m), total=n_steps, progress=progress
    )
    return chunks[0] if len(chunks) == 1 else jnp.concatenate(chunks, axis=0)


def rollout(
    params: Params,
    initial_positions: PositionWindow,
    radius: Radii,
    n_steps: int,
    *,
    model_config: ModelConfig,
    mask: ParticleMask | None = None,
    capacity: GraphCapacity | int | None = None,
    chunk_size: int = 50,
    compiler_options: Mapping[str, Any] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Positions:
    """Autoregressive rollout of ``n_steps`` frames (host; :func:`rollout_scan` is the pure core).

    The steps run in compiled chunks of about ``chunk_size``; a chunk stops at
    a step whose graph overflowed, the capacity grows and that step is
    recomputed, so the result is exactly that of a graph without any size
    limit. Capacities sized here land on the ladder of
    :mod:`dispgns.capacity`, so rollouts of other trajectories mostly reuse
    the programs already compiled.

    Args:
      params: from :func:`dispgns.init_params`.
      initial_positions: concrete ``(C, N, D)`` first ``C`` frames (normalised units).
      radius: ``(N,)`` radii (normalised units).
      n_steps: number of frames to predict.
      model_config: :class:`ModelConfig`.
      mask: optional ``(N,)`` bool, ``False`` for padding particles.
      capacity: the first graph capacity (``None``: fitted to the initial frame with 10 % head-room).
      chunk_size: steps per compiled chunk.
      compiler_options: XLA options for the chunks (e.g.
        :func:`dispgns.tuning.network_compiler_options`).
      progress: ``progress(done_steps)`` whenever steps are kept.

    Returns:
      ``(n_steps, N, D)`` predicted positions for frames ``C .. C + n_steps - 1``.
    """
    settings = (mask, capacity, chunk_size, compiler_options, progress, None)
    return _host_rollout(params, initial_positions, radius, n_steps, model_config, settings, batched=False)


def rollout_batch(
    params: Params,
    initial_positions: BatchWindow,
    radius: BatchRadii,
    n_steps: int,
    *,
    model_config: ModelConfig,
    mask: BatchMask | None = None,
    capacity: GraphCapacity | int | None = None,
    chunk_size: int = 50,
    compiler_options: Mapping[str, Any] | None = None,
    progress: Callable[[int], None] | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> BatchPositions:
    """Rollouts of ``B`` trajectories of equal padded size in one compiled program per chunk (host).

    The same result as :func:`rollout` of each trajectory (padding never
    changes a real particle), computed on one disjoint graph of all ``B``
    trajectories per step, with the same overflow handling: after an
    overflow in any trajectory the capacity grows and every trajectory
    redoes that step. Under ``jit`` use ``jax.vmap(rollout_scan)``.

    Args:
      initial_positions: concrete ``(B, C, N, D)`` first ``C`` frames
        (normalised units), padding rows anywhere (masked).
      radius: ``(B, N)`` radii. mask: optional ``(B, N)`` bool.
      capacity: the first graph capacity per trajectory (``None``: fitted to
        the initial frames of every trajectory).
      mesh: a 1-D ``jax.sharding.Mesh`` of this process's devices to split the
        trajectories over (``B`` a multiple of its size): each device rolls out
        its share as one disjoint graph, and an overflow on any device grows
        the capacity for all. ``None``: one device.
      Other arguments as :func:`rollout`.

    Returns:
      ``(B, n_steps, N, D)`` predicted positions for frames ``C .. C + n_steps - 1``.
    """
    settings = (mask, capacity, chunk_size, compiler_options, progress, mesh)
    positions = _host_rollout(params, initial_positions, radius, n_steps, model_config, settings, batched=True)
    return jnp.moveaxis(positions, 0, 1)
