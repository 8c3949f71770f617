"""Radius graphs on jax-md neighbour lists, with fixed capacities, and the graph capacity policy.

The learned simulator connects every ordered pair of particles closer than the
connectivity radius at the last input frame, **self-loops included**. Graphs
live in arrays of static size so that they can be built inside ``jit``,
``vmap``, ``grad`` and ``lax.scan``:

* ``E = capacity.edges + N`` edge slots: ``capacity.edges`` for the ordered
  pairs ``s != r`` plus one self-loop per particle slot (padding slots too);
* the edges come sorted by receiver, unused slots at the end hold index ``N``
  (out of range: they gather nothing real and scatter nowhere);
* a graph that needs more slots than it has sets ``overflow`` instead of
  dropping edges (:func:`radius_graph` is pure; growing is the caller's job).

The capacity policy lives here and nowhere else: :func:`fit_capacity` sizes a
capacity from data, :func:`grow_capacity` grows one after an overflow, both
on the ladder of :mod:`dispgns.capacity` (so that capacities sized from
different data repeat and reuse compiled programs); :func:`edge_budget_for`
and :func:`grow_edge_budget` do the same for batches merged into one graph
(:func:`merge_graphs`).

Positions are in normalised units (the box is ``bounds``, by default
``[-1, 1]^D``). Padding particles (``mask == False``) are parked on a lattice
far outside the box, farther than the radius from everything, so they never
create an edge to a real particle or to each other (only their own self-loop).

Candidate pairs come either from all ``N^2`` pairs (``capacity.cell is None``)
or from a jax-md cell list with ``capacity.cell`` particles per cell. The cell
grid is the box grown by one radius on each side and hashed periodically, so
two particles closer than the radius always sit in neighbouring cells, even
when a rollout pushes them out of the box: the cell list never misses a pair,
it can only overflow (and says so).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jax_md import partition, space
from jaxtyping import ArrayLike, Bool, Float, Int
from scipy.spatial import cKDTree

from dispgns.arrays import Box, Count, Flag, Frame, ParticleMask, host_array
from dispgns.capacity import coarse_ladder, ladder
from dispgns.tuning import thresholds

__all__ = [
    "DEFAULT_BOUNDS",
    "Bounds",
    "Graph",
    "GraphCapacity",
    "as_bounds",
    "bounds_array",
    "capacity_for_counts",
    "cell_list_possible",
    "count_pairs",
    "edge_budget_for",
    "fit_capacity",
    "full_capacity",
    "grow_capacity",
    "grow_edge_budget",
    "host_count_pairs",
    "host_max_cell_occupancy",
    "merge_graphs",
    "merged_edge_count",
    "on_ladder",
    "park_padding",
    "parking_lattice",
    "radius_graph",
    "uses_cell_list",
]

Bounds = tuple[tuple[float, float], ...]
# Shapes (jaxtyping, no runtime check): E edge slots; positions of any leading shape ``(..., N, D)`` with a
# mask broadcastable to ``(..., N)``; B graphs of a batch, merged into one list of M edge slots.
_EdgeIndex = Int[ArrayLike, "E"]
_AnyFrames = Float[ArrayLike, "*frames N D"]
_AnyMask = Bool[ArrayLike, "*frames N"]
_FrameCounts = Int[ArrayLike, "*frames"]
_MergedIndex = Int[ArrayLike, "M"]

DEFAULT_BOUNDS: Bounds = ((-1.0, 1.0), (-1.0, 1.0))


@dataclasses.dataclass(frozen=True)
class GraphCapacity:
    """Static sizes of a radius graph (hashable: part of a jit cache key).

    Attributes:
      edges: slots for ordered pairs ``s != r`` of real particles. The graph
        has ``edges + N`` slots, the extra ``N`` holding the self-loops.
      cell: particles per cell of the jax-md cell list, or ``None`` for the
        all-pairs candidate path (exact for any configuration, ``O(N^2)``).
    """

    edges: int
    cell: int | None = None

    def __post_init__(self):
        if int(self.edges) != self.edges or self.edges < 0:
            raise ValueError(f"GraphCapacity.edges must be an integer >= 0, got {self.edges!r}")
        if self.cell is not None and (int(self.cell) != self.cell or self.cell < 1):
            raise ValueError(f"GraphCapacity.cell must be None or an integer >= 1, got {self.cell!r}")


class Graph(NamedTuple):
    """A radius graph in fixed-size arrays (a pytree).

    Attributes:
      senders: ``(E,)`` int32 sender index ``s`` of each edge ``s -> r``;
        ``N`` in unused slots.
      receivers: ``(E,)`` int32 receiver index ``r``, non-decreasing; ``N`` in
        unused slots (which come last).
      overflow: ``()`` bool, more edges (or more particles in a cell) than the
        capacity: some edges are missing and the graph must not be used.
    """

    senders: _EdgeIndex
    receivers: _EdgeIndex
    overflow: Flag


def bounds_array(bounds: Sequence[Sequence[float]], dtype: DTypeLike | None = None) -> Box:
    """``bounds`` ``((lo_0, hi_0), ..., (lo_{D-1}, hi_{D-1}))`` as a ``(D, 2)`` array."""
    return jnp.asarray(np.asarray(bounds, dtype=float), dtype)


def as_bounds(bounds: Sequence[Sequence[float]] | Box | None, dim: int) -> Bounds:
    """Validate ``bounds`` for ``dim`` axes and return it as a hashable tuple of ``(lo, hi)`` floats.

    ``None`` is the default box ``[-1, 1]^dim`` (normalised units).
    """
    if bounds is None:
        return ((-1.0, 1.0),) * int(dim)
    b = np.asarray(bounds, dtype=float)
    if b.shape != (dim, 2) or not np.all(b[:, 1] > b[:, 0]):
        raise ValueError(f"bounds must be {dim} pairs (lo, hi) with lo < hi, got {bounds!r}")
    return tuple((float(lo), float(hi)) for lo, hi in b)


def _grid(connectivity_radius: float, bounds: Bounds):
    """Cell grid of the cell list: origin (D,), extent (D,), cells per side (D,), cell size (D,)."""
    lo = np.array([b[0] for b in bounds]) - connectivity_radius
    extent = np.array([b[1] - b[0] for b in bounds]) + 2.0 * connectivity_radius
    cells = np.maximum(np.floor(extent / connectivity_radius).astype(int), 1)
    return lo, extent, cells, extent / cells


def park_padding(
    position: _AnyFrames, mask: _AnyMask | None, *, connectivity_radius: float, bounds: Bounds | None = None
) -> _AnyFrames:
    """Move padding particles onto a lattice far outside the box.

    Lattice points are at least two cells (two radii) apart and spread over
    all cells of the grid, so padding particles neither pair with anything
    nor crowd one cell of the cell list.

    Args:
      position: ``(..., N, D)`` positions (normalised units).
      mask: ``(N,)`` bool (or broadcastable to ``position.shape[:-1]``),
        ``False`` for padding particles; ``None`` means all real.

    Returns:
      ``position`` with padding rows replaced (real rows untouched).
    """
    if mask is None:
        return position
    n, dim = position.shape[-2:]
    parked = jnp.asarray(
        parking_lattice(n, dim, connectivity_radius=connectivity_radius, bounds=bounds),
        jax.dtypes.canonicalize_dtype(position.dtype),
    )
    return jnp.where(jnp.asarray(mask)[..., None], position, parked)


def parking_lattice(n: int, dim: int, *, connectivity_radius: float, bounds: Bounds | None = None) -> Frame:
    """The ``(n, dim)`` float64 numpy positions :func:`park_padding` gives padding slots ``0 .. n-1``.

    Numpy, so that host code can use it inside a user's ``jit`` without
    creating tracers.
    """
    bounds = as_bounds(bounds, dim)
    _, extent, cells, cell_size = _grid(connectivity_radius, bounds)
    per_axis = np.maximum(cells // 2, 1)
    k = np.arange(n)
    # Axis 0 also carries the overflow of the index, so every slot gets its own point.
    points = [k % per_axis[0] + per_axis[0] * (k // int(np.prod(per_axis)))]
    points += [(k // int(np.prod(per_axis[:d]))) % per_axis[d] for d in range(1, dim)]
    points = np.stack(points, axis=-1)
    base = np.array([b[1] for b in bounds]) + 64.0 * extent
    return base + (2.0 * points + 0.5) * cell_size


def cell_list_possible(dim: int, *, connectivity_radius: float, bounds: Bounds | None = None) -> bool:
    """Whether jax-md can build a cell list here: ``D`` of 2 or 3 and >= 3 cells per side."""
    if dim not in (2, 3):
        return False
    _, _, cells, _ = _grid(connectivity_radius, as_bounds(bounds, dim))
    return bool(np.all(cells >= 3))


@contextlib.contextmanager
def _quiet_x64_scatter():
    """Silence jax-md's int64 -> int32 scatter warning under x64 (harmless: ids < 2^31)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="scatter inputs have incompatible types", category=FutureWarning)
        yield


@functools.cache
def _neighbor_fns(connectivity_radius: float, bounds: Bounds, use_cells: bool):
    _, extent, _, _ = _grid(connectivity_radius, bounds)
    displacement, _ = space.free()
    # jax-md turns the radius into arrays here; keep them concrete when the
    # first call happens inside a trace (they are cached beyond it).
    with jax.ensure_compile_time_eval():
        return partition.neighbor_list(
            displacement,
            jnp.asarray(extent, jnp.float32),
            r_cutoff=connectivity_radius,
            dr_threshold=0.0,  # always rebuild: the graph is recomputed at every step
            capacity_multiplier=1.0,
            disable_cell_list=not use_cells,
            mask_self=False,  # self-loops are edges of the graph
            format=partition.NeighborListFormat.Sparse,
        )


@functools.cache
def _base_template(
    dim: int, connectivity_radius: float, bounds: Bounds, use_cells: bool, x64: bool
) -> partition.NeighborList:
    """A jax-md neighbour list allocated eagerly on a few far-apart points, once per setting.

    Only its static parts matter: with ``dr_threshold = 0`` an update rebuilds
    everything from the new positions, at the capacities stored in the list.
    """
    fns = _neighbor_fns(connectivity_radius, bounds, use_cells)
    with jax.ensure_compile_time_eval(), _quiet_x64_scatter():
        origin, _, _, _ = _grid(connectivity_radius, bounds)
        dummy = parking_lattice(4, dim, connectivity_radius=connectivity_radius, bounds=bounds)
        dummy = jnp.asarray(dummy - origin, jnp.float64 if x64 else jnp.float32)
        nbrs = fns.allocate(dummy)
    if use_cells and nbrs.cell_list_fn is None:
        raise ValueError(
            f"a cell list needs at least 3 cells per side; the box {bounds} grown by the radius "
            f"{connectivity_radius} is too small: use GraphCapacity(cell=None)"
        )
    return nbrs


def _template(
    n: int, dim: int, connectivity_radius: float, bounds: Bounds, capacity: GraphCapacity, x64: bool
) -> partition.NeighborList:
    """A jax-md neighbour list with the requested static capacities."""
    base = _base_template(dim, connectivity_radius, bounds, capacity.cell is not None, x64)
    return dataclasses.replace(base, max_occupancy=int(capacity.edges) + n, cell_list_capacity=capacity.cell)


def radius_graph(
    position: Frame,
    mask: ParticleMask | None = None,
    *,
    connectivity_radius: float,
    capacity: GraphCapacity,
    bounds: Bounds | None = None,
) -> Graph:
    """All ordered pairs with ``|x_s - x_r| < connectivity_radius``, self-loops included.

    Pure and jittable; vmap it over a leading batch axis for several graphs.

    Args:
      position: ``(N, D)`` positions in normalised units (padding rows are
        ignored: they are parked far away here).
      mask: ``(N,)`` bool, ``False`` for padding particles; ``None``: all real.
      connectivity_radius: static, normalised units.
      capacity: static :class:`GraphCapacity`.
      bounds: static box ``((lo, hi),) * D``, only used to lay out the cell
        grid and the padding lattice (particles may lie outside it).

    Returns:
      a :class:`Graph` with ``E = capacity.edges + N`` slots.
    """
    n, dim = position.shape
    bounds = as_bounds(bounds, dim)
    x64 = position.dtype == jnp.float64
    template = _template(n, dim, float(connectivity_radius), bounds, capacity, x64)
    parked = park_padding(jax.lax.stop_gradient(position), mask, connectivity_radius=connectivity_radius, bounds=bounds)
    origin, _, _, _ = _grid(connectivity_radius, bounds)
    with _quiet_x64_scatter():
        nbrs = template.update(parked - jnp.asarray(origin, parked.dtype))
    slots = int(capacity.edges) + n
    idx = nbrs.idx
    if idx.shape[1] <= slots:
        # jax-md kept every candidate slot. Its pruning scatters all rejected
        # candidates into the very last slot, which then holds a non-edge
        # unless every candidate was accepted: re-test that one slot.
        shifted = parked - jnp.asarray(origin, parked.dtype)
        s_last, r_last = idx[0, -1], idx[1, -1]
        inside = (s_last < n) & (r_last < n)
        diff = shifted[jnp.minimum(s_last, n - 1)] - shifted[jnp.minimum(r_last, n - 1)]
        keep = inside & (jnp.sum(diff * diff) < jnp.asarray(connectivity_radius, shifted.dtype) ** 2)
        idx = idx.at[:, -1].set(jnp.where(keep, idx[:, -1], n))
    if idx.shape[1] < slots:
        # jax-md clips the capacity to the number of candidates; keep the static size.
        idx = jnp.pad(idx, ((0, 0), (0, slots - idx.shape[1])), constant_values=n)
    # jax-md's sparse rows are grouped by the particle whose candidates were
    # scanned (idx[1]); calling it the receiver gives receiver-sorted edges.
    overflow = (nbrs.error.code & (partition.PEC.NEIGHBOR_LIST_OVERFLOW | partition.PEC.CELL_LIST_OVERFLOW)) != 0
    return Graph(senders=idx[0].astype(jnp.int32), receivers=idx[1].astype(jnp.int32), overflow=overflow)


def count_pairs(position: _AnyFrames, mask: _AnyMask | None = None, *, connectivity_radius: float) -> _FrameCounts:
    """Number of ordered pairs ``s != r`` of real particles closer than the radius (pure, all pairs).

    ``position``: ``(..., N, D)``; returns int32 of shape ``position.shape[:-2]``.
    Builds ``N x N`` distances: for small graphs and tests (:func:`host_count_pairs` scales).
    """
    x = jax.lax.stop_gradient(position)
    d2 = sum((x[..., :, None, d] - x[..., None, :, d]) ** 2 for d in range(x.shape[-1]))
    close = d2 < connectivity_radius**2
    n = x.shape[-2]
    close = close & ~jnp.eye(n, dtype=bool)
    if mask is not None:
        mask = jnp.asarray(mask, bool)
        close = close & mask[..., :, None] & mask[..., None, :]
    return jnp.sum(close, axis=(-2, -1), dtype=jnp.int32)


def _frames_and_masks(position, mask) -> tuple[np.ndarray, np.ndarray]:
    """Concrete ``(..., N, D)`` positions and a mask broadcastable to ``(..., N)`` as ``(F, N, D)``, ``(F, N)``."""
    x = host_array(position, "position")
    if x.ndim < 2:
        raise ValueError(f"position must have shape (..., N, D), got {x.shape}")
    keep = np.ones(x.shape[:-1], bool) if mask is None else host_array(mask, "mask").astype(bool)
    try:
        keep = np.broadcast_to(keep, x.shape[:-1])
    except ValueError:
        raise ValueError(f"mask of shape {keep.shape} does not fit positions of shape {x.shape}") from None
    return x.reshape((-1,) + x.shape[-2:]), keep.reshape((-1, x.shape[-2]))


def host_count_pairs(position: _AnyFrames, mask: _AnyMask | None = None, *, connectivity_radius: float) -> _FrameCounts:
    """Host count of ordered pairs ``s != r`` of real particles closer than the radius, per frame.

    ``position``: concrete ``(..., N, D)``; ``mask``: broadcastable to
    ``position.shape[:-1]``. Returns int64 counts of shape
    ``position.shape[:-2]``. Counting is done in float64 and so may differ
    from the float32 graph on pairs within rounding of the radius, which the
    capacities' head-room covers. Small frames are counted in blocks of
    ``N x N`` distances, large ones with a k-d tree (``O(N log N)``).
    """
    x = host_array(position, "position")
    frames, keep = _frames_and_masks(x, mask)
    frames = frames.astype(np.float64)
    n, dim = frames.shape[1:]
    r2 = float(connectivity_radius) ** 2
    counts = np.empty((frames.shape[0],), np.int64)
    if n <= _DENSE_COUNT_MAX_PARTICLES:
        step = max(1, 4_000_000 // max(1, n * n))
        for start in range(0, frames.shape[0], step):
            block, real = frames[start : start + step], keep[start : start + step]
            d2 = sum((block[:, :, None, d] - block[:, None, :, d]) ** 2 for d in range(dim))
            close = (d2 < r2) & real[:, :, None] & real[:, None, :]
            counts[start : start + step] = np.count_nonzero(close, axis=(1, 2)) - real.sum(axis=1)
    else:
        # count_neighbors counts distances <= r: the largest float64 below r gives "< r".
        below = float(np.nextafter(float(connectivity_radius), 0.0))
        for f, (points, real) in enumerate(zip(frames, keep)):
            tree = cKDTree(points[real])
            counts[f] = int(tree.count_neighbors(tree, below)) - int(real.sum())
    return counts.reshape(x.shape[:-2])


# Up to this many particles host_count_pairs builds N x N distances (fast in
# numpy blocks, and memory-bounded); above, a k-d tree per frame.
_DENSE_COUNT_MAX_PARTICLES = 1024


def host_max_cell_occupancy(
    position: _AnyFrames, mask: _AnyMask | None = None, *, connectivity_radius: float, bounds: Bounds | None = None
) -> int:
    """Most particles in one cell of the cell list over all frames (padding parked as in :func:`radius_graph`).

    ``position``: concrete ``(..., N, D)``; ``mask``: broadcastable to ``position.shape[:-1]``.
    """
    frames, keep = _frames_and_masks(position, mask)
    n, dim = frames.shape[1:]
    bounds = as_bounds(bounds, dim)
    origin, extent, _, _ = _grid(connectivity_radius, bounds)
    parked = parking_lattice(n, dim, connectivity_radius=connectivity_radius, bounds=bounds)
    frames = np.where(keep[..., None], frames, parked[None])
    # jax-md's hashing, in its float32 arithmetic.
    box = np.float32(extent)
    cells = np.floor(box / np.float32(connectivity_radius)).astype(np.int64)
    cell_size = box / cells
    shifted = (frames - origin).astype(np.float32)
    index = np.mod(np.trunc(shifted / cell_size).astype(np.int64), cells)
    flat = np.zeros(index.shape[:2], np.int64)
    for d in range(dim - 1, -1, -1):
        flat = flat * cells[d] + index[..., d]
    return int(max(np.bincount(f, minlength=1).max() for f in flat))


# ----------------------------------------------------------------------------- the capacity policy
# Every graph capacity dispgns sizes from data or grows after an overflow is
# decided by the three functions below, on the ladder of dispgns.capacity.


def capacity_for_counts(
    pairs: int, n: int, *, occupancy: int | None = None, margin: float = 0.05, extra: int = 32
) -> GraphCapacity:
    """The capacity, on the ladder, for a graph of ``pairs`` ordered pairs among ``n`` particle slots.

    Edges: ``pairs * (1 + margin) + extra`` rounded up to the ladder (multiples
    of 64, rungs ~19 % apart), at most all ``n (n - 1)`` pairs. Cells (when the
    fullest cell holds ``occupancy`` particles; ``None``: no cell list):
    ``occupancy * (1 + 4 margin) + 1``, at least 4, on the coarse ladder, at
    most ``n``.
    """
    edges = min(ladder(math.ceil(int(pairs) * (1.0 + margin)) + int(extra), quantum=64), n * (n - 1))
    cell = None
    if occupancy is not None:
        cell = min(coarse_ladder(max(4, math.ceil(int(occupancy) * (1.0 + 4 * margin)) + 1)), max(n, 1))
    return GraphCapacity(edges=edges, cell=cell)


def uses_cell_list(n: int, dim: int, *, connectivity_radius: float, bounds: Bounds | None = None) -> bool:
    """The default candidate search: a cell list from ``tuning.thresholds().cell_list_min_particles`` slots on.

    Both searches give the same graph; the cell list is faster for many particles.
    """
    return n >= thresholds().cell_list_min_particles and cell_list_possible(
        dim, connectivity_radius=connectivity_radius, bounds=bounds
    )


def fit_capacity(
    position: _AnyFrames,
    mask: _AnyMask | None = None,
    *,
    connectivity_radius: float,
    bounds: Bounds | None = None,
    margin: float = 0.05,
    use_cell_list: bool | None = None,
) -> GraphCapacity:
    """The capacity, on the ladder, that fits the graph of every frame of ``position`` with head-room (host).

    Args:
      position: concrete ``(..., N, D)`` positions (normalised units): one
        frame, a trajectory, a batch of trajectories...
      mask: ``None`` or bool broadcastable to ``position.shape[:-1]``.
      margin: relative head-room over the most pairs found (``0.5`` for a
        graph that must last a rollout under ``jit``, where it cannot grow).
      use_cell_list: ``None``: :func:`uses_cell_list`.

    Returns:
      :func:`capacity_for_counts` of the largest frame.
    """
    frames, keep = _frames_and_masks(position, mask)
    n, dim = frames.shape[1:]
    pairs = int(np.max(host_count_pairs(frames, keep, connectivity_radius=connectivity_radius)))
    if use_cell_list is None:
        use_cell_list = uses_cell_list(n, dim, connectivity_radius=connectivity_radius, bounds=bounds)
    occupancy = None
    if use_cell_list:
        occupancy = host_max_cell_occupancy(frames, keep, connectivity_radius=connectivity_radius, bounds=bounds)
    return capacity_for_counts(pairs, n, occupancy=occupancy, margin=margin)


def grow_capacity(
    capacity: GraphCapacity,
    n: int,
    position: _AnyFrames | None = None,
    mask: _AnyMask | None = None,
    *,
    connectivity_radius: float | None = None,
    bounds: Bounds | None = None,
) -> GraphCapacity:
    """A capacity on the ladder larger than ``capacity`` (after an overflow), for ``n`` particle slots.

    At least 1.25 x ``capacity`` (edges and cells), and when the positions
    where it overflowed are given (concrete ``(..., N, D)``; mask
    broadcastable to ``(..., N)``), enough for their graphs with 20 %
    head-room. Capped at all pairs and at ``n`` per cell: the result equals
    ``capacity`` only when nothing can grow.
    """
    edges = max(math.ceil(capacity.edges * 1.25), capacity.edges + 1)
    cell = None if capacity.cell is None else max(math.ceil(capacity.cell * 1.25), capacity.cell + 2)
    if position is not None:
        if connectivity_radius is None:
            raise ValueError("grow_capacity needs connectivity_radius to fit positions")
        fit = fit_capacity(
            position,
            mask,
            connectivity_radius=connectivity_radius,
            bounds=bounds,
            margin=0.2,
            use_cell_list=capacity.cell is not None,
        )
        edges, cell = max(edges, fit.edges), None if cell is None else max(cell, fit.cell)
    edges, cell = min(edges, n * (n - 1)), None if cell is None else min(cell, max(n, 1))
    return on_ladder(
        GraphCapacity(edges=max(edges, capacity.edges), cell=None if cell is None else max(cell, capacity.cell)), n
    )


def full_capacity(n: int) -> GraphCapacity:
    """Room for every ordered pair of ``n`` particles on the all-pairs path: it can never overflow."""
    return GraphCapacity(edges=n * (n - 1))


def on_ladder(capacity: GraphCapacity, n: int | None = None) -> GraphCapacity:
    """``capacity`` rounded up to the ladder of :mod:`dispgns.capacity` (edges and cells), never below it.

    Edges go to multiples of 64 on rungs ~19 % apart, cells to ``2^k`` or
    ``1.5 x 2^k`` (a cell's head-room is cheap, and the fullest cell of a
    settling bed varies more than the pair count). Capped at all pairs and
    at ``n`` per cell when the particle count ``n`` is given.
    """
    edges = max(ladder(capacity.edges, quantum=64), capacity.edges)
    cell = None if capacity.cell is None else coarse_ladder(capacity.cell)
    if n is not None:
        edges = max(min(edges, n * (n - 1)), capacity.edges)
        cell = None if cell is None else max(min(cell, n), capacity.cell)
    return GraphCapacity(edges=edges, cell=cell)


def edge_budget_for(need: int) -> int:
    """Edge slots, on the ladder, for a merged graph that needs ``need`` (see :func:`merge_graphs`)."""
    return ladder(need, quantum=64)


def grow_edge_budget(budget: int) -> int:
    """The next edge budget after a merged graph overflowed ``budget`` (at least 1.25 x, on the ladder)."""
    return ladder(max(math.ceil(budget * 1.25), budget + 1), quantum=64)


# ----------------------------------------------------------------------------- merged graphs


def merged_edge_count(graphs: Graph, n: int) -> Count:
    """Number of real edges (self-loops included) of ``B`` graphs ``(B, E)`` over ``n`` node slots: ``()`` int32."""
    return jnp.sum(graphs.receivers < n, dtype=jnp.int32)


def merge_graphs(graphs: Graph, n: int, edge_budget: int | None = None) -> tuple[_MergedIndex, _MergedIndex]:
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
      Edges beyond ``edge_budget`` are dropped: the caller checks
      :func:`merged_edge_count` ``<= edge_budget`` and reports an overflow.
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
