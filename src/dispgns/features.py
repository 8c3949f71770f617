"""The paper's node and edge features (Hashemi & Izadkhah 2025, after DeepMind's GNS).

Inputs are the last ``C`` positions of every particle and its radius, in
normalised box units; frame spacing is the unit of time, so the velocities
are ``v_k = x_k - x_{k-1}`` for ``k = 1 .. C-1``. With ``D`` the dimension:

* node features, ``(C-1) D + 2 D + 1`` values (15 for ``C = 6, D = 2``):
  ``[v_1, ..., v_{C-1}] / a_i`` time-major (``v_1x, v_1y, v_2x, ...``), then
  the distances to the lower walls and then to the upper walls at the last
  frame divided by ``a_i`` and clipped to ``[-clip, clip]``, then ``a_i``;
* edge features of ``s -> r``, ``C D + 2`` values (14): ``(x_s - x_r) / (a_s
  + a_r)`` at the last frame, its Euclidean norm, ``(v_s,k - v_r,k) / (a_s +
  a_r)`` for ``k = 1 .. C-1`` (time-major), and ``a_s + a_r``.

Everything here is pure and works under ``jit``/``vmap``/``grad`` (the norm
has a finite gradient at the zero length of self-loops), in the dtype of the
positions.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, Int

from dispgns import graph as graph_lib
from dispgns.arrays import Box, PositionWindow, Radii, host_array
from dispgns.capacity import Attempt, drive

# Shapes (jaxtyping, no runtime check): C input frames, E edges, F node and G edge features.
_Velocities = Float[ArrayLike, "C-1 N D"]
_NodeFeatures = Float[ArrayLike, "N F"]
_EdgeFeatures = Float[ArrayLike, "E G"]
_EdgeIndex = Int[ArrayLike, "E"]

__all__ = ["edge_feature_size", "edge_features", "graph_features", "node_feature_size", "node_features", "velocities"]


def node_feature_size(input_sequence_length: int, dim: int) -> int:
    """``(C - 1) D + 2 D + 1``."""
    return (input_sequence_length - 1) * dim + 2 * dim + 1


def edge_feature_size(input_sequence_length: int, dim: int) -> int:
    """``C D + 2``."""
    return input_sequence_length * dim + 2


def velocities(position_seq: PositionWindow) -> _Velocities:
    """``(C, N, D)`` positions -> ``(C-1, N, D)`` velocities (one frame = one time unit)."""
    return position_seq[1:] - position_seq[:-1]


def _time_major(seq: jnp.ndarray) -> jnp.ndarray:
    """``(K, N, D)`` -> ``(N, K D)`` ordered ``[k0 x, k0 y, k1 x, ...]``."""
    k, n, d = seq.shape
    return jnp.transpose(seq, (1, 0, 2)).reshape(n, k * d)


def _safe_norm(x: jnp.ndarray) -> jnp.ndarray:
    """Euclidean norm over the last axis with a zero (not NaN) gradient at 0."""
    sq = jnp.sum(x * x, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def node_features(
    position_seq: PositionWindow,
    radius: Radii,
    *,
    bounds: Sequence[Sequence[float]] | Box | None = None,
    boundary_clip: float = 4.0,
) -> _NodeFeatures:
    """Node features of the paper.

    Args:
      position_seq: ``(C, N, D)`` positions, oldest first (normalised units).
      radius: ``(N,)`` radii ``a_i`` (normalised units, > 0).
      bounds: static box ``((lo, hi),) * D`` (``None``: ``[-1, 1]^D``).
      boundary_clip: static clip of the wall distances in radii.

    Returns:
      ``(N, (C-1) D + 2 D + 1)``.
    """
    b = graph_lib.bounds_array(graph_lib.as_bounds(bounds, position_seq.shape[-1]), position_seq.dtype)
    inv_a = (1.0 / radius)[:, None]
    vel = _time_major(velocities(position_seq)) * inv_a
    last = position_seq[-1]
    walls = jnp.concatenate([last - b[:, 0], b[:, 1] - last], axis=-1) * inv_a
    walls = jnp.clip(walls, -boundary_clip, boundary_clip)
    return jnp.concatenate([vel, walls, radius[:, None]], axis=-1)


def edge_features(
    position_seq: PositionWindow, radius: Radii, senders: _EdgeIndex, receivers: _EdgeIndex
) -> _EdgeFeatures:
    """Edge features of ``s -> r`` for every edge.

    Args:
      position_seq: ``(C, N, D)`` positions (normalised units).
      radius: ``(N,)`` radii.
      senders, receivers: ``(E,)`` int indices in ``[0, N)``; out-of-range
        padding indices are clipped (their rows are then meaningless).

    Returns:
      ``(E, C D + 2)``.
    """
    c, n, d = position_seq.shape
    # Gather one row per endpoint: [x_last, v_1 .. v_{C-1}, a].
    per_node = jnp.concatenate([position_seq[-1], _time_major(velocities(position_seq)), radius[:, None]], axis=-1)
    s = jnp.take(per_node, senders, axis=0, mode="clip")
    r = jnp.take(per_node, receivers, axis=0, mode="clip")
    a_sum = s[:, -1] + r[:, -1]
    inv = (1.0 / a_sum)[:, None]
    rel = (s[:, :d] - r[:, :d]) * inv
    rel_vel = (s[:, d:-1] - r[:, d:-1]) * inv
    return jnp.concatenate([rel, _safe_norm(rel)[:, None], rel_vel, a_sum[:, None]], axis=-1)


def graph_features(
    position_seq: PositionWindow,
    radius: Radii,
    *,
    bounds: Sequence[Sequence[float]] | Box | None = None,
    connectivity_radius: float = 0.2,
    boundary_clip: float = 4.0,
) -> tuple[_NodeFeatures, _EdgeFeatures, _EdgeIndex, _EdgeIndex]:
    """Node features, edge features and edges of one configuration, padding removed.

    A host convenience for inspection and tests; it needs concrete arrays
    (the number of edges is data-dependent; the graph capacity is fitted and
    grown until nothing is dropped). Edges are every ordered pair within
    ``connectivity_radius`` at the last frame, self-loops included, sorted by
    (receiver, sender).

    Args:
      position_seq: ``(C, N, D)`` positions (normalised units).
      radius: ``(N,)`` radii (normalised units).

    Returns:
      ``(node_features (N, (C-1)D + 2D + 1), edge_features (E, CD + 2),
      senders (E,), receivers (E,))`` in the dtype of ``position_seq``.
    """
    position_seq = host_array(position_seq, "position_seq", pure="node_features and edge_features")
    if not np.issubdtype(position_seq.dtype, np.floating):
        position_seq = position_seq.astype(np.float32)
    radius = host_array(radius, "radius").astype(position_seq.dtype)
    if position_seq.ndim != 3 or radius.shape != position_seq.shape[1:2]:
        raise ValueError(
            f"expected position_seq (C, N, D) and radius (N,), got {position_seq.shape} and {radius.shape}"
        )
    n = position_seq.shape[1]
    bounds = graph_lib.as_bounds(bounds, position_seq.shape[2])
    last = position_seq[-1]
    build = lambda capacity: _graph_jit(last, connectivity_radius, capacity, bounds)

    def attempt(_, capacity, __):
        graph = build(capacity)
        return Attempt(None, None, 0, True) if bool(graph.overflow) else Attempt(None, graph, 1, False)

    grow = lambda capacity, _: graph_lib.grow_capacity(
        capacity, n, last, connectivity_radius=connectivity_radius, bounds=bounds
    )
    capacity = graph_lib.fit_capacity(last, connectivity_radius=connectivity_radius, bounds=bounds)
    _, (graph,), _ = drive(attempt, None, capacity, grow)
    senders, receivers = np.asarray(graph.senders), np.asarray(graph.receivers)
    keep = receivers < n
    senders, receivers = senders[keep], receivers[keep]
    order = np.lexsort((senders, receivers))
    senders, receivers = jnp.asarray(senders[order]), jnp.asarray(receivers[order])
    nodes, edges = _features_jit(position_seq, radius, senders, receivers, bounds, float(boundary_clip))
    return nodes, edges, senders, receivers


@functools.partial(jax.jit, static_argnums=(4, 5))
def _features_jit(position_seq, radius, senders, receivers, bounds, boundary_clip):
    nodes = node_features(position_seq, radius, bounds=bounds, boundary_clip=boundary_clip)
    return nodes, edge_features(position_seq, radius, senders, receivers)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _graph_jit(position, connectivity_radius, capacity, bounds):
    return graph_lib.radius_graph(
        position, None, connectivity_radius=connectivity_radius, capacity=capacity, bounds=bounds
    )
