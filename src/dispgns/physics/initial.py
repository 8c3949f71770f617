"""The authors' initial-condition protocol for sedimentation trajectories (SI units)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import DTypeLike

from dispgns.arrays import Frame, ParticleMask, PRNGKey, Radii
from dispgns.capacity import Attempt, coarse_ladder, drive, ladder
from dispgns.physics.config import PhysicsConfig

__all__ = [
    "MAX_PARTICLES",
    "RANDOM_PACKING_LIMIT",
    "InitialState",
    "PlacementError",
    "particle_count_range",
    "place_particles",
    "sample_initial_state",
]


class InitialState(NamedTuple):
    """A sampled initial state.

    Attributes:
      position: ``(N, D)`` centres in m. velocity: ``(N, D)`` in m/s (one
      common velocity for all particles). radius: ``(N,)`` in m.
      start_height: the lower edge ``y0`` (m) of the region the particles
      were placed in.
    """

    position: Frame
    velocity: Frame
    radius: Radii
    start_height: float


class PlacementError(RuntimeError):
    """The requested packing could not be placed without overlaps."""


def particle_count_range(
    start_height: float,
    max_radius: float,
    config: PhysicsConfig,
    dim: int = 2,
    *,
    radii_choices: Sequence[float] | None = None,
) -> tuple[int, int]:
    """Inclusive range of particle counts the protocol draws from.

    ``N_max = prod_{d < D-1} (2 h_d) * (h_{D-1} - y0) / (2 a_max)^D`` cubes of
    side ``2 a_max`` fit the placement region (the box above ``y0``, with the
    half-sizes ``h_d`` of ``config``; ``(2L)^(D-1) (L - y0) / (2 a_max)^D`` in
    the paper's square box); the protocol draws ``N`` uniformly from
    ``floor(0.7 N_max) ... floor(0.7 N_max) + 3``.

    Given ``radii_choices`` (m, drawn uniformly), the count is capped where
    random placement cannot reach it: when ``0.7 N_max`` particles of the mean
    ball volume would fill more than :data:`RANDOM_PACKING_LIMIT` of the
    region (one radius or a narrow list: ``0.7 pi / 4 = 0.55`` for equal
    disks, above where random sequential placement jams), the range moves
    down so that its largest count fills at most that fraction. The paper's radii
    lists stay well below it (area fractions 0.29-0.39 in 2-D, volume
    fractions 0.16-0.23 in 3-D), so their counts are the protocol's.
    """
    region = _region_volume(config.half_sizes(dim), start_height)
    n_scale = int(0.7 * region / (2.0 * max_radius) ** dim)
    limit = RANDOM_PACKING_LIMIT.get(dim)
    if radii_choices is not None and limit is not None:
        mean_volume = float(np.mean(_ball_volume(np.asarray(radii_choices, dtype=float), dim)))
        if (n_scale + 3) * mean_volume > limit * region:
            # Never below 1 where the protocol itself places one or more (huge radii: a few particles).
            n_scale = min(n_scale, max(1, int(limit * region / mean_volume) - 3))
    if n_scale + 3 > _MAX_PARTICLES:
        raise ValueError(
            f"largest radius {max_radius} m gives {n_scale:,} particles in the box, more than the "
            f"{_MAX_PARTICLES:,} particle indices can address: use larger radii"
        )
    return n_scale, n_scale + 3


def _region_volume(half_sizes: Sequence[float], start_height: float) -> float:
    """Volume (area in 2-D) in m^D of the box above ``start_height``."""
    horizontal = 1.0
    for half in half_sizes[:-1]:
        horizontal *= 2.0 * half
    return horizontal * (half_sizes[-1] - start_height)


def _ball_volume(radius, dim: int):
    """Volume of a ``dim``-ball (area of a disk in 2-D)."""
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1) * radius**dim


# The default size guard of sample_initial_state: its arrays and the simulation after it grow with N,
# and a radius typed in the wrong unit asks for tens of millions of particles.
MAX_PARTICLES = 1_000_000

# The packing fraction (of the placement region) the protocol's count may fill, per dimension. Random
# sequential placement of equal disks jams near 0.55 (spheres 0.38) in an unbounded region; with the
# 4,096 draws per particle of sample_initial_state and the walls it reached (all of 4 seeds) 0.47 for
# 3 mm disks in the paper's box, 0.28 for 3 mm and 0.27 for 4 mm spheres in the paper3d cube, and
# failed at 0.49 and 0.29-0.31. The limits keep a margin below those.
RANDOM_PACKING_LIMIT = {2: 0.45, 3: 0.25}

# Particles placed per compiled call of place_particles (Ctrl-C is seen between calls).
_BLOCK = 4096

# Particle indices (neighbour lists, graphs) are int32.
_MAX_PARTICLES = 2**31 - 1


class _Grid(NamedTuple):
    """Static cell grid over the whole box for the overlap test (hashable: a jit cache key).

    ``per_side[d]`` cells of side ``size[d]`` m along axis ``d``; every side is
    at least ``2 a_max``, so two particles that overlap lie in the same or
    adjacent cells.
    """

    per_side: tuple[int, ...]
    size: tuple[float, ...]


def _grid_for(half_sizes: Sequence[float], max_radius: float, n: int) -> _Grid:
    dim = len(half_sizes)
    volume = math.prod(2.0 * h for h in half_sizes)
    # Cells at least 2 a_max wide; and not many more cells than particles
    # (tiny radii in a large box), which would only cost memory.
    side = max(2.0 * max_radius, (volume / (4.0 * n + 16.0)) ** (1.0 / dim))
    per_side = tuple(max(1, int(2.0 * h // side)) for h in half_sizes)
    return _Grid(per_side, tuple(2.0 * h / c for h, c in zip(half_sizes, per_side)))


def _cell_capacity_bound(grid: _Grid, min_radius: float, n: int) -> int:
    """Most non-overlapping particles of radius >= ``min_radius`` whose centres fit in one cell.

    Their balls lie inside the cell grown by ``min_radius`` on every side and
    do not overlap, so their count is at most that volume over one ball's.
    """
    grown = math.prod(s + 2.0 * min_radius for s in grid.size)
    return max(1, min(n, int(grown / _ball_volume(min_radius, len(grid.size)))))


def place_particles(
    key: PRNGKey,
    radius: Radii,
    start_height: float,
    config: PhysicsConfig,
    *,
    dim: int = 2,
    candidates: int = 64,
    max_rounds: int = 64,
) -> tuple[Frame, ParticleMask]:
    """Place particles one at a time, in index order, without overlap (jit-compiled, cost linear in N).

    Particle ``i`` is drawn uniformly in ``[-h_d + a_i, h_d - a_i]`` on every
    horizontal axis ``d`` and in ``[y0 + a_i, h_{D-1} - a_i]`` on the last
    (vertical) one, with the half-sizes ``h_d`` of ``config.box_half_size``,
    and rejected if it is closer than ``a_i + a_j`` to a particle already
    placed. ``candidates`` draws are tested at once per round, up to
    ``max_rounds`` rounds per particle; the first draw that fits is kept.

    The overlap test looks only at the particles in the ``3^D`` cells around
    a draw (cells at least ``2 max(radius)`` wide), so it finds exactly the
    overlaps an all-pairs test finds and placing ``N`` particles costs
    ``O(N)`` (92,000 disks: 60 s on a 2-core machine under heavy load, mostly
    compilation). The cells hold a static number
    of particles each; when a cell fills up, the placement stops there, the
    capacity grows outside ``jit`` and the placement goes on
    (:func:`dispgns.capacity.drive`), so the result never depends on it.

    Args:
      key: PRNG key. radius: ``(N,)`` in m (concrete: the grid is sized from
        it). start_height: ``y0`` in m.
      config, dim, candidates, max_rounds: static.

    Returns:
      ``(position (N, D), placed (N,) bool)``; ``placed[i]`` is ``False`` when
      no valid spot was found for particle ``i`` (its row is then invalid).
    """
    if isinstance(radius, jax.core.Tracer) or isinstance(start_height, jax.core.Tracer):
        raise TypeError("place_particles sizes its cell grid from concrete radii: call it outside jit")
    radius = jnp.asarray(radius)
    n_real = radius.shape[0]
    half_sizes = config.half_sizes(dim)
    if n_real == 0:
        return jnp.zeros((0, dim), radius.dtype), jnp.zeros((0,), bool)
    host_radius = np.asarray(radius, np.float64)
    # Compiled for particle counts on the capacity ladder, not for every count:
    # the rows past n_real are never placed (placement stops at n_real).
    n = ladder(n_real, quantum=16)
    radius = jnp.concatenate([radius, jnp.full((n - n_real,), host_radius.min(), radius.dtype)])
    grid = _grid_for(half_sizes, float(host_radius.max()), n)
    n_cells = math.prod(grid.per_side)
    bound = _cell_capacity_bound(grid, float(host_radius.min()), n)
    # A first guess from the mean occupancy (a few times it); the bound is exact but
    # can be huge for tiny radii (sample_initial_states pads with them).
    guess = coarse_ladder(max(4, math.ceil(3.0 * n / n_cells) + 2))
    capacity = min(bound, guess)
    start_height = jnp.asarray(start_height, radius.dtype)
    state = (
        jnp.zeros((n, dim), radius.dtype),
        jnp.zeros((n,), bool),
        jnp.full((n_cells + 1, capacity), n, jnp.int32),
        jnp.zeros((n_cells + 1,), jnp.int32),
        jnp.zeros((), jnp.int32),
    )

    def run(state, capacity, remaining):
        # At most _BLOCK particles per compiled call: the host regains control between calls, so Ctrl-C
        # (KeyboardInterrupt) stops a long placement within one block. Same keys, same result.
        stop = min(n_real, int(state[4]) + _BLOCK)
        new_state, overflow = _place_jit(
            key, radius, start_height, stop, state, half_sizes, grid, capacity, candidates, max_rounds
        )
        done = int(new_state[4]) - int(state[4])
        return Attempt(new_state, None, done, bool(overflow))

    def grow(capacity, state):
        return min(n, coarse_ladder(capacity + 1))

    def run_padded(state, capacity, remaining):
        # The cell table of a grown capacity: the old one with empty slots appended.
        table = state[2]
        if table.shape[1] < capacity:
            table = jnp.pad(table, ((0, 0), (0, capacity - table.shape[1])), constant_values=n)
            state = state[:2] + (table,) + state[3:]
        return run(state, capacity, remaining)

    state, _, _ = drive(run_padded, state, capacity, grow, total=n_real)
    return state[0][:n_real], state[1][:n_real]


def _place(key, radius, start_height, n_real, state, half_sizes, grid: _Grid, capacity, candidates, max_rounds):
    """Place particles ``state.next ... n_real - 1``; stop before a particle whose cell is full.

    ``state`` = ``(position (N, D), placed (N,), table (cells + 1, C), count
    (cells + 1,), next)``; the table lists the placed particles of each cell
    (``N`` = empty slot; the extra last row stays empty).
    """
    n, dim = radius.shape[0], len(half_sizes)
    dtype = radius.dtype
    half = jnp.asarray(half_sizes, dtype)
    cell_size = np.asarray(grid.size)
    per_side = np.asarray(grid.per_side, np.int32)
    n_cells = math.prod(grid.per_side)
    steps = [(0,) if count == 1 else (-1, 0, 1) for count in grid.per_side]
    offsets = np.array(list(itertools.product(*steps)), np.int32)
    strides = np.cumprod((1,) + grid.per_side[:0:-1])[::-1].astype(np.int32)

    def cell_of(point):
        coordinate = jnp.floor((point + half) / cell_size.astype(dtype)).astype(jnp.int32)
        return jnp.clip(coordinate, 0, per_side - 1)

    def find_spot(i, position, table):
        a_i = radius[i]
        low = (-half).at[-1].set(start_height) + a_i
        high = half - a_i

        def attempt(search):
            round_index, _, _ = search
            round_key = jax.random.fold_in(jax.random.fold_in(key, i), round_index)
            trial = jax.random.uniform(round_key, (candidates, dim), dtype, low, high)
            around = cell_of(trial)[:, None, :] + offsets[None]
            inside = jnp.all((around >= 0) & (around < per_side), axis=-1)
            cells = jnp.where(inside, around @ strides, n_cells)
            others = table[cells].reshape(candidates, -1)
            other_position = position[jnp.minimum(others, n - 1)]
            gap = jnp.linalg.norm(trial[:, None, :] - other_position, axis=-1)
            clear = (gap >= a_i + radius[jnp.minimum(others, n - 1)]) | (others == n)
            ok = jnp.all(clear, axis=1)
            first = jnp.argmax(ok)
            return round_index + 1, jnp.any(ok), trial[first]

        def keep_trying(search):
            round_index, found, _ = search
            return (~found) & (round_index < max_rounds)

        _, found, spot = lax.while_loop(keep_trying, attempt, (jnp.zeros((), jnp.int32), jnp.zeros((), bool), low))
        return found, spot

    def place_one(carry):
        (position, placed, table, count, i), _ = carry
        found, spot = find_spot(i, position, table)
        cell = cell_of(spot) @ strides
        full = found & (count[cell] >= capacity)
        record = found & ~full
        slot = jnp.where(record, cell, n_cells)
        table = table.at[slot, jnp.minimum(count[slot], capacity - 1)].set(jnp.where(record, i, n))
        count = count.at[slot].add(record.astype(jnp.int32))
        # Scatters, not selects over whole arrays: one placement costs O(1), not O(N).
        row = jnp.where(full, n, i)
        position = position.at[row].set(spot, mode="drop")
        placed = placed.at[row].set(found, mode="drop")
        return (position, placed, table, count, jnp.where(full, i, i + 1)), full

    def more(carry):
        (_, _, _, _, i), full = carry
        return (i < n_real) & ~full

    return lax.while_loop(more, place_one, (state, jnp.zeros((), bool)))


def sample_initial_state(
    key: PRNGKey,
    radii_choices: Sequence[float],
    config: PhysicsConfig = PhysicsConfig(),
    *,
    dim: int = 2,
    n_particles: int | None = None,
    start_height: float | None = None,
    dtype: DTypeLike | None = None,
    candidates: int = 64,
    max_rounds: int = 64,
    max_particles: int = MAX_PARTICLES,
) -> InitialState:
    """Draw one initial state with the authors' protocol.

    1. ``y0 ~ U(-H/4, 0)`` with ``H`` the vertical (last) half-size of the
       box (``L`` in the paper's square box), unless ``start_height`` is given;
    2. ``N`` from :func:`particle_count_range` (unless ``n_particles`` is given),
       capped for one radius or a narrow list where random placement would
       jam (:data:`RANDOM_PACKING_LIMIT`);
    3. radii uniformly from ``radii_choices`` (m);
    4. non-overlapping placement in index order (:func:`place_particles`),
       anywhere in the box above ``y0`` (any rectangular box, any D);
    5. one common velocity ``(U(-vs, vs), ..., U(-vs, vs) / 4)`` with the
       isolated settling speed ``vs`` of the smallest radius in the list.

    The particle count is data-dependent, so this function runs eagerly with
    a concrete ``key``; its placement core is jitted. The same key always
    gives the same state. Ctrl-C stops the placement within one block of
    particles.

    ``max_particles`` (default :data:`MAX_PARTICLES` = 1,000,000) is a size
    guard: a count beyond it (drawn by the protocol or given) is refused up
    front, before any work, with the count in the message.

    Raises:
      ValueError: bad radii, a count of 0 or beyond ``max_particles``.
      PlacementError: when some particle finds no free spot after
        ``candidates * max_rounds`` draws (the packing is too dense).
    """
    radii_choices = np.asarray(radii_choices, dtype=float)
    if (
        radii_choices.ndim != 1
        or radii_choices.size == 0
        or not np.all(np.isfinite(radii_choices) & (radii_choices > 0))
    ):
        raise ValueError(f"radii_choices must be a non-empty list of radii > 0 m, got {radii_choices.tolist()}")
    half_sizes = config.half_sizes(dim)
    half = half_sizes[-1]
    if np.any(radii_choices >= min(half_sizes)):
        raise ValueError(
            f"every radius must be below the smallest box half-size {min(half_sizes)} m, got {radii_choices.tolist()}"
        )
    if dtype is None:
        dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    key_height, key_count, key_radii, key_place, key_velocity = jax.random.split(key, 5)
    if start_height is None:
        start_height = float(jax.random.uniform(key_height, (), minval=-0.25 * half, maxval=0.0))
    if not (-half < start_height < half):
        raise ValueError(f"start_height must lie inside the box (-{half}, {half}) m, got {start_height}")
    drawn = n_particles is None
    if drawn:
        low, high = particle_count_range(
            start_height, float(radii_choices.max()), config, dim, radii_choices=radii_choices
        )
        if low < 1:
            raise ValueError(
                f"the largest radius {radii_choices.max():g} m is too large for the protocol's particle count "
                f"(floor(0.7 N_max) = {low} above y0 = {start_height:.4g} m in a box of half-sizes {half_sizes} m): "
                f"use smaller radii or pass n_particles"
            )
        if low > max_particles:
            raise ValueError(
                f"radii {radii_choices.tolist()} m would place about {low:,} particles (the protocol's count for the "
                f"largest radius {radii_choices.max():g} m in a box of half-sizes {half_sizes} m), more than "
                f"max_particles = {max_particles:,}: are the radii in m? Use larger radii, pass n_particles, or "
                f"raise max_particles"
            )
        n_particles = int(jax.random.randint(key_count, (), low, high + 1))
    if isinstance(n_particles, bool) or not isinstance(n_particles, int | np.integer) or n_particles < 1:
        raise ValueError(f"n_particles must be an integer >= 1, got {n_particles!r}")
    if n_particles > max_particles:
        raise ValueError(
            f"n_particles = {n_particles:,} is more than max_particles = {max_particles:,}: raise max_particles to "
            f"place that many"
        )
    choice = jax.random.randint(key_radii, (n_particles,), 0, radii_choices.size)
    radius = jnp.asarray(radii_choices, dtype)[choice]
    if float(start_height) + 2 * float(radii_choices.max()) > half:
        raise PlacementError(f"start_height {start_height} m leaves no room for radius {radii_choices.max()} m")

    position, placed = place_particles(
        key_place, radius, start_height, config, dim=dim, candidates=candidates, max_rounds=max_rounds
    )
    placed = np.asarray(placed)
    if not placed.all():
        first = int(np.argmin(placed))
        region = _region_volume(half_sizes, start_height)
        filled = float(np.sum(_ball_volume(np.asarray(radius, np.float64), dim))) / region
        fraction = "area" if dim == 2 else "volume"
        raise PlacementError(
            f"could not place particle {first} of {n_particles} (radius {float(radius[first]):.4g} m) without "
            f"overlap after {candidates * max_rounds} random draws; the requested packing is too dense "
            f"({fraction} fraction {filled:.2f} above y0 = {start_height:.4g} m). "
            + (
                f"The protocol's count for these radii is too dense for random placement (large radii leave "
                f"little room near the walls): pass n_particles (about {max(1, int(0.9 * first))} fit here) or "
                f"smaller radii."
                if drawn
                else "Use fewer particles, smaller radii or a lower start height."
            )
        )

    vs = config.settling_speed(float(radii_choices.min()), dim)
    velocity = jax.random.uniform(key_velocity, (dim,), dtype, -vs, vs)
    velocity = velocity.at[-1].multiply(0.25)
    velocity = jnp.broadcast_to(velocity, (n_particles, dim))
    return InitialState(position, velocity, radius, float(start_height))


_place_jit = jax.jit(_place, static_argnums=(5, 6, 7, 8, 9))
