"""Explicit-Euler integration of the suspension: the pure ``init``/``step`` pair, a pure scan, host drivers.

The state is a frozen pytree (:class:`SimState`); the step is a pure function
of it, so it can be jitted, vmapped over trajectories, differentiated and
scanned. Capacities (colliding particles evaluated per step, neighbour-list
sizes) are static; overflowing one is a flag, never silently ignored:

* pure: :func:`euler_integrator` (``init_fn, step_fn``) and
  :func:`simulate_scan` (all frames as one ``lax.scan``, overflow flags
  returned, frames after an overflow NaN);
* host: :func:`simulate` and :func:`simulate_batch` take concrete arrays, run
  the trajectory in compiled chunks with neighbour lists, and grow a
  capacity and redo the chunk after an overflow
  (:func:`dispgns.capacity.drive`).

Units are SI: positions in m, velocities in m/s, radii in m, time in s.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import dataclasses as md_dataclasses
from jax_md import partition
from jaxtyping import ArrayLike, Float

from dispgns.arrays import (
    BatchFrame,
    BatchMask,
    BatchPositions,
    BatchRadii,
    Count,
    Flag,
    Frame,
    FrameFlags,
    ParticleMask,
    Positions,
    Radii,
    host_array,
)
from dispgns.capacity import Attempt, coarse_ladder, drive, ladder
from dispgns.physics.config import PhysicsConfig
from dispgns.physics.forces import external_force, interaction_force, neighbor_force, neighbor_table, particle_mass
from dispgns.physics.walls import WallCounts, resolve_walls
from dispgns.tuning import jitted
from dispgns.validation import check_particles

# One frame ``(N, D)`` or a batch of them ``(B, N, D)``.
_OneOrBatch = Float[ArrayLike, "*B N D"]

__all__ = [
    "PhysicsCapacity",
    "SimState",
    "SimulatedFrames",
    "euler_integrator",
    "neighbor_fn_for",
    "simulate",
    "simulate_batch",
    "simulate_scan",
    "update_neighbors",
]


@md_dataclasses.dataclass
class SimState:
    """State of a suspension between Euler steps (a pytree).

    Attributes:
      position: ``(N, D)`` centres in m.
      velocity: ``(N, D)`` in m/s.
      radius: ``(N,)`` in m.
      mask: ``(N,)`` bool, ``False`` for padding particles; they do not move,
        exert no force and never collide.
      mass: ``(N,)`` kg, and ``external``: ``(N, D)`` buoyant weight in N,
        precomputed once because they do not change.
      wall_hits: ``(2 D,)`` int32, cumulative wall crossings per wall (right,
        left, top, bottom in 2-D; a corner crossing counts on both walls).
      corner_events: int32, cumulative multi-axis crossings.
      overflow: bool, a step needed more colliding-particle capacity than it
        had; the state is then wrong and must be recomputed.
      step: int32, Euler steps taken.
    """

    position: Frame
    velocity: Frame
    radius: Radii
    mask: ParticleMask
    mass: Radii
    external: Frame
    wall_hits: WallCounts
    corner_events: Count
    overflow: Flag
    step: Count


def _far_away_positions(count: int, dim: int, spacing: float, box_half_size: float, dtype) -> jnp.ndarray:
    # box_half_size: the largest half-size over the axes (m).
    """Positions for padding particles: outside the box, farther than ``spacing`` apart."""
    offsets = (3.0 * box_half_size + spacing * jnp.arange(1, count + 1, dtype=dtype))[:, None]
    return jnp.broadcast_to(offsets, (count, dim)).astype(dtype)


def _park_padding(position: jnp.ndarray, mask: jnp.ndarray, config: PhysicsConfig) -> jnp.ndarray:
    """Move padding particles far outside the box, apart from each other.

    Neighbour lists then never pair them, and whatever the caller left in
    padding rows (NaN included) never enters the arithmetic: a masked pair
    contributes ``0 * displacement``, which is 0 only for finite values.
    """
    n, dim = position.shape
    largest = config.largest_half_size
    reach = 2.0 * largest if config.cutoff is None else config.cutoff + config.neighbor_skin
    spacing = 1.01 * reach
    parked = _far_away_positions(n, dim, spacing, largest, position.dtype)
    return jnp.where(mask[:, None], position, parked)


# Neighbour capacities (cell slots and list slots) are this factor above the
# occupancy seen at allocation, as jax-md does.
_CAPACITY_MULTIPLIER = 1.25


def _half_sizes(config: PhysicsConfig, dim: int, dtype):
    """The box half-sizes ``(D,)`` in m: the shift from the box frame into the cell-list frame."""
    if not isinstance(config.box_half_size, tuple):
        return config.box_half_size  # a Python float, as before: the square box's arithmetic is unchanged
    return np.asarray(config.half_sizes(dim), dtype)


def _cell_grid(config: PhysicsConfig, dim: int) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Cells per axis and cell side per axis in m of the grid over ``[0, 2 h_0] x ... x [0, 2 h_{D-1}]``.

    Cells are at least the list radius ``cutoff + neighbor_skin`` wide, so
    every pair within it lies in the same or adjacent cells.
    """
    reach = config.cutoff + config.neighbor_skin
    per_side, sizes = [], []
    for half in config.half_sizes(dim):
        box = 2.0 * half
        count = max(1, int(box // reach))
        while count > 1 and box / count < reach:
            count -= 1
        per_side.append(count)
        sizes.append(box / count)
    return tuple(per_side), tuple(sizes)


def _flat_cell(coordinate: jnp.ndarray, per_side: tuple[int, ...]) -> jnp.ndarray:
    """Row-major cell number of integer cell coordinates ``(..., D)``."""
    flat = coordinate[..., 0]
    for d in range(1, coordinate.shape[-1]):
        flat = flat * per_side[d] + coordinate[..., d]
    return flat


def _cells(position: jnp.ndarray, config: PhysicsConfig):
    """Integer cell coordinates ``(N, D)`` (clipped into the grid) and ``parked`` ``(N,)``.

    Parked particles (padding, placed far outside the box) lie more than a
    cell outside the grid: they get no cell and no neighbours.
    """
    per_side, size = _cell_grid(config, position.shape[-1])
    count = np.asarray(per_side, np.int32)
    coordinate = jnp.floor(position / np.asarray(size, position.dtype)).astype(jnp.int32)
    parked = jnp.any((coordinate < -1) | (coordinate > count), axis=-1)
    return jnp.clip(coordinate, 0, count - 1), parked


@functools.partial(jax.jit, static_argnames=("config", "cell_capacity", "max_neighbors"))
def _build_neighbors(position, error, config: PhysicsConfig, cell_capacity: int, max_neighbors: int):
    """Dense neighbour list of ``position`` ``(N, D)`` (m, in ``[0, 2L]^D``) from a cell list.

    Returns ``idx`` ``(N, max_neighbors)`` (``N`` marks empty slots), the
    most neighbours any particle has, and ``error`` with the overflow bits
    set when a cell held more than ``cell_capacity`` particles or a particle
    more than ``max_neighbors`` neighbours. Shaped for XLA on CPU, where
    sorts, cumulative sums and distances reduced over a minor axis of size D
    are slow: the cell table is filled by ``C`` rounds of one scatter per
    particle instead of an argsort, distances are per axis, and list slots
    come from population counts instead of a cumsum over the candidates.
    ``C = cell_capacity``; the order inside a list is deterministic (by cell,
    then by particle index).
    """
    n, dim = position.shape
    per_side, _ = _cell_grid(config, dim)
    n_cells = math.prod(per_side)
    coordinate, parked = _cells(position, config)
    cell = _flat_cell(coordinate, per_side)

    # Cell table (n_cells + 1, C): round s puts the smallest particle not yet
    # placed of every cell into slot s; the extra row stays empty (id N).
    ids = jnp.arange(n, dtype=jnp.int32)
    size = (n_cells + 1) * cell_capacity

    def place(s, carry):
        table, placed = carry
        target = jnp.where(placed, size, cell * cell_capacity + s)
        table = table.at[target].min(ids, mode="drop")
        return table, placed | (table[jnp.minimum(target, size - 1)] == ids)

    table, placed = lax.fori_loop(0, cell_capacity, place, (jnp.full((size,), n, jnp.int32), parked))
    table = table.reshape(n_cells + 1, cell_capacity)

    # Candidates: the particles of the 3^D cells around each particle's own
    # (one cell when the grid has a single cell per side).
    steps = [(0,) if count == 1 else (-1, 0, 1) for count in per_side]
    offsets = np.array(list(itertools.product(*steps)), np.int32)
    around = coordinate[:, None, :] + offsets[None]
    inside = jnp.all((around >= 0) & (around < np.asarray(per_side, np.int32)), axis=-1) & ~parked[:, None]
    candidate = table[jnp.where(inside, _flat_cell(around, per_side), n_cells)].reshape(n, -1)
    padded = jnp.concatenate([position, jnp.zeros((1, dim), position.dtype)])
    other = padded[candidate]
    r2 = sum((position[:, d][:, None] - other[..., d]) ** 2 for d in range(dim))
    reach = config.cutoff + config.neighbor_skin
    valid = (candidate < n) & (candidate != ids[:, None]) & (r2 < reach**2)

    # Slot of each valid candidate = number of valid candidates before it.
    # Per group of <= 31 candidates the flags form one int32 whose population
    # count below a bit gives the rank inside the group.
    width = min(cell_capacity, 31)
    groups = -(-valid.shape[1] // width)
    flags = jnp.pad(valid, ((0, 0), (0, groups * width - valid.shape[1]))).reshape(n, groups, width)
    bit = jnp.arange(width, dtype=jnp.int32)
    bits = jnp.sum(jnp.where(flags, jnp.left_shift(1, bit), 0), axis=-1)
    in_group = lax.population_count(bits)
    before_group = jnp.cumsum(in_group, axis=1) - in_group
    below = lax.population_count(bits[..., None] & (jnp.left_shift(1, bit) - 1))
    slot = (before_group[..., None] + below).reshape(n, -1)[:, : valid.shape[1]]
    count = before_group[:, -1] + in_group[:, -1]
    keep = valid & (slot < max_neighbors)
    target = jnp.where(keep, ids[:, None] * max_neighbors + slot, n * max_neighbors)
    idx = jnp.full((n * max_neighbors,), n, jnp.int32).at[target.ravel()].set(candidate.ravel(), mode="drop")

    pec = partition.PartitionErrorCode
    error = error.update(pec.CELL_LIST_OVERFLOW, ~jnp.all(placed))
    error = error.update(pec.NEIGHBOR_LIST_OVERFLOW, jnp.max(count, initial=0) > max_neighbors)
    return idx.reshape(n, max_neighbors), jnp.max(count, initial=0), error


@functools.cache
def neighbor_fn_for(config: PhysicsConfig, dim: int) -> partition.NeighborListFns:
    """Cell-list neighbour functions for ``config.cutoff`` (cached per config).

    Returns jax-md ``NeighborListFns``: ``allocate(position, extra_capacity=0)``
    (outside ``jit``; sizes the cell and list capacities from the occupancy
    it sees, times 1.25, plus ``extra_capacity``) and ``update(position,
    neighbors)``, which always rebuilds at the list's capacities and sets
    ``did_buffer_overflow`` when they are exceeded. The lists are jax-md
    dense ``NeighborList`` s of radius ``cutoff + neighbor_skin``;
    :func:`update_neighbors` decides when a rebuild is due (from the
    distances moved since the last build and the particles' speeds).
    Positions are passed shifted by ``+L`` so that they lie in ``[0, 2L]``;
    padding particles parked outside the box get no neighbours.
    """
    if config.cutoff is None:
        raise ValueError("neighbour lists need PhysicsConfig.cutoff to be set (got None = all pairs)")
    per_side, cell_size = _cell_grid(config, dim)
    cell_size = cell_size[0] if len(set(cell_size)) == 1 else np.asarray(cell_size)

    def make(position, idx, error, cell_capacity, max_neighbors):
        return partition.NeighborList(
            idx,
            position,
            error,
            cell_capacity,
            max_neighbors,
            partition.NeighborListFormat.Dense,
            cell_size,
            None,
            update_fn,
        )

    def update_fn(position, neighbors, **unused):
        cell_capacity, max_neighbors = neighbors.cell_list_capacity, neighbors.max_occupancy
        idx, _, error = _build_neighbors(position, neighbors.error, config, cell_capacity, max_neighbors)
        return make(position, idx, error, cell_capacity, max_neighbors)

    def allocate_fn(position, extra_capacity: int = 0, **unused):
        position = jnp.asarray(position)
        n = position.shape[0]
        coordinate, parked = (np.asarray(a) for a in _cells(position, config))
        strides = np.cumprod((1,) + per_side[:0:-1])[::-1]
        cells = coordinate[~parked] @ strides
        occupancy = int(np.bincount(cells).max(initial=0))
        cell_capacity = max(1, int(occupancy * _CAPACITY_MULTIPLIER)) + extra_capacity
        candidates = math.prod(1 if count == 1 else 3 for count in per_side) * cell_capacity
        error = partition.PartitionError(jnp.zeros((), jnp.uint8))
        idx, most, error = _build_neighbors(position, error, config, cell_capacity, candidates)
        max_neighbors = int(int(most) * _CAPACITY_MULTIPLIER + extra_capacity)
        max_neighbors = max(1, min(max_neighbors, candidates, n - 1))
        return make(position, idx[:, :max_neighbors], error, cell_capacity, max_neighbors)

    return partition.NeighborListFns(allocate_fn, update_fn)


def update_neighbors(
    neighbors: partition.NeighborList,
    position: _OneOrBatch,
    config: PhysicsConfig,
    velocity: _OneOrBatch | None = None,
) -> partition.NeighborList:
    """Rebuild ``neighbors`` when the coming step could need a pair it lacks.

    A list built at radius ``cutoff + skin`` holds every pair the step needs
    while ``max_i (d_i + e_i) + max_j d_j <= skin``, where ``d`` is the
    distance moved since the build and ``e_i`` how far particle ``i``'s trial
    positions (wall contact points) lie from it. Contact points lie on the
    step's path, so with ``velocity`` given, ``e_i`` is bounded by
    ``2 dt |v_i|`` (twice the Euler displacement leaves room for a second,
    corner contact after a reflection); without it, every particle may
    move ``skin / 4`` and ``e`` gets the other half of the skin.

    Works on one list (``position (N, D)``) or a stack of lists
    (``position (B, N, D)``); for a stack the decision is taken once for the
    whole batch, so the rebuild is skipped, not merely masked, on most steps.
    Positions are in m, in the box frame (the shift into the cell-list frame
    happens here); ``velocity``, like ``position``, in m/s.
    """
    shifted = position + _half_sizes(config, position.shape[-1], position.dtype)
    moved = jnp.sqrt(jnp.sum((shifted - neighbors.reference_position) ** 2, axis=-1))
    if velocity is None:
        due = jnp.max(moved) > 0.25 * config.neighbor_skin
    else:
        reach = 2.0 * config.dt * jnp.sqrt(jnp.sum(velocity**2, axis=-1))
        due = jnp.max(moved + reach) + jnp.max(moved) > config.neighbor_skin
    if position.ndim == 2:
        rebuild = lambda: neighbors.update(shifted)
    else:
        rebuild = lambda: jax.vmap(lambda x, nbrs: nbrs.update(x))(shifted, neighbors)
    return lax.cond(due, rebuild, lambda: neighbors)


def euler_integrator(
    config: PhysicsConfig, *, collision_capacity: int | None = None
) -> tuple[Callable[..., SimState], Callable[..., SimState]]:
    """The model's explicit-Euler integrator as a pair of pure functions.

    Args:
      config: physics parameters (static).
      collision_capacity: static; how many wall-colliding particles per step
        get their contact-point force evaluated. ``None`` evaluates all N
        (exact, can never overflow, about twice the cost of a step without
        collisions); a small number is much cheaper and sets
        ``state.overflow`` when exceeded.

    Returns:
      ``(init_fn, step_fn)``:

      * ``init_fn(position, velocity, radius, mask=None)`` builds a
        :class:`SimState`.
      * ``step_fn(state, neighbors=None)`` advances one Euler step of
        ``config.dt`` seconds. With ``config.cutoff`` set, pass a jax-md
        neighbour list for linear cost: allocate it outside ``jit`` with
        ``neighbor_fn_for(config, D).allocate(position + L)`` and refresh it
        before every step with :func:`update_neighbors` (passing the
        velocities makes rebuilds rarer), checking
        ``did_buffer_overflow`` afterwards. Without one, pairs are still cut
        off at ``config.cutoff`` but found by the all-pairs ``N x N`` path.

    On the CPU, ``jax.jit(loop, compiler_options=dispgns.tuning.physics_compiler_options())``
    compiles a loop over ``step_fn`` as :func:`simulate` compiles its own
    (512-bit vector loops, ~1.6x faster on AVX-512 machines). JAX accepts
    the options on the outermost jit only: ``jax.jit(jax.grad(loss), ...)``,
    not ``jax.grad`` of a jit with options.
    """

    def init_fn(position, velocity, radius, mask=None) -> SimState:
        position = jnp.asarray(position)
        dtype = position.dtype
        velocity = jnp.asarray(velocity, dtype)
        radius = jnp.asarray(radius, dtype)
        n, dim = position.shape
        mask = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
        position = _park_padding(position, mask, config)
        velocity = jnp.where(mask[:, None], velocity, 0.0)
        # Padding radii are replaced by a harmless positive value.
        radius = jnp.where(mask, radius, jnp.max(jnp.where(mask, radius, 0.0)))
        return SimState(
            position=position,
            velocity=velocity,
            radius=radius,
            mask=mask,
            mass=particle_mass(radius, config, dim),
            external=external_force(radius, config, dim),
            wall_hits=jnp.zeros((2 * dim,), jnp.int32),
            corner_events=jnp.zeros((), jnp.int32),
            overflow=jnp.zeros((), bool),
            step=jnp.zeros((), jnp.int32),
        )

    def step_fn(state: SimState, neighbors: partition.NeighborList | None = None) -> SimState:
        x, v, a, mask = state.position, state.velocity, state.radius, state.mask
        n = x.shape[0]
        if neighbors is None:

            def force_at(query, query_index):
                return interaction_force(query, query_index, x, a, mask, config)

            start_force = force_at(x, jnp.arange(n))
        else:
            # The gathered table is shared by the start-of-step force and the
            # wall contact points; the start force reads the list rows in order.
            table = neighbor_table(x, a, mask)

            def force_at(query, query_index):
                rows = neighbors.idx[jnp.minimum(query_index, n - 1)]
                return neighbor_force(query, query_index, rows, table, config)

            start_force = neighbor_force(x, jnp.arange(n), neighbors.idx, table, config)
        inv_mass = (1.0 / state.mass)[:, None]
        drag = (config.drag * a)[:, None]
        euler_velocity = v + config.dt * inv_mass * (state.external - drag * v + start_force)
        euler_position = x + config.dt * v
        walls = resolve_walls(
            x,
            v,
            euler_position,
            euler_velocity,
            start_force,
            a,
            state.mass,
            state.external,
            mask,
            config,
            force_at,
            collision_capacity,
        )
        select = mask[:, None]
        return state.set(
            position=jnp.where(select, walls.position, x),
            velocity=jnp.where(select, walls.velocity, v),
            wall_hits=state.wall_hits + walls.wall_hits.astype(jnp.int32),
            corner_events=state.corner_events + walls.corner_events.astype(jnp.int32),
            overflow=state.overflow | walls.overflow,
            step=state.step + 1,
        )

    return init_fn, step_fn


def _advance_frames(
    state: SimState, neighbors, *, config: PhysicsConfig, n_frames: int, save_every: int, collision_capacity, batched
):
    """Run ``n_frames * save_every`` steps of one state or a stacked batch of states (pure).

    Returns ``((state, neighbors), (xs, vs, overflow))`` with frames stacked
    on axis 0; ``overflow`` says whether the collision capacity had been
    exceeded by the end of each frame.
    """
    if batched and state.position.shape[0] == 1:
        # A batch of one runs unbatched: XLA's CPU gathers with a batch
        # dimension (neighbour lists under vmap) are about 3x slower.
        squeeze = lambda tree: jax.tree_util.tree_map(lambda leaf: leaf[0], tree)
        expand = lambda tree: jax.tree_util.tree_map(lambda leaf: leaf[None], tree)
        (state, neighbors), (xs, vs, flags) = _advance_frames(
            squeeze(state),
            squeeze(neighbors),
            config=config,
            n_frames=n_frames,
            save_every=save_every,
            collision_capacity=collision_capacity,
            batched=False,
        )
        return (expand(state), expand(neighbors)), (xs[:, None], vs[:, None], flags[:, None])
    _, step_fn = euler_integrator(config, collision_capacity=collision_capacity)
    step = jax.vmap(step_fn) if batched else step_fn

    def one_step(_, carry):
        state, neighbors = carry
        if neighbors is not None:
            neighbors = update_neighbors(neighbors, state.position, config, state.velocity)
        return step(state, neighbors), neighbors

    def frame(carry, _):
        carry = lax.fori_loop(0, save_every, one_step, carry)
        return carry, (carry[0].position, carry[0].velocity, carry[0].overflow)

    return lax.scan(frame, (state, neighbors), None, length=n_frames)


class SimulatedFrames(NamedTuple):
    """Frames of a simulation (a pytree).

    Attributes:
      position: ``(n_frames, N, D)`` in m (frame 0 is the initial state).
      velocity: ``(n_frames, N, D)`` in m/s.
      overflow: ``(n_frames,)`` bool; True from the first frame whose steps
        exceeded the collision capacity on (those frames are NaN).
    """

    position: Positions
    velocity: Positions
    overflow: FrameFlags


def simulate_scan(
    x0: Frame,
    v0: Frame,
    radius: Radii,
    config: PhysicsConfig = PhysicsConfig(),
    *,
    n_frames: int,
    save_every: int = 15,
    mask: ParticleMask | None = None,
    collision_capacity: int | None = None,
) -> SimulatedFrames:
    """Simulate one trajectory as one ``lax.scan`` (pure: ``jit``, ``vmap``, ``grad``).

    Pairs come from the all-pairs path (a finite ``config.cutoff`` is applied
    on it); :func:`simulate` is the host convenience with neighbour lists.

    Args:
      x0: ``(N, D)`` initial centres in m. v0: ``(N, D)`` in m/s. radius: ``(N,)`` in m.
      config: static physics parameters.
      n_frames: static; frames returned (frame 0 is ``x0``), ``save_every``
        Euler steps apart (static).
      mask: optional ``(N,)`` bool, ``False`` for padding particles.
      collision_capacity: static; colliding particles evaluated per step
        (``None``: all, exact, it cannot overflow); a small number is cheaper
        and sets the overflow flags when exceeded.

    Returns:
      :class:`SimulatedFrames`, in the dtype of ``x0``.
    """
    x0, v0, radius, mask = _check_inputs(x0, v0, radius, mask, batched=False)
    _check_frames(n_frames, save_every)
    _check_collision_capacity(collision_capacity, allow_auto=False)
    init_fn, _ = euler_integrator(config, collision_capacity=collision_capacity)
    _, (xs, vs, flags) = _advance_frames(
        init_fn(x0, v0, radius, mask),
        None,
        config=config,
        n_frames=n_frames - 1,
        save_every=save_every,
        collision_capacity=collision_capacity,
        batched=False,
    )
    # A pure run cannot grow its capacity: every frame from the first overflowing one on is NaN.
    poison = jnp.where(flags, jnp.nan, 0.0).astype(xs.dtype)[:, None, None]
    return SimulatedFrames(
        position=_stack_frames(x0, [xs + poison], 0),
        velocity=_stack_frames(v0, [vs + poison], 0),
        overflow=jnp.concatenate([jnp.zeros((1,), bool), flags]),
    )


def _check_frames(n_frames, save_every):
    for name, value in (("n_frames", n_frames), ("save_every", save_every)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def _check_collision_capacity(collision_capacity, *, allow_auto: bool = True):
    if collision_capacity is None or (
        allow_auto and isinstance(collision_capacity, str) and collision_capacity == "auto"
    ):
        return
    if (
        isinstance(collision_capacity, bool)
        or not isinstance(collision_capacity, int | np.integer)
        or collision_capacity < 1
    ):
        allowed = '"auto", None' if allow_auto else "None"
        raise ValueError(f"collision_capacity must be {allowed} or an integer >= 1, got {collision_capacity!r}")


def _stack_frames(first: jnp.ndarray, chunks: list, axis: int) -> jnp.ndarray:
    return jnp.concatenate([jnp.expand_dims(first, axis)] + chunks, axis=axis)


def _check_inputs(x0, v0, radius, mask, batched: bool):
    lead = 3 if batched else 2
    x0 = jnp.asarray(x0)
    if x0.ndim != lead:
        raise ValueError(f"x0 must have shape {'(B, N, D)' if batched else '(N, D)'}, got {x0.shape}")
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.float32)
    v0 = jnp.asarray(v0, x0.dtype)
    radius = jnp.asarray(radius, x0.dtype)
    if v0.shape != x0.shape:
        raise ValueError(f"v0 must have the shape of x0 {x0.shape}, got {v0.shape}")
    if radius.shape != x0.shape[:-1]:
        raise ValueError(f"radius must have shape {x0.shape[:-1]}, got {radius.shape}")
    if mask is None:
        mask = jnp.ones(x0.shape[:-1], bool)
    mask = jnp.asarray(mask, bool)
    if mask.shape != x0.shape[:-1]:
        raise ValueError(f"mask must have shape {x0.shape[:-1]}, got {mask.shape}")
    return x0, v0, radius, mask


def _check_state(x0, v0, radius, mask, config: PhysicsConfig) -> None:
    """The cheap host checks of :mod:`dispgns.validation` on a physics state (SI units, the box of ``config``)."""
    if x0.shape[-2] == 0 or not bool(np.any(np.asarray(mask))):
        raise ValueError(f"x0 holds no particles (shape {x0.shape}): expected at least one real particle")
    halves = config.half_sizes(x0.shape[-1])
    box = f"L = {halves[0]:g} m" if len(set(halves)) == 1 else f"half-sizes {', '.join(f'{h:g}' for h in halves)} m"
    check_particles(
        np.asarray(x0),
        np.asarray(radius),
        mask=np.asarray(mask),
        velocity=np.asarray(v0),
        bounds=tuple((-h, h) for h in halves),
        box=f"the box ({box})",
        position_name="x0",
        velocity_name="v0",
        radius_below=min(halves),
    )


def simulate(
    x0: Frame,
    v0: Frame,
    radius: Radii,
    config: PhysicsConfig = PhysicsConfig(),
    *,
    n_frames: int,
    save_every: int = 15,
    mask: ParticleMask | None = None,
    return_velocity: bool = False,
    collision_capacity: int | None | str = "auto",
    chunk_frames: int = 50,
    compiler_options: Mapping[str, Any] | None = None,
) -> Positions | tuple[Positions, Positions]:
    """Simulate one trajectory and return its saved frames (host; :func:`simulate_scan` is the pure core).

    The frames are computed in compiled chunks; after a chunk that overflowed
    a capacity (colliding particles, neighbour list) the capacity grows and
    the chunk is redone, so the result is that of unlimited capacities.

    Args:
      x0: concrete ``(N, D)`` initial centres in m, inside ``[-L + a_i, L - a_i]``.
      v0: ``(N, D)`` initial velocities in m/s.
      radius: ``(N,)`` radii in m.
      config: physics parameters.
      n_frames: frames returned, at Euler steps ``0, save_every, ...,
        (n_frames - 1) * save_every`` (frame 0 is ``x0``).
      save_every: Euler steps between frames (15 in the paper: 1.5 ms).
      mask: optional ``(N,)`` bool, ``False`` for padding particles; their
        output rows are meaningless and they never affect real particles.
      return_velocity: also return the velocities at the saved frames.
      collision_capacity: ``"auto"`` (a small capacity, grown on overflow),
        ``None`` (every particle, exact, cannot overflow) or an int >= 1 (the
        starting capacity, grown on overflow).
      chunk_frames: frames per compiled chunk between overflow checks.
      compiler_options: XLA options for the chunks (e.g.
        :func:`dispgns.tuning.physics_compiler_options`).

    Returns:
      positions ``(n_frames, N, D)`` in m (and velocities ``(n_frames, N, D)``
      in m/s if ``return_velocity``), in the dtype of ``x0``: float64 when
      ``x0`` is float64 and ``jax_enable_x64`` is on, float32 otherwise.
    """
    x0, v0, radius, mask = _host_inputs(x0, v0, radius, mask, batched=False, pure="dispgns.simulate_scan")
    _check_state(x0, v0, radius, mask, config)
    _check_frames(n_frames, save_every)
    _check_collision_capacity(collision_capacity)
    settings = (n_frames, save_every, collision_capacity, chunk_frames, compiler_options)
    xs, vs = _drive(x0[None], v0[None], radius[None], mask[None], config, settings)
    return (xs[0], vs[0]) if return_velocity else xs[0]


def simulate_batch(
    x0: BatchFrame,
    v0: BatchFrame,
    radius: BatchRadii,
    mask: BatchMask | None,
    config: PhysicsConfig = PhysicsConfig(),
    *,
    n_frames: int,
    save_every: int = 15,
    return_velocity: bool = False,
    collision_capacity: int | None | str = "auto",
    chunk_frames: int = 50,
    compiler_options: Mapping[str, Any] | None = None,
    progress: Callable[[int], None] | None = None,
) -> BatchPositions | tuple[BatchPositions, BatchPositions]:
    """Simulate B trajectories with different particle counts in one vmapped call (host).

    Trajectories are padded to a common ``N``; padding particles
    (``mask == False``) never touch real ones, so each real trajectory equals
    its own :func:`simulate` run up to float summation order. Under ``jit``,
    ``jax.vmap(simulate_scan)`` is the pure equivalent.

    Args:
      x0, v0: concrete ``(B, N, D)`` initial positions (m) and velocities (m/s).
      radius: ``(B, N)`` radii in m. mask: ``(B, N)`` bool.
      progress: optional callable receiving the number of frames completed
        after each chunk (for progress bars).
      Other arguments as in :func:`simulate`.

    Returns:
      positions ``(B, n_frames, N, D)`` in m (and velocities if asked).
    """
    x0, v0, radius, mask = _host_inputs(x0, v0, radius, mask, batched=True, pure="jax.vmap(dispgns.simulate_scan)")
    _check_state(x0, v0, radius, mask, config)
    _check_frames(n_frames, save_every)
    _check_collision_capacity(collision_capacity)
    settings = (n_frames, save_every, collision_capacity, chunk_frames, compiler_options)
    xs, vs = _drive(x0, v0, radius, mask, config, settings, progress=progress)
    return (xs, vs) if return_velocity else xs


def _host_inputs(x0, v0, radius, mask, *, batched: bool, pure: str):
    """Concrete inputs of a host driver, as jax arrays (a traced input raises and names the pure core)."""
    arrays = [host_array(value, name, pure=pure) for value, name in ((x0, "x0"), (v0, "v0"), (radius, "radius"))]
    if mask is not None:
        mask = host_array(mask, "mask", pure=pure)
    # jnp.asarray keeps float64 when x64 is on (numpy float64 inputs otherwise become float32).
    return _check_inputs(*(jnp.asarray(a) for a in arrays), mask, batched=batched)


@dataclasses.dataclass(frozen=True)
class PhysicsCapacity:
    """Static capacities of a chunk of physics steps (hashable: a jit cache key).

    Attributes:
      collisions: colliding particles evaluated per step (``None``: all of them).
      cell: particles per cell of the neighbour cell list (``None``: no neighbour list).
      neighbors: neighbours per particle in the list (``None``: no neighbour list).
    """

    collisions: int | None
    cell: int | None = None
    neighbors: int | None = None


class _Run(NamedTuple):
    """The driver's state: the simulation, its neighbour lists, and what overflowed in the last attempt."""

    state: SimState
    neighbors: Any
    collisions_overflowed: bool = False
    neighbors_overflowed: bool = False


def _neighbor_capacity(position, mask, config: PhysicsConfig, grown_from: PhysicsCapacity | None = None):
    """``(cell, neighbors)`` capacities, on the ladder, for the lists of ``position`` ``(B, N, D)`` (m, host).

    jax-md's allocation sizes them from the occupancy it sees, times 1.25;
    after an overflow (``grown_from``) they also grow by at least 25 %.
    """
    neighbor_fn = neighbor_fn_for(config, position.shape[-1])
    lists = [neighbor_fn.allocate(x) for x in _shifted(position, mask, config)]
    cell = coarse_ladder(max(nbrs.cell_list_capacity for nbrs in lists))
    neighbors = ladder(max(nbrs.max_occupancy for nbrs in lists))
    if grown_from is not None:
        cell = coarse_ladder(max(cell, math.ceil(1.25 * grown_from.cell)))
        neighbors = ladder(max(neighbors, math.ceil(1.25 * grown_from.neighbors)))
    return cell, max(1, min(neighbors, position.shape[1] - 1))


def _neighbor_lists(position, mask, config: PhysicsConfig, capacity: PhysicsCapacity):
    """Neighbour lists of ``position`` ``(B, N, D)`` (m) at ``capacity``'s static sizes, stacked on axis 0."""
    neighbor_fn = neighbor_fn_for(config, position.shape[-1])
    shifted = _shifted(position, mask, config)
    template = md_dataclasses.replace(
        neighbor_fn.allocate(shifted[0]), cell_list_capacity=capacity.cell, max_occupancy=capacity.neighbors
    )
    lists = [neighbor_fn.update(x, template) for x in shifted]
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *lists)


def _shifted(position, mask, config: PhysicsConfig) -> list:
    """Each trajectory's positions in the cell-list frame ``[0, 2L]^D``, padding parked outside."""
    half = _half_sizes(config, position.shape[-1], position.dtype)
    return [_park_padding(position[b], mask[b], config) + half for b in range(position.shape[0])]


def _drive(x0, v0, radius, mask, config, settings, progress=None):
    """Chunked, overflow-checked run of B trajectories with :func:`dispgns.capacity.drive`.

    ``settings``: ``(n_frames, save_every, collision_capacity, chunk_frames,
    compiler_options)`` of :func:`simulate`. Returns ``(B, n_frames, N, D)`` positions and velocities. A chunk that
    overflowed is redone from its start with the grown capacity.
    """
    n_frames, save_every, collision_capacity, chunk_frames, compiler_options = settings
    n = x0.shape[1]
    if collision_capacity == "auto":
        collisions = min(n, ladder(max(16, math.ceil(n / 8))))
    else:
        collisions = collision_capacity
    capacity = PhysicsCapacity(collisions=collisions)
    neighbors = None
    if config.cutoff is not None:
        cell, slots = _neighbor_capacity(x0, mask, config)
        capacity = dataclasses.replace(capacity, cell=cell, neighbors=slots)
        neighbors = _neighbor_lists(x0, mask, config, capacity)
    init_fn, _ = euler_integrator(config)
    start = _Run(jax.vmap(init_fn)(x0, v0, radius, mask), neighbors)
    # Every chunk has the same length (one compilation); the last one may run
    # past n_frames and its extra frames are dropped.
    length = max(1, min(chunk_frames, n_frames - 1))
    advance = jitted(
        _advance_frames,
        compiler_options,
        static_argnames=("config", "n_frames", "save_every", "collision_capacity", "batched"),
    )

    def attempt(run: _Run, capacity: PhysicsCapacity, remaining: int) -> Attempt:
        neighbors = run.neighbors
        if neighbors is not None and (neighbors.cell_list_capacity, neighbors.max_occupancy) != (
            capacity.cell,
            capacity.neighbors,
        ):
            neighbors = _neighbor_lists(run.state.position, mask, config, capacity)
        (state, new_neighbors), (xs, vs, _) = advance(
            run.state,
            neighbors,
            config=config,
            n_frames=length,
            save_every=save_every,
            collision_capacity=capacity.collisions,
            batched=True,
        )
        collided = bool(np.any(np.asarray(state.overflow)))
        crowded = new_neighbors is not None and bool(np.any(np.asarray(new_neighbors.did_buffer_overflow)))
        if collided or crowded:
            return Attempt(
                run._replace(neighbors=neighbors, collisions_overflowed=collided, neighbors_overflowed=crowded),
                None,
                0,
                True,
            )
        keep = min(length, remaining)
        frames = (jnp.swapaxes(xs[:keep], 0, 1), jnp.swapaxes(vs[:keep], 0, 1))
        return Attempt(_Run(state, new_neighbors), frames, keep, False)

    def grow(capacity: PhysicsCapacity, run: _Run) -> PhysicsCapacity:
        if run.collisions_overflowed:
            capacity = dataclasses.replace(capacity, collisions=min(n, ladder(2 * capacity.collisions)))
        if run.neighbors_overflowed:
            cell, slots = _neighbor_capacity(run.state.position, mask, config, grown_from=capacity)
            capacity = dataclasses.replace(capacity, cell=cell, neighbors=slots)
        return capacity

    total = n_frames - 1
    _, chunks, _ = drive(attempt, start, capacity, grow, total=total, progress=progress) if total else (None, [], None)
    positions = _stack_frames(x0, [xs for xs, _ in chunks], 1)
    velocities = _stack_frames(v0, [vs for _, vs in chunks], 1)
    return positions, velocities
