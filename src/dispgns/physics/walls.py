"""Wall collisions with contact time, restitution and the post-contact remainder.

The definition is the order-independent ("vectorized") one of the reference
model: every particle whose explicit-Euler position crosses a wall is handled
on its own, with all other particles at their start-of-step positions. A
particle that crosses several axes in one step meets the walls in order of
contact time (computed from the start-of-step state; ties go to the lower
axis), and a later wall is processed only if the result of the earlier
collisions still crosses it. At most one collision per axis and step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
from jax import lax
from jaxtyping import ArrayLike, Float, Int

from dispgns.arrays import Count, Flag, Frame, ParticleMask, Radii
from dispgns.physics.config import PhysicsConfig

# Per wall (axis 0 upper, axis 0 lower, axis 1 upper, ...), W = 2 D.
WallCounts = Int[ArrayLike, "W"]

__all__ = [
    "WallCounts",
    "WallResult",
    "resolve_walls",
]

# force_at(query (Q, D), query_index (Q,)) -> (Q, D): interaction force in N
# on particle query_index[q] placed at query[q], all others where they started.
_Queries = Float[ArrayLike, "Q D"]
_QueryIndex = Int[ArrayLike, "Q"]
ForceAtFn = Callable[[_Queries, _QueryIndex], _Queries]


class WallResult(NamedTuple):
    """Outcome of one step's wall handling.

    Attributes:
      position, velocity: ``(N, D)`` end-of-step state, m and m/s.
      wall_hits: ``(2 D,)`` int, particles whose Euler position crossed each
        wall this step (a corner crossing counts on both walls), in the order (axis 0 upper, axis 0 lower, axis 1 upper,
        axis 1 lower, ...): right, left, top, bottom in 2-D.
      corner_events: int, particles that crossed two or more axes this step.
      overflow: bool, more colliding particles than the static capacity; the
        step's result is then wrong and must be recomputed with more capacity.
    """

    position: Frame
    velocity: Frame
    wall_hits: WallCounts
    corner_events: Count
    overflow: Flag


def _select_axis(on_axis: list, columns: list) -> jnp.ndarray:
    """Per particle, the entry of ``columns`` on the axis flagged in ``on_axis``."""
    picked = jnp.where(on_axis[0], columns[0], 0.0)
    for flag, column in zip(on_axis[1:], columns[1:]):
        picked = jnp.where(flag, column, picked)
    return picked


def resolve_walls(
    position: Frame,
    velocity: Frame,
    euler_position: Frame,
    euler_velocity: Frame,
    start_force: Frame,
    radius: Radii,
    mass: Radii,
    external: Frame,
    mask: ParticleMask,
    config: PhysicsConfig,
    force_at: ForceAtFn,
    capacity: int | None = None,
) -> WallResult:
    """Replace the Euler result of every wall-crossing particle by its collision.

    Args:
      position, velocity: ``(N, D)`` start-of-step state (m, m/s).
      euler_position, euler_velocity: ``(N, D)`` unconstrained Euler result.
      start_force: ``(N, D)`` interaction force at the start of the step (N).
      radius, mass: ``(N,)`` in m and kg.
      external: ``(N, D)`` external force (N).
      mask: ``(N,)`` bool, ``False`` for padding particles (never collide).
      config: physics parameters (``box_half_size``, ``restitution``, ``drag``, ``dt``).
      force_at: evaluates the interaction force at trial positions.
      capacity: static; at most this many colliding particles are handled per
        step (their contact-point forces cost ``capacity x N`` pair terms
        instead of ``N x N``). ``None``: all N, no overflow possible.
    """
    n, dim = position.shape
    # Admissible centre range per particle and axis, (N, D): one half-size per axis.
    half = jnp.asarray(config.half_sizes(dim), position.dtype)
    lower_all = -half + radius[:, None]
    upper_all = half - radius[:, None]
    above = (euler_position > upper_all) & mask[:, None]
    below = (euler_position < lower_all) & mask[:, None]
    crossed_any = jnp.any(above | below, axis=-1)
    wall_hits = jnp.stack([jnp.sum(above, axis=0), jnp.sum(below, axis=0)], axis=-1).reshape(2 * dim)
    corner_events = jnp.sum(jnp.sum(above | below, axis=-1) >= 2)

    exact = capacity is None or capacity >= n
    overflow = jnp.zeros((), bool) if exact else jnp.sum(crossed_any) > capacity

    def collide():
        return _collide(
            position,
            velocity,
            euler_position,
            euler_velocity,
            start_force,
            radius,
            mass,
            external,
            lower_all,
            upper_all,
            crossed_any,
            config,
            force_at,
            None if exact else capacity,
        )

    # Most steps have no wall crossing at all: the cond then skips the gathers
    # and contact-point forces (under vmap it becomes a select of both).
    new_position, new_velocity = lax.cond(jnp.any(crossed_any), collide, lambda: (euler_position, euler_velocity))
    return WallResult(new_position, new_velocity, wall_hits, corner_events, overflow)


def _collide(
    position,
    velocity,
    euler_position,
    euler_velocity,
    start_force,
    radius,
    mass,
    external,
    lower_all,
    upper_all,
    crossed_any,
    config: PhysicsConfig,
    force_at: ForceAtFn,
    capacity: int | None,
):
    """End-of-step ``(position, velocity)``, ``(N, D)``, with every crossing particle's collision applied.

    Arguments as in :func:`resolve_walls`; ``lower_all``/``upper_all`` ``(N, D)``
    are the admissible centre range in m per axis, ``crossed_any`` ``(N,)`` flags the
    crossing particles and ``capacity`` is ``None`` (all rows) or ``< N``.
    """
    n, dim = position.shape
    dtype = position.dtype
    # Work on the colliding particles only: gather them (up to `capacity`),
    # run every wall event on those rows, scatter the results back once.
    if capacity is None:
        index = jnp.arange(n)
        gather = lambda array: array
    else:
        (index,) = jnp.nonzero(crossed_any, size=capacity, fill_value=n)
        safe_index = jnp.minimum(index, n - 1)
        gather = lambda array: array[safe_index]
    active = gather(crossed_any) & (index < n)
    columns = lambda array: [array[:, d] for d in range(dim)]
    x, v = columns(gather(position)), columns(gather(velocity))
    result_x, result_v = columns(gather(euler_position)), columns(gather(euler_velocity))
    force_start, ext = columns(gather(start_force)), columns(gather(external))
    lower, upper = columns(gather(lower_all)), columns(gather(upper_all))
    drag = config.drag * gather(radius)
    inv_mass = 1.0 / gather(mass)
    sqrt_restitution = math.sqrt(config.restitution)

    crossed = [(c > hi) | (c < lo) for c, lo, hi in zip(result_x, lower, upper)]
    n_crossed = sum(c.astype(jnp.int32) for c in crossed)
    contact_time = [
        jnp.where(
            crossed[d],
            (jnp.where(result_x[d] > upper[d], upper[d], lower[d]) - x[d]) / jnp.where(crossed[d], v[d], 1.0),
            jnp.inf,
        )
        for d in range(dim)
    ]
    # Rank of each axis in contact-time order; ties go to the lower axis.
    rank = [
        sum(
            ((contact_time[e] < contact_time[d]) | ((contact_time[e] == contact_time[d]) & (e < d))).astype(jnp.int32)
            for e in range(dim)
            if e != d
        )
        for d in range(dim)
    ]

    start, start_velocity, force_at_start = x, v, force_start
    remaining = jnp.full(lower[0].shape, config.dt, dtype)
    for event in range(dim):
        on_axis = [r == event for r in rank]
        result_d = _select_axis(on_axis, result_x)
        # The walls of the axis met at this event (exactly the square box's
        # values when every half-size is equal: a select, no arithmetic).
        upper_d, lower_d = _select_axis(on_axis, upper), _select_axis(on_axis, lower)
        if event > 0:
            still_crossing = (result_d > upper_d) | (result_d < lower_d)
            active = active & (event < n_crossed) & still_crossing
        wall = jnp.where(result_d > upper_d, upper_d, lower_d)
        start_d = _select_axis(on_axis, start)
        velocity_d = jnp.where(active, _select_axis(on_axis, start_velocity), 1.0)
        t_contact = jnp.clip((wall - start_d) / velocity_d, 0.0, remaining)
        t_rest = remaining - t_contact
        contact = [s + t_contact * w for s, w in zip(start, start_velocity)]
        # Drag in both parts of the sub-step uses the velocity it started with.
        other_forces = [e - drag * w for e, w in zip(ext, start_velocity)]
        before = [w + t_contact * inv_mass * (o + f) for w, o, f in zip(start_velocity, other_forces, force_at_start)]
        reflected = [sqrt_restitution * jnp.where(flag, -b, b) for flag, b in zip(on_axis, before)]

        def contact_force(contact=contact, active=active):  # called within this iteration (lax.cond)
            return columns(force_at(jnp.stack(contact, axis=-1), jnp.where(active, index, n)))

        if event == 0:
            force_at_contact = contact_force()
        else:
            # Only corner crossings reach a second wall: usually none, so skip the force.
            force_at_contact = lax.cond(
                jnp.any(active), contact_force, lambda contact=contact: [jnp.zeros_like(c) for c in contact]
            )
        after_v = [r + t_rest * inv_mass * (o + f) for r, o, f in zip(reflected, other_forces, force_at_contact)]
        after_x = [c + t_rest * r for c, r in zip(contact, reflected)]

        keep = lambda new, old, active=active: [jnp.where(active, a, b) for a, b in zip(new, old)]
        result_x, result_v = keep(after_x, result_x), keep(after_v, result_v)
        start, start_velocity = keep(contact, start), keep(reflected, start_velocity)
        force_at_start = keep(force_at_contact, force_at_start)
        remaining = jnp.where(active, t_rest, remaining)

    # In exact arithmetic every particle ends inside; the clip only removes
    # rounding of a contact point that lands an ulp beyond its wall.
    result_x = [jnp.clip(c, lo, hi) for c, lo, hi in zip(result_x, lower, upper)]
    new_x, new_v = jnp.stack(result_x, axis=-1), jnp.stack(result_v, axis=-1)
    collided = gather(crossed_any) & (index < n)
    if capacity is None:
        new_position = jnp.where(collided[:, None], new_x, euler_position)
        new_velocity = jnp.where(collided[:, None], new_v, euler_velocity)
    else:
        scatter_index = jnp.where(collided, index, n)
        new_position = euler_position.at[scatter_index].set(new_x, mode="drop")
        new_velocity = euler_velocity.at[scatter_index].set(new_v, mode="drop")
    return new_position, new_velocity
