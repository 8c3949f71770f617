"""The learned simulator: one-step predictions and autoregressive rollouts.

Units are normalised box units (positions divided by the half box size ``L``,
the box is ``model_config.bounds``, by default ``[-1, 1]^D``) and frames (one
frame = one time unit, 1.5 ms in the paper's data).

One step, for the last ``C`` positions ``x_{t-C+1} .. x_t`` of every particle:

1. radius graph at ``x_t`` (:mod:`dispgns.graph`), node and edge features
   (:mod:`dispgns.features`), velocity features standardised with
   ``params["normalization"]``;
2. network output ``y`` (:mod:`dispgns.model`), acceleration
   ``acc = (y * acceleration_std + acceleration_mean) * a_i``;
3. ``v_new = (x_t - x_{t-1}) + acc``, ``x_new = x_t + v_new``.

Graph capacity. Every function takes ``capacity`` (a
:class:`~dispgns.graph.GraphCapacity` or an int, the number of ordered pairs
``s != r`` the graph can hold). Called with concrete arrays, ``None`` sizes it
from the data and an overflow grows it and recomputes; nothing is ever
dropped. Sizes chosen here are rounded up to a fixed ladder of capacities
(:func:`dispgns.graph.on_ladder`, rungs ~19 % apart), so that rollouts of
other trajectories, and steps on other positions, mostly reuse the programs
already compiled. Under a JAX transformation (``jit``, ``vmap``, ``grad``) sizes
cannot change: ``capacity`` is then used as given; ``None`` sizes it from the
positions if they are concrete (e.g. only ``params`` traced) and otherwise
means all ``N (N - 1)`` pairs (exact but slow). Any overflow poisons the
affected outputs with NaN instead of silently dropping edges. The default
candidate search (all pairs or jax-md cell list) is chosen by particle count
(:data:`dispgns.graph.CELL_LIST_MIN_PARTICLES`); an explicit
``GraphCapacity(edges, cell)`` chooses it.

Padding particles (``mask == False``) never influence real ones; their
outputs are zero accelerations and unchanged positions.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from dispgns import features as features_lib
from dispgns import graph as graph_lib
from dispgns.graph import Graph, GraphCapacity
from dispgns.model import ModelConfig, apply_network
from dispgns.runtime import network_jit


def _is_traced(*trees) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))


def _as_capacity(capacity) -> GraphCapacity | None:
    if capacity is None or isinstance(capacity, GraphCapacity):
        return capacity
    return GraphCapacity(edges=int(capacity))


def _keep_concrete(x, dtype):
    """``x`` as an array of ``dtype``, concrete if ``x`` is.

    Inside a user's ``jit`` every ``jnp`` operation on a closed-over
    constant returns a tracer, and a graph can only be sized from concrete
    positions: concrete inputs are therefore converted with numpy.
    """
    if isinstance(x, jax.core.Tracer):
        return jnp.asarray(x, dtype)
    if isinstance(x, jax.Array) and x.dtype == dtype:
        return x
    return np.asarray(x, dtype)


def _float_dtype(x):
    dtype = x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype
    return jax.dtypes.canonicalize_dtype(dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.float32)


def _check(position, radius, mask, model_config: ModelConfig, *, leading: int):
    """Validate shapes; return arrays (float positions, radius in their dtype, bool mask), concrete if given so."""
    position = _keep_concrete(position, _float_dtype(position))
    radius = _keep_concrete(radius, position.dtype)
    c, d = model_config.input_sequence_length, model_config.dim
    if position.ndim != 3 or position.shape[0] != leading or position.shape[2] != d:
        raise ValueError(
            f"positions must have shape ({leading}, N, {d}) (C = input_sequence_length = {c}, "
            f"D = dim), got {position.shape}"
        )
    n = position.shape[1]
    if radius.shape != (n,):
        raise ValueError(f"radius must have shape ({n},), got {radius.shape}")
    if n == 0:
        raise ValueError(f"positions hold no particles: shape {position.shape}")
    # numpy, not jnp: a default mask must stay concrete inside a user's jit.
    mask = np.ones((n,), bool) if mask is None else _keep_concrete(mask, np.dtype(bool))
    if mask.shape != (n,):
        raise ValueError(f"mask must have shape ({n},), got {mask.shape}")
    _check_radius(radius, mask)
    return position, radius, mask


def _check_radius(radius, mask):
    """Radii of real particles must be finite and > 0 (they divide features and accelerations); checked when concrete."""
    if _is_traced(radius, mask):
        return
    real = np.asarray(radius)[np.asarray(mask, bool)]
    bad = ~(np.isfinite(real) & (real > 0))
    if np.any(bad):
        raise ValueError(
            f"radius must be finite and > 0 for every real particle; got {real[bad][:5].tolist()} "
            f"({int(bad.sum())} bad value(s))"
        )


def _check_steps(n_steps):
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}")


def sanitize(position_seq: jnp.ndarray, radius: jnp.ndarray, mask: jnp.ndarray, model_config: ModelConfig):
    """Padding rows replaced by parked positions and unit radii (finite features, no edges to real particles)."""
    position_seq = graph_lib.park_padding(
        position_seq, mask, connectivity_radius=model_config.connectivity_radius, bounds=model_config.bounds
    )
    radius = jnp.where(mask, radius, jnp.ones_like(radius))
    return position_seq, radius


def build_graph(position: jnp.ndarray, mask: jnp.ndarray, capacity: GraphCapacity, model_config: ModelConfig) -> Graph:
    """The radius graph of ``position`` ``(N, D)`` for ``model_config`` (see :func:`dispgns.graph.radius_graph`)."""
    return graph_lib.radius_graph(
        position,
        mask,
        connectivity_radius=model_config.connectivity_radius,
        capacity=capacity,
        bounds=model_config.bounds,
    )


def network_output(
    params, position_seq: jnp.ndarray, radius: jnp.ndarray, graph: Graph, *, model_config: ModelConfig
) -> jnp.ndarray:
    """Standardised network output ``(N, D)`` for sanitised inputs and a graph (what the loss compares).

    Args:
      params: from :func:`dispgns.init_params`.
      position_seq: ``(C, N, D)``, padding rows sanitised (:func:`sanitize`).
      radius: ``(N,)``, padding radii > 0.
      graph: from :func:`build_graph` on ``position_seq[-1]``.
    """
    c = model_config
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    nodes = _standardized_nodes(position_seq, radius, norm, c)
    edges = features_lib.edge_features(position_seq, radius, graph.senders, graph.receivers)
    return apply_network(params["network"], nodes, edges, graph.senders, graph.receivers, model_config=c)


def merged_edge_count(graphs: Graph, n: int) -> jnp.ndarray:
    """Number of real edges (self-loops included) of ``B`` graphs ``(B, E)`` over ``n`` node slots: ``()`` int32."""
    return jnp.sum(graphs.receivers < n, dtype=jnp.int32)


def merge_graphs(graphs: Graph, n: int, edge_budget: int | None = None):
    """``B`` graphs as one disjoint graph over ``B (n + 1)`` nodes (one dummy node per example).

    Example ``b``'s node ``i`` becomes node ``b (n + 1) + i``; unused edge
    slots point at the example's dummy node ``b (n + 1) + n``. With an
    ``edge_budget`` the real edges are moved to the front of a list of that
    static length (in order, so receivers stay sorted) and the rest of it
    points at the last dummy node: the per-edge work then scales with the
    edges the batch has, not with ``B`` times the largest example's capacity.

    Args:
      graphs: :class:`Graph` with ``(B, E)`` arrays.
      n: node slots per example.
      edge_budget: static total edge slots, or ``None`` (``B E`` slots, no
        compaction).

    Returns:
      ``(senders, receivers)``, each ``(B E,)`` or ``(edge_budget,)`` int32.
      Edges beyond ``edge_budget`` are dropped: check
      :func:`merged_edge_count` ``<= edge_budget`` (the training step does).
    """
    b, e = graphs.senders.shape
    offset = (jnp.arange(b, dtype=jnp.int32) * (n + 1))[:, None]
    senders = (jnp.minimum(graphs.senders, n) + offset).reshape(b * e)
    receivers = (jnp.minimum(graphs.receivers, n) + offset).reshape(b * e)
    if edge_budget is None:
        return senders, receivers
    real = (graphs.receivers < n).reshape(b * e)
    slot = jnp.where(real, jnp.cumsum(real, dtype=jnp.int32) - 1, edge_budget)
    dummy = jnp.full((edge_budget,), b * (n + 1) - 1, jnp.int32)
    compact = lambda values: dummy.at[slot].set(values, mode="drop", indices_are_sorted=True)
    return compact(senders), compact(receivers)


def network_output_batch(
    params,
    position_seq: jnp.ndarray,
    radius: jnp.ndarray,
    graphs: Graph,
    *,
    model_config: ModelConfig,
    edge_budget: int | None = None,
) -> jnp.ndarray:
    """:func:`network_output` for ``B`` examples at once, as one disjoint graph.

    Merging the examples (rather than vmapping the network) keeps gathers
    and scatters plain and the per-edge matmuls large. Each example gets one
    extra dummy node that absorbs its unused edge slots, so receivers stay
    sorted and every index is in range (see :func:`merge_graphs`).

    Args:
      position_seq: ``(B, C, N, D)`` sanitised inputs; radius: ``(B, N)``.
      graphs: :class:`Graph` with ``(B, E)`` arrays (e.g. vmapped :func:`build_graph`).
      edge_budget: static total edge slots of the merged graph (``None``:
        ``B E``); the caller must check :func:`merged_edge_count` against it.

    Returns:
      ``(B, N, D)`` standardised network output.
    """
    c = model_config
    b, steps, n, dim = position_seq.shape
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    nodes = jax.vmap(lambda x, a: _standardized_nodes(x, a, norm, c))(position_seq, radius)
    nodes = jnp.concatenate([nodes, jnp.zeros((b, 1, nodes.shape[-1]), nodes.dtype)], axis=1)
    senders, receivers = merge_graphs(graphs, n, edge_budget)
    # Edge features on the merged node arrays (dummy nodes: position 0, radius 1: finite features).
    flat_x = jnp.concatenate([position_seq, jnp.zeros((b, steps, 1, dim), position_seq.dtype)], axis=2)
    flat_x = jnp.moveaxis(flat_x, 1, 0).reshape(steps, b * (n + 1), dim)
    flat_a = jnp.concatenate([radius, jnp.ones((b, 1), radius.dtype)], axis=1).reshape(b * (n + 1))
    edges = features_lib.edge_features(flat_x, flat_a, senders, receivers)
    out = apply_network(params["network"], nodes.reshape(b * (n + 1), -1), edges, senders, receivers, model_config=c)
    return out.reshape(b, n + 1, -1)[:, :n]


def _standardized_nodes(position_seq, radius, norm, c: ModelConfig):
    nodes = features_lib.node_features(position_seq, radius, bounds=c.bounds, boundary_clip=c.boundary_clip)
    n_vel = (c.input_sequence_length - 1) * c.dim
    mean = jnp.tile(norm["velocity_mean"], c.input_sequence_length - 1).astype(nodes.dtype)
    std = jnp.tile(norm["velocity_std"], c.input_sequence_length - 1).astype(nodes.dtype)
    return jnp.concatenate([(nodes[:, :n_vel] - mean) / std, nodes[:, n_vel:]], axis=-1)


def acceleration_from_output(params, output: jnp.ndarray, radius: jnp.ndarray) -> jnp.ndarray:
    """De-standardise the network output: ``(y * std + mean) * a_i``, ``(N, D)`` in box units / frame^2."""
    norm = jax.tree_util.tree_map(lax.stop_gradient, params["normalization"])
    return (output * norm["acceleration_std"] + norm["acceleration_mean"]) * radius[:, None]


def one_step(params, position_seq, radius, mask, capacity: GraphCapacity, model_config: ModelConfig):
    """One step with a fixed graph capacity (pure; no validation, no overflow handling).

    Args:
      position_seq: ``(C, N, D)``; radius: ``(N,)``; mask: ``(N,)`` bool.
      capacity: static :class:`GraphCapacity`; model_config: static.

    Returns:
      ``(acceleration (N, D), next position (N, D), overflow ())``; when
      ``overflow`` is True the graph missed edges and the outputs are wrong.
    """
    x, a = sanitize(position_seq, radius, mask, model_config)
    graph = build_graph(x[-1], mask, capacity, model_config)
    acc = acceleration_from_output(params, network_output(params, x, a, graph, model_config=model_config), a)
    acc = jnp.where(mask[:, None], acc, 0.0).astype(position_seq.dtype)
    last = position_seq[-1]
    velocity = last - position_seq[-2] + acc
    next_position = jnp.where(mask[:, None], _constrain(last + velocity, radius, model_config), last)
    return acc, next_position, graph.overflow


def _constrain(position, radius, model_config: ModelConfig):
    """``position`` ``(..., N, D)`` moved onto the wall contact positions where beyond them (if asked)."""
    if not model_config.keep_inside_box:
        return position
    b = graph_lib.bounds_array(model_config.bounds, position.dtype)
    a = jnp.asarray(radius, position.dtype)[..., None]
    return jnp.clip(position, b[:, 0] + a, b[:, 1] - a)


@functools.partial(network_jit, static_argnames=("capacity", "model_config"))
def _step_jit(params, position_seq, radius, mask, *, capacity, model_config):
    return one_step(params, position_seq, radius, mask, capacity, model_config)


def _full_capacity(n: int) -> GraphCapacity:
    return GraphCapacity(edges=n * (n - 1))


def _predict(params, position_seq, radius, mask, capacity, model_config):
    position_seq, radius, mask = _check(
        position_seq, radius, mask, model_config, leading=model_config.input_sequence_length
    )
    n = position_seq.shape[1]
    capacity = _as_capacity(capacity)
    if _is_traced(params, position_seq, radius, mask):
        # Under a transformation the graph size cannot adapt: size it from the
        # positions when they are concrete, else take all pairs.
        if capacity is None:
            capacity = (
                _full_capacity(n)
                if _is_traced(position_seq, mask)
                else _fitted(np.asarray(position_seq)[-1], mask, model_config)
            )
        acc, nxt, overflow = one_step(params, position_seq, radius, mask, capacity, model_config)
        poison = jnp.where(overflow, jnp.nan, 0.0).astype(acc.dtype)
        return acc + poison, nxt + poison
    if capacity is None:
        capacity = _fitted(position_seq[-1], mask, model_config)
    while True:
        acc, nxt, overflow = _step_jit(params, position_seq, radius, mask, capacity=capacity, model_config=model_config)
        if not bool(overflow):
            return acc, nxt
        capacity = _grown(capacity, position_seq[-1], mask, model_config)


def predict_acceleration(params, position_seq, radius, *, model_config: ModelConfig, mask=None, capacity=None):
    """Predicted acceleration of every particle for one step.

    Args:
      params: ``{"network", "normalization"}`` from :func:`dispgns.init_params`.
      position_seq: ``(C, N, D)`` last ``C`` positions, oldest first
        (normalised units).
      radius: ``(N,)`` radii (normalised units).
      model_config: static :class:`ModelConfig`.
      mask: optional ``(N,)`` bool, ``False`` for padding particles.
      capacity: optional graph capacity (see the module docstring).

    Returns:
      ``(N, D)`` acceleration in normalised units per frame^2 (the change of
      velocity over the next frame); zero for padding particles.
    """
    return _predict(params, position_seq, radius, mask, capacity, model_config)[0]


def predict_position(params, position_seq, radius, *, model_config: ModelConfig, mask=None, capacity=None):
    """Predicted next position ``x_t + (x_t - x_{t-1}) + acc``, ``(N, D)`` (arguments as :func:`predict_acceleration`).

    Padding particles keep their last position.
    """
    return _predict(params, position_seq, radius, mask, capacity, model_config)[1]


def _scan_steps(params, window, radius, mask, *, length: int, capacity: GraphCapacity, model_config: ModelConfig):
    """``length`` steps from ``window`` (C, N, D); returns (last window, positions (length, N, D), overflow)."""

    def body(carry, _):
        window, overflow = carry
        _, nxt, step_overflow = one_step(params, window, radius, mask, capacity, model_config)
        overflow = overflow | step_overflow
        window = jnp.concatenate([window[1:], nxt[None]], axis=0)
        return (window, overflow), (nxt, overflow)

    (window, _), (positions, flags) = lax.scan(body, (window, jnp.zeros((), bool)), None, length=length)
    return window, positions, flags


def _steps_until_overflow(step, window, limit, *, length: int, axis: int):
    """Up to ``limit`` steps of ``step(window) -> (next, overflow ())``, stopping after an overflowing one.

    ``window`` holds the last ``C`` frames along ``axis`` (0 for one
    trajectory ``(C, N, D)``, 1 for a batch ``(B, C, N, D)``); ``limit`` is
    traced (at most the static ``length``), so one compilation serves every
    chunk. ``step`` returns the next frame with the window's dtype.

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


@functools.partial(network_jit, static_argnames=("length", "capacity", "model_config"))
def _rollout_chunk(
    params, window, radius, mask, limit, *, length: int, capacity: GraphCapacity, model_config: ModelConfig
):
    """Up to ``limit`` steps of one trajectory, stopping at an overflow (see :func:`_steps_until_overflow`)."""
    step = lambda w: one_step(params, w, radius, mask, capacity, model_config)[1:]
    return _steps_until_overflow(step, window, limit, length=length, axis=0)


@functools.partial(network_jit, static_argnames=("length", "capacity", "model_config"))
def _rollout_chunk_batch(
    params, windows, radius, mask, limit, *, length: int, capacity: GraphCapacity, model_config: ModelConfig
):
    """:func:`_rollout_chunk` of ``B`` windows ``(B, C, N, D)``; positions ``(length, B, N, D)``."""

    def step(w):
        _, nxt, overflow = one_step_batch(params, w, radius, mask, capacity, model_config)
        return nxt, jnp.any(overflow)

    return _steps_until_overflow(step, windows, limit, length=length, axis=1)


def _roll_in_chunks(
    run_chunk, window, n_steps: int, chunk_size: int, capacity: GraphCapacity, grow, *, axis: int, progress=None
):
    """The host loop of the concrete rollouts: compiled chunks, capacity grown after an overflow.

    ``run_chunk(window, limit, length, capacity)`` is a ``_rollout_chunk*``
    call; ``grow(capacity, last frame)`` returns a larger capacity. A chunk
    stops at its first overflowing step, so only that step is computed
    again (with the larger graph). ``progress(done)`` is called whenever
    steps were kept. Returns positions ``(n_steps, ...)``.
    """
    n_chunks = math.ceil(n_steps / max(1, chunk_size))
    length = math.ceil(n_steps / n_chunks)
    chunks, done = [], 0
    while done < n_steps:
        limit = min(length, n_steps - done)
        new_window, positions, taken, overflow = run_chunk(window, jnp.int32(limit), length, capacity)
        taken, overflow = int(taken), bool(overflow)
        valid = taken - 1 if overflow else taken
        if valid:
            chunks.append(positions[:valid])
            done += valid
            if progress is not None:
                progress(done)
        # After an overflow the window is the one before the overflowing step
        # (whose graph missed edges): go on from it with a graph that fits.
        window = new_window
        if not overflow:
            continue
        grown = grow(capacity, jnp.take(window, window.shape[axis] - 1, axis=axis))
        if grown == capacity:
            raise RuntimeError(
                f"the graph overflows {capacity}, which cannot grow (every pair already fits): "
                "the positions at that step are probably not finite"
            )
        capacity = grown
    return chunks[0] if len(chunks) == 1 else jnp.concatenate(chunks, axis=0)


def rollout(
    params,
    initial_positions,
    radius,
    n_steps: int,
    *,
    model_config: ModelConfig,
    mask=None,
    capacity=None,
    chunk_size: int = 50,
):
    """Autoregressive rollout of ``n_steps`` frames (compiled loops, graph rebuilt at every step).

    With concrete arrays the steps run in compiled chunks of about
    ``chunk_size``; a chunk stops at a step whose graph overflowed, the
    capacity is grown and that step is recomputed, so the result is exactly
    that of a graph without any size limit. Under ``jit``/``vmap``/
    ``grad`` the whole rollout is one scan with the given ``capacity`` (when
    ``None``: sized from concrete initial positions with 50 % head-room, or
    all ``N (N - 1)`` pairs if they are traced too); every frame from the
    first overflowing step on is NaN. It is vmappable over trajectories of
    equal (padded) size and differentiable with respect to ``params``,
    positions and radii.

    Args:
      params: from :func:`dispgns.init_params`.
      initial_positions: ``(C, N, D)`` first ``C`` frames (normalised units).
      radius: ``(N,)`` radii (normalised units).
      n_steps: static, number of frames to predict.
      model_config: static :class:`ModelConfig`.
      mask: optional ``(N,)`` bool, ``False`` for padding particles.
      capacity: optional graph capacity.
      chunk_size: static, steps per compiled chunk in the concrete path
        (the host checks for an overflow between chunks; a chunk stops at
        its first overflowing step, so only that step is redone). On the
        CPU the chunks are compiled with
        :func:`dispgns.network_compiler_options`.

    Returns:
      ``(n_steps, N, D)`` predicted positions for frames ``C .. C + n_steps - 1``.
    """
    window, radius, mask = _check(
        initial_positions, radius, mask, model_config, leading=model_config.input_sequence_length
    )
    n = window.shape[1]
    _check_steps(n_steps)
    capacity = _as_capacity(capacity)
    if _is_traced(params, window, radius, mask):
        if capacity is None:
            if _is_traced(window, mask):
                capacity = _full_capacity(n)
            else:
                capacity = _fitted(np.asarray(window)[-1], mask, model_config, margin=0.5)
        _, positions, flags = _scan_steps(
            params, window, radius, mask, length=n_steps, capacity=capacity, model_config=model_config
        )
        return positions + jnp.where(flags, jnp.nan, 0.0).astype(positions.dtype)[:, None, None]

    if capacity is None:
        capacity = _fitted(window[-1], mask, model_config, margin=0.1)
    run_chunk = lambda w, limit, length, capacity: _rollout_chunk(
        params, w, radius, mask, limit, length=length, capacity=capacity, model_config=model_config
    )
    grow = lambda capacity, position: _grown(capacity, position, mask, model_config)
    return _roll_in_chunks(run_chunk, window, n_steps, chunk_size, capacity, grow, axis=0)


def _fitted(position, mask, model_config: ModelConfig, *, margin: float = 0.05) -> GraphCapacity:
    """A capacity on the ladder that fits the graph of ``position`` ``(N, D)`` with ``margin`` head-room (eager).

    On the ladder, calls on other positions and other trajectories mostly
    land on a capacity whose programs are already compiled.
    """
    fit = graph_lib.capacity_for(
        position, mask, connectivity_radius=model_config.connectivity_radius, bounds=model_config.bounds, margin=margin
    )
    return graph_lib.on_ladder(fit, position.shape[0])


def _grown(capacity: GraphCapacity, position, mask, model_config: ModelConfig) -> GraphCapacity:
    """A capacity larger than ``capacity`` that fits the graph of ``position`` ``(N, D)`` with head-room."""
    return _batch_capacity(capacity, np.asarray(position)[None], np.asarray(mask)[None], model_config, margin=0.2)


def one_step_batch(
    params,
    position_seq,
    radius,
    mask,
    capacity: GraphCapacity,
    model_config: ModelConfig,
    edge_budget: int | None = None,
):
    """:func:`one_step` for ``B`` trajectories at once, evaluated as one disjoint graph.

    Args:
      position_seq: ``(B, C, N, D)``; radius, mask: ``(B, N)``.
      edge_budget: static total edge slots of the merged graph (see
        :func:`merge_graphs`); exceeding it sets every overflow flag.

    Returns:
      ``(acceleration (B, N, D), next position (B, N, D), overflow (B,))``.
    """
    x, a = jax.vmap(lambda p, r, m: sanitize(p, r, m, model_config))(position_seq, radius, mask)
    graphs = jax.vmap(lambda p, m: build_graph(p, m, capacity, model_config))(x[:, -1], mask)
    output = network_output_batch(params, x, a, graphs, model_config=model_config, edge_budget=edge_budget)
    acc = jax.vmap(lambda y, r: acceleration_from_output(params, y, r))(output, a)
    acc = jnp.where(mask[..., None], acc, 0.0).astype(position_seq.dtype)
    last = position_seq[:, -1]
    next_position = jnp.where(
        mask[..., None], _constrain(last + (last - position_seq[:, -2]) + acc, radius, model_config), last
    )
    overflow = graphs.overflow
    if edge_budget is not None:
        overflow = overflow | (merged_edge_count(graphs, x.shape[2]) > edge_budget)
    return acc, next_position, overflow


def rollout_batch(
    params,
    initial_positions,
    radius,
    n_steps: int,
    *,
    model_config: ModelConfig,
    mask=None,
    capacity=None,
    chunk_size: int = 50,
    progress=None,
):
    """Rollouts of ``B`` trajectories of equal padded size in one compiled program per chunk.

    The same result as :func:`rollout` of each trajectory (padding never
    changes a real particle), computed on one disjoint graph of all ``B``
    trajectories per step, with the same chunked overflow handling: after an
    overflow in any trajectory the capacity grows and every trajectory is
    recomputed from the first overflowing step on. Concrete arrays only
    (under ``jit``/``vmap`` use ``jax.vmap(rollout)``).

    Args:
      params: from :func:`dispgns.init_params`.
      initial_positions: ``(B, C, N, D)`` first ``C`` frames (normalised
        units), padding rows anywhere (masked).
      radius: ``(B, N)`` radii (normalised units).
      n_steps: frames to predict.
      model_config: static :class:`ModelConfig`.
      mask: optional ``(B, N)`` bool, ``False`` for padding particles.
      capacity: optional graph capacity per trajectory (``None``: sized from
        the initial frames of every trajectory).
      chunk_size: steps per compiled chunk.
      progress: optional ``progress(done_steps)`` callback whenever steps are done
        (after each chunk, and before a capacity growth).

    Returns:
      ``(B, n_steps, N, D)`` predicted positions for frames ``C .. C + n_steps - 1``.
    """
    windows = jnp.asarray(initial_positions)
    if not jnp.issubdtype(windows.dtype, jnp.floating):
        windows = windows.astype(jnp.float32)
    c, d = model_config.input_sequence_length, model_config.dim
    if windows.ndim != 4 or windows.shape[1] != c or windows.shape[3] != d:
        raise ValueError(f"initial_positions must have shape (B, {c}, N, {d}), got {windows.shape}")
    b, _, n, _ = windows.shape
    radius = jnp.asarray(radius, windows.dtype)
    if radius.shape != (b, n):
        raise ValueError(f"radius must have shape ({b}, {n}), got {radius.shape}")
    mask = np.ones((b, n), bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (b, n):
        raise ValueError(f"mask must have shape ({b}, {n}), got {mask.shape}")
    _check_radius(radius, mask)
    _check_steps(n_steps)
    if _is_traced(params, windows, radius):
        raise ValueError("rollout_batch needs concrete arrays; under a transformation use jax.vmap(rollout)")
    mask = jnp.asarray(mask)
    capacity = _as_capacity(capacity)
    if capacity is None:
        capacity = _batch_capacity(None, windows[:, -1], mask, model_config, margin=0.1)
    run_chunk = lambda w, limit, length, capacity: _rollout_chunk_batch(
        params, w, radius, mask, limit, length=length, capacity=capacity, model_config=model_config
    )
    # One trajectory's overflow stops them all; every graph is refitted at that frame.
    grow = lambda capacity, position: _batch_capacity(capacity, position, mask, model_config, margin=0.2)
    positions = _roll_in_chunks(run_chunk, windows, n_steps, chunk_size, capacity, grow, axis=1, progress=progress)
    return jnp.moveaxis(positions, 0, 1)


def _batch_capacity(
    capacity: GraphCapacity | None, positions, mask, model_config: ModelConfig, *, margin: float
) -> GraphCapacity:
    """A capacity on the ladder that fits every graph of ``positions`` ``(B, N, D)`` (grown past ``capacity``)."""
    positions, mask = np.asarray(positions), np.asarray(mask)
    use_cells = None if capacity is None else capacity.cell is not None
    fits = [
        graph_lib.capacity_for(
            p,
            m,
            connectivity_radius=model_config.connectivity_radius,
            bounds=model_config.bounds,
            use_cell_list=use_cells,
            margin=margin,
        )
        for p, m in zip(positions, mask)
    ]
    cells = [f.cell for f in fits if f.cell is not None]
    fit = GraphCapacity(edges=max(f.edges for f in fits), cell=max(cells) if cells else None)
    n = positions.shape[1]
    if capacity is None:
        return graph_lib.on_ladder(fit, n)
    grown = graph_lib.grow_capacity(capacity, n, factor=1.25)
    cell = None if capacity.cell is None else max(grown.cell, fit.cell or 0)
    return graph_lib.on_ladder(GraphCapacity(edges=max(grown.edges, fit.edges), cell=cell), n)
