"""The authors' initial-condition protocol for sedimentation trajectories (SI units)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from dispgns.physics.config import PhysicsConfig

__all__ = [
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

    position: jnp.ndarray
    velocity: jnp.ndarray
    radius: jnp.ndarray
    start_height: float


class PlacementError(RuntimeError):
    """The requested packing could not be placed without overlaps."""


def particle_count_range(
    start_height: float, max_radius: float, config: PhysicsConfig, dim: int = 2
) -> tuple[int, int]:
    """Inclusive range of particle counts the protocol draws from.

    ``N_max = (2L)^(D-1) (L - y0) / (2 a_max)^D`` squares of side ``2 a_max``
    fit the placement region; the protocol draws ``N`` uniformly from
    ``floor(0.7 N_max) ... floor(0.7 N_max) + 3``.
    """
    half = config.box_half_size
    region = (2.0 * half) ** (dim - 1) * (half - start_height)
    n_scale = int(0.7 * region / (2.0 * max_radius) ** dim)
    if n_scale + 3 > _MAX_PARTICLES:
        raise ValueError(
            f"largest radius {max_radius} m gives {n_scale:,} particles in the box, more than the "
            f"{_MAX_PARTICLES:,} particle indices can address: use larger radii"
        )
    return n_scale, n_scale + 3


# Particle indices (neighbour lists, graphs) are int32.
_MAX_PARTICLES = 2**31 - 1


def place_particles(
    key, radius, start_height, config: PhysicsConfig, *, dim: int = 2, candidates: int = 64, max_rounds: int = 64
):
    """Place particles one at a time, in index order, without overlap (jit-compiled).

    Particle ``i`` is drawn uniformly in ``[-L + a_i, L - a_i]^(D-1) x
    [y0 + a_i, L - a_i]`` and rejected if it is closer than ``a_i + a_j`` to a
    particle already placed. ``candidates`` draws are tested at once per
    round, up to ``max_rounds`` rounds per particle.

    Args:
      key: PRNG key. radius: ``(N,)`` in m. start_height: ``y0`` in m.
      config, dim, candidates, max_rounds: static.

    Returns:
      ``(position (N, D), placed (N,) bool)``; ``placed[i]`` is ``False`` when
      no valid spot was found for particle ``i`` (its row is then invalid).
    """
    radius = jnp.asarray(radius)
    start_height = jnp.asarray(start_height, radius.dtype)
    return _place_jit(key, radius, start_height, config, candidates, max_rounds, radius.shape[0], dim)


def _place(key, radius, start_height, config, candidates, max_rounds, n, dim):
    half = config.box_half_size
    dtype = radius.dtype

    def place_one(i, carry):
        position, placed = carry
        a_i = radius[i]
        low = jnp.full((dim,), -half, dtype).at[-1].set(start_height) + a_i
        high = jnp.full((dim,), half, dtype) - a_i

        def attempt(state):
            round_index, _, _ = state
            round_key = jax.random.fold_in(jax.random.fold_in(key, i), round_index)
            trial = jax.random.uniform(round_key, (candidates, dim), dtype, low, high)
            gap = jnp.linalg.norm(trial[:, None, :] - position[None, :, :], axis=-1)
            clear = (gap >= a_i + radius[None, :]) | ~placed[None, :]
            ok = jnp.all(clear, axis=1)
            first = jnp.argmax(ok)
            return round_index + 1, jnp.any(ok), trial[first]

        def keep_trying(state):
            round_index, found, _ = state
            return (~found) & (round_index < max_rounds)

        _, found, spot = lax.while_loop(keep_trying, attempt, (jnp.zeros((), jnp.int32), jnp.zeros((), bool), low))
        return position.at[i].set(spot), placed.at[i].set(found)

    position = jnp.zeros((n, dim), dtype)
    placed = jnp.zeros((n,), bool)
    return lax.fori_loop(0, n, place_one, (position, placed))


def sample_initial_state(
    key: jax.Array,
    radii_choices: Sequence[float],
    config: PhysicsConfig = PhysicsConfig(),
    *,
    dim: int = 2,
    n_particles: int | None = None,
    start_height: float | None = None,
    dtype=None,
    candidates: int = 64,
    max_rounds: int = 64,
) -> InitialState:
    """Draw one initial state with the authors' protocol.

    1. ``y0 ~ U(-L/4, 0)`` (unless ``start_height`` is given);
    2. ``N`` from :func:`particle_count_range` (unless ``n_particles`` is given);
    3. radii uniformly from ``radii_choices`` (m);
    4. non-overlapping placement in index order (:func:`place_particles`);
    5. one common velocity ``(U(-vs, vs), ..., U(-vs, vs) / 4)`` with the
       isolated settling speed ``vs`` of the smallest radius in the list.

    The particle count is data-dependent, so this function runs eagerly with
    a concrete ``key``; its placement core is jitted. The same key always
    gives the same state.

    Raises:
      PlacementError: when some particle finds no free spot after
        ``candidates * max_rounds`` draws (the packing is too dense).
    """
    radii_choices = np.asarray(radii_choices, dtype=float)
    if radii_choices.ndim != 1 or radii_choices.size == 0 or np.any(radii_choices <= 0):
        raise ValueError(f"radii_choices must be a non-empty list of radii > 0 m, got {radii_choices.tolist()}")
    half = config.box_half_size
    if np.any(radii_choices >= half):
        raise ValueError(f"every radius must be below the box half-size L = {half} m, got {radii_choices.tolist()}")
    if dtype is None:
        dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    key_height, key_count, key_radii, key_place, key_velocity = jax.random.split(key, 5)
    if start_height is None:
        start_height = float(jax.random.uniform(key_height, (), minval=-0.25 * half, maxval=0.0))
    if not (-half < start_height < half):
        raise ValueError(f"start_height must lie inside the box (-{half}, {half}) m, got {start_height}")
    if n_particles is None:
        low, high = particle_count_range(start_height, float(radii_choices.max()), config, dim)
        n_particles = int(jax.random.randint(key_count, (), low, high + 1))
    if n_particles < 1:
        raise ValueError(f"n_particles must be >= 1, got {n_particles}")
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
        region = (2 * half) ** (dim - 1) * (half - start_height)
        filled = float(np.sum(math.pi * np.asarray(radius) ** 2)) / region if dim == 2 else float("nan")
        raise PlacementError(
            f"could not place particle {first} of {n_particles} (radius {float(radius[first]):.4g} m) without "
            f"overlap after {candidates * max_rounds} random draws; the requested packing is too dense "
            f"(area fraction {filled:.2f} above y0 = {start_height:.4g} m). Use fewer particles, smaller "
            f"radii or a lower start height."
        )

    vs = config.settling_speed(float(radii_choices.min()))
    velocity = jax.random.uniform(key_velocity, (dim,), dtype, -vs, vs)
    velocity = velocity.at[-1].multiply(0.25)
    velocity = jnp.broadcast_to(velocity, (n_particles, dim))
    return InitialState(position, velocity, radius, float(start_height))


_place_jit = jax.jit(_place, static_argnums=(3, 4, 5, 6, 7))
