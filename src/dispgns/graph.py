"""Radius graphs on jax-md neighbour lists, with fixed capacities and overflow detection.

The learned simulator connects every ordered pair of particles closer than the
connectivity radius at the last input frame, **self-loops included**. Graphs
live in arrays of static size so that they can be built inside ``jit``,
``vmap``, ``grad`` and ``lax.scan``:

* ``E = capacity.edges + N`` edge slots: ``capacity.edges`` for the ordered
  pairs ``s != r`` plus one self-loop per particle slot (padding slots too);
* the edges come sorted by receiver, unused slots at the end hold index ``N``
  (out of range: they gather nothing real and scatter nowhere);
* a graph that needs more slots than it has sets ``overflow`` instead of
  dropping edges; the caller grows the capacity outside ``jit``
  (:func:`grow_capacity`) and recomputes, or poisons its result with NaN when
  it is traced and cannot grow; :func:`on_ladder` rounds a capacity up to a
  fixed geometric ladder, so that capacities sized from different data
  repeat (one compilation each).

Positions are in normalised box units (the box is ``bounds``, by default
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
from jax_md import partition, space

Bounds = tuple[tuple[float, float], ...]

DEFAULT_BOUNDS: Bounds = ((-1.0, 1.0), (-1.0, 1.0))

# From this many particle slots on, capacity_for picks the cell list. Measured
# on 2 CPU cores with the settled packings of the data: all pairs 0.19 ms vs
# cells 0.27 ms at N = 60, 0.40 vs 0.44 ms at 120, 1.6 vs 0.7 ms at 220,
# 28 vs 7 ms at 1000 (jax-md's all-pairs pruning scans N^2 candidates).
CELL_LIST_MIN_PARTICLES = 160


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

    senders: jnp.ndarray
    receivers: jnp.ndarray
    overflow: jnp.ndarray


def bounds_array(bounds: Sequence[Sequence[float]], dtype=None) -> jnp.ndarray:
    """``bounds`` ``((lo_0, hi_0), ..., (lo_{D-1}, hi_{D-1}))`` as a ``(D, 2)`` array."""
    return jnp.asarray(np.asarray(bounds, dtype=float), dtype)


def as_bounds(bounds, dim: int) -> Bounds:
    """Validate ``bounds`` for ``dim`` axes and return it as a hashable tuple of ``(lo, hi)`` floats."""
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
    position: jnp.ndarray, mask: jnp.ndarray | None, *, connectivity_radius: float, bounds: Bounds = DEFAULT_BOUNDS
) -> jnp.ndarray:
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


def parking_lattice(n: int, dim: int, *, connectivity_radius: float, bounds: Bounds = DEFAULT_BOUNDS) -> np.ndarray:
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


def cell_list_possible(dim: int, *, connectivity_radius: float, bounds: Bounds = DEFAULT_BOUNDS) -> bool:
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
    position: jnp.ndarray,
    mask: jnp.ndarray | None = None,
    *,
    connectivity_radius: float,
    capacity: GraphCapacity,
    bounds: Bounds = DEFAULT_BOUNDS,
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


def count_pairs(position: jnp.ndarray, mask: jnp.ndarray | None = None, *, connectivity_radius: float) -> jnp.ndarray:
    """Number of ordered pairs ``s != r`` of real particles closer than the radius.

    All-pairs, jittable. ``position``: ``(..., N, D)``; returns int32 of shape
    ``position.shape[:-2]``.
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


def _host_array(x, name: str) -> np.ndarray:
    if isinstance(x, jax.core.Tracer):
        raise ValueError(f"{name} must be concrete to size a graph (got a traced array); pass a capacity instead")
    return np.asarray(x)


def host_count_pairs(position, mask=None, *, connectivity_radius: float) -> np.ndarray:
    """Host (numpy) count of ordered pairs ``s != r`` of real particles closer than the radius.

    ``position``: concrete ``(..., N, D)``; returns int64 counts of shape
    ``position.shape[:-2]``. Counting is done in float64 and so may differ
    from the float32 graph on pairs within rounding of the radius.
    """
    x = _host_array(position, "position").astype(np.float64)
    lead, (n, dim) = x.shape[:-2], x.shape[-2:]
    x = x.reshape((-1, n, dim))
    keep = np.ones((n,), bool) if mask is None else _host_array(mask, "mask").astype(bool)
    x = x[:, keep]
    counts = np.empty((x.shape[0],), np.int64)
    r2 = float(connectivity_radius) ** 2
    m = x.shape[1]
    step = max(1, 4_000_000 // max(1, m * m))
    for start in range(0, x.shape[0], step):
        block = x[start : start + step]
        d2 = np.zeros(block.shape[:1] + (m, m))
        for d in range(dim):
            d2 += (block[:, :, None, d] - block[:, None, :, d]) ** 2
        counts[start : start + step] = np.count_nonzero(d2 < r2, axis=(1, 2)) - m
    return counts.reshape(lead)


def host_max_cell_occupancy(position, mask=None, *, connectivity_radius: float, bounds: Bounds = DEFAULT_BOUNDS) -> int:
    """Most particles in one cell of the cell list (padding parked as in :func:`radius_graph`).

    ``position``: concrete ``(N, D)`` or ``(T, N, D)`` (maximum over frames).
    """
    x = _host_array(position, "position")
    frames = x if x.ndim == 3 else x[None]
    n, dim = frames.shape[1:]
    bounds = as_bounds(bounds, dim)
    origin, extent, _, _ = _grid(connectivity_radius, bounds)
    if mask is not None:
        parked = parking_lattice(n, dim, connectivity_radius=connectivity_radius, bounds=bounds)
        keep = _host_array(mask, "mask").astype(bool)
        frames = np.where(keep[None, :, None], frames, parked[None])
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


def round_capacity(count: int, *, margin: float = 0.05, minimum_extra: int = 32, quantum: int = 64) -> int:
    """A capacity for ``count`` items: ``count * (1 + margin) + minimum_extra``, rounded up to ``quantum``."""
    need = math.ceil(count * (1.0 + margin)) + minimum_extra
    return int(quantum * math.ceil(need / quantum))


def capacity_for(
    position: jnp.ndarray,
    mask: jnp.ndarray | None = None,
    *,
    connectivity_radius: float,
    bounds: Bounds = DEFAULT_BOUNDS,
    use_cell_list: bool | None = None,
    margin: float = 0.05,
) -> GraphCapacity:
    """A :class:`GraphCapacity` that fits the graph of ``position`` with some margin (eager).

    Args:
      position: ``(N, D)`` or ``(T, N, D)`` positions (the capacity fits every frame).
      mask: ``(N,)`` bool or ``None``.
      use_cell_list: ``None`` picks the cell list when ``N >=
        CELL_LIST_MIN_PARTICLES`` and jax-md can build one
        (:func:`cell_list_possible`).
      margin: relative head-room on top of the counted pairs.
    """
    x = _host_array(position, "position")
    frames = x if x.ndim == 3 else x[None]
    n = frames.shape[1]
    pairs = int(np.max(host_count_pairs(frames, mask, connectivity_radius=connectivity_radius)))
    if use_cell_list is None:
        use_cell_list = n >= CELL_LIST_MIN_PARTICLES and cell_list_possible(
            frames.shape[-1], connectivity_radius=connectivity_radius, bounds=bounds
        )
    cell = None
    if use_cell_list:
        occupancy = host_max_cell_occupancy(frames, mask, connectivity_radius=connectivity_radius, bounds=bounds)
        cell = max(4, math.ceil(occupancy * (1.0 + 4 * margin)) + 1)
    return GraphCapacity(edges=min(round_capacity(pairs, margin=margin), n * (n - 1)), cell=cell)


def _rung(need: int) -> int:
    """The smallest ``ceil(2^(k/4))``, ``k = 0, 1, ...``, that is ``>= need`` (rungs at most ~19 % apart)."""
    k = max(0, 4 * (max(int(need), 1).bit_length() - 1))
    while math.ceil(2.0 ** (k / 4)) < need:
        k += 1
    return math.ceil(2.0 ** (k / 4))


def _coarse_rung(need: int) -> int:
    """The smallest ``2^k`` or ``3 x 2^(k-1)`` that is ``>= need``."""
    power = 1 << max(int(need) - 1, 0).bit_length()
    return power * 3 // 4 if power >= 4 and power * 3 // 4 >= need else power


def on_ladder(capacity: GraphCapacity, n: int | None = None, *, quantum: int = 64) -> GraphCapacity:
    """``capacity`` rounded up to the next rung of a fixed geometric ladder (edges and cells).

    A capacity sized from data differs by a few pairs from one trajectory or
    call to the next, and every new one is a new compilation. Rounded up to
    rungs about 19 % apart (edges in multiples of ``quantum``) the capacities
    repeat, so later rollouts and steps reuse the programs compiled for
    earlier ones. Capped at all pairs (edges) and at ``n`` (cells) when the
    particle count ``n`` is given; never below ``capacity``.
    """
    edges = max(quantum * _rung(math.ceil(capacity.edges / quantum)), capacity.edges)
    # Cells on a coarser ladder (2^k and 1.5 x 2^k): a cell's head-room is cheap, and the fullest cell of a
    # settling bed varies more between trajectories than the pair count does.
    cell = None if capacity.cell is None else _coarse_rung(capacity.cell)
    if n is not None:
        edges = max(min(edges, n * (n - 1)), capacity.edges)
        cell = None if cell is None else max(min(cell, n), capacity.cell)
    return GraphCapacity(edges=edges, cell=cell)


def grow_capacity(capacity: GraphCapacity, n: int | None = None, factor: float = 1.5) -> GraphCapacity:
    """A larger capacity after an overflow (edges and cells grown by ``factor``; capped at all pairs)."""
    edges = round_capacity(int(capacity.edges * factor), margin=0.0)
    if n is not None:
        edges = min(edges, n * (n - 1))
    cell = None if capacity.cell is None else max(capacity.cell + 2, math.ceil(capacity.cell * factor))
    if n is not None and cell is not None:
        cell = min(cell, n)
    return GraphCapacity(edges=edges, cell=cell)
