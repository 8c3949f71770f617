"""Masses, external forces and the truncated Lennard-Jones pair force (SI units).

Every function is pure and works for any spatial dimension ``D`` (2 for the
disks of the paper, 3 for spheres). Shapes: ``N`` particles, ``Q`` query rows.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax import lax
from jaxtyping import ArrayLike, Float, Int

from dispgns.arrays import Frame, ParticleMask, Radii
from dispgns.physics.config import PhysicsConfig
from dispgns.tuning import thresholds

# Q trial positions (m), the particle each belongs to, and a dense neighbour list of M slots per particle.
_Queries = Float[ArrayLike, "Q D"]
_QueryIndex = Int[ArrayLike, "Q"]
_NeighborIndex = Int[ArrayLike, "N M"]
_QueryNeighbors = Int[ArrayLike, "Q M"]
# What neighbor_table packs per particle (position, radius, real flag) plus the empty slot; per-pair values
# of any (broadcast) shape.
_Table = Float[ArrayLike, "N+1 D+2"]
_PerPair = Float[ArrayLike, "*pairs"]

__all__ = [
    "external_force",
    "interaction_force",
    "neighbor_force",
    "neighbor_table",
    "pair_force_over_distance",
    "particle_mass",
    "particle_volume",
]


def particle_volume(radius: Radii, config: PhysicsConfig, dim: int) -> Radii:
    """Volume in m^3 of each particle; ``radius`` is ``(N,)`` in m.

    ``dim = 2``: disks of thickness ``config.thickness`` (the paper's model);
    ``dim = 3``: spheres.
    """
    if dim == 2:
        return math.pi * radius**2 * config.thickness
    if dim == 3:
        return (4.0 / 3.0) * math.pi * radius**3
    raise ValueError(f"spatial dimension must be 2 or 3, got {dim}")


def particle_mass(radius: Radii, config: PhysicsConfig, dim: int) -> Radii:
    """Mass in kg, ``(N,)``."""
    return config.density * particle_volume(radius, config, dim)


def external_force(radius: Radii, config: PhysicsConfig, dim: int) -> Frame:
    """Buoyant weight in N, ``(N, D)``: zero except ``-(rho - rho_f) V g`` on the last axis."""
    weight = (config.density - config.fluid_density) * particle_volume(radius, config, dim) * config.gravity
    force = jnp.zeros(radius.shape + (dim,), dtype=radius.dtype)
    return force.at[..., -1].set(-weight)


def pair_force_over_distance(r2: _PerPair, a_i: _PerPair, a_j: _PerPair, config: PhysicsConfig) -> _PerPair:
    """``-U'(max(r, r_m)) / r`` for pairs at squared distance ``r2`` (m^2).

    Multiplying by the displacement ``x_i - x_j`` gives the force on ``i`` in N.
    Below ``r_m = min_distance_coeff * min(a_i, a_j)`` the magnitude is frozen at
    its value at ``r_m`` while the direction stays the true one. Callers must
    pass ``r2 > 0`` (mask coincident or self pairs before calling).
    """
    p = int(config.lj_exponent)
    sigma = a_i + a_j
    inv_r = lax.rsqrt(r2)
    # 1 / max(r, r_m) = min(1/r, 1/r_m), with r_m = c min(a_i, a_j): one rsqrt per pair.
    # 1 / (c min(a_i, a_j)) = max(1 / (c a_i), 1 / (c a_j)) exactly (the same rounded
    # reciprocal is picked), and on broadcast (Q, 1) x (1, N) radii the reciprocals
    # are per particle, not per pair.
    inv_r_min = jnp.maximum(1.0 / (config.min_distance_coeff * a_i), 1.0 / (config.min_distance_coeff * a_j))
    inv_r_eff = jnp.minimum(inv_r, inv_r_min)
    ratio_p = lax.integer_pow(sigma * inv_r_eff, p)
    well_depth = config.well_depth_coeff * sigma * sigma
    # -U'(r_eff) = 4 p U0 / r_eff (2 s^2p - s^p); dividing by r for the unit vector.
    return (4.0 * p) * well_depth * (2.0 * ratio_p * ratio_p - ratio_p) * inv_r_eff * inv_r


def interaction_force(
    query: _Queries,
    query_index: _QueryIndex,
    position: Frame,
    radius: Radii,
    mask: ParticleMask,
    config: PhysicsConfig,
    neighbor_idx: _NeighborIndex | None = None,
) -> _Queries:
    """Pair force in N on particle ``query_index[q]`` placed at ``query[q]``.

    Every other real particle ``j`` sits at ``position[j]``. This is
    ``F_i(x with x_i -> y)`` of the reference model: the force a particle
    feels at a trial position (its start-of-step position, or a wall contact
    point) with all others at their start-of-step positions.

    Args:
      query: ``(Q, D)`` trial positions in m.
      query_index: ``(Q,)`` int, the particle each row belongs to; rows whose
        index is ``>= N`` (padding) get zero force.
      position: ``(N, D)`` positions of all particles in m.
      radius: ``(N,)`` radii in m.
      mask: ``(N,)`` bool, ``False`` for padding particles, which exert no force.
      config: physics parameters; ``config.cutoff`` (m) drops pairs farther
        apart than it.
      neighbor_idx: ``None`` for all pairs (dense ``Q x N``), or a jax-md dense
        neighbour list ``(N, M)`` built at a radius of at least
        ``config.cutoff`` plus the largest trial displacement, with ``N``
        marking empty slots.

    Returns:
      ``(Q, D)`` forces in N.
    """
    n, dim = position.shape
    if neighbor_idx is not None:
        table = neighbor_table(position, radius, mask)
        return neighbor_force(query, query_index, neighbor_idx[jnp.minimum(query_index, n - 1)], table, config)
    safe_index = jnp.minimum(query_index, n - 1)
    a_i = radius[safe_index][:, None]
    query_valid = (query_index < n) & mask[safe_index]
    # One (Q, N) array per axis: XLA on CPU vectorises these far better than
    # (Q, N, D) arrays reduced over a minor axis of size 2.
    displacement = [query[:, d][:, None] - position[:, d][None, :] for d in range(dim)]
    valid = mask[None, :] & (jnp.arange(n)[None, :] != query_index[:, None]) & query_valid[:, None]
    coeff = _pair_coefficient(displacement, valid, a_i, radius[None, :], config)
    # sum_j c_qj (y_q - x_j) = y_q sum_j c_qj - (c x)_q: one matrix product
    # instead of D row reductions of (Q, N) products, a third of the cost of a
    # step at N = 220 on CPU. The two terms cancel, so the rounding error
    # grows with |x_j - centre| / r_qj: centring on the real particles keeps
    # it at the direct sum's in the reference's settled bed (2e-4 of a
    # particle's weight at most, in float32), while 1 mm disks packed across
    # the whole box see ~13x the direct sum's (1.1-1.3e-3 of the weight). The
    # direct sum with 512-bit loops is 0.11-0.13 ms per step, above the
    # 0.1 ms target. Padding rows are parked at finite positions and have c = 0.
    count = jnp.maximum(jnp.sum(mask), 1).astype(position.dtype)
    centre = jnp.sum(jnp.where(mask[:, None], position, 0.0), axis=0) / count
    others = position - centre
    sums = jnp.dot(
        coeff, jnp.concatenate([others, jnp.ones((n, 1), position.dtype)], axis=1), precision=lax.Precision.HIGHEST
    )
    return (query - centre) * sums[:, dim:] - sums[:, :dim]


def neighbor_table(position: Frame, radius: Radii, mask: ParticleMask) -> _Table:
    """Per-particle data that a neighbour-list force gathers, packed as ``(N + 1, D + 2)``.

    Row ``j < N`` holds ``x_j`` (m, ``D`` columns), ``a_j`` (m) and 1.0 for a
    real particle or 0.0 for padding; row ``N`` is the empty slot that jax-md
    neighbour lists point to (0.0 flag, radius 1 m so that masked arithmetic
    stays finite). Built once per step and shared by every force evaluation
    of that step.
    """
    dtype = position.dtype
    rows = jnp.concatenate([position, radius[:, None], mask[:, None].astype(dtype)], axis=1)
    empty = jnp.zeros((1, rows.shape[1]), dtype).at[0, -2].set(1.0)
    return jnp.concatenate([rows, empty], axis=0)


def neighbor_force(
    query: _Queries,
    query_index: _QueryIndex,
    others: _QueryNeighbors,
    table: _Table,
    config: PhysicsConfig,
) -> _Queries:
    """Pair force in N on particle ``query_index[q]`` at ``query[q]`` from its listed neighbours.

    The same force as :func:`interaction_force` with a neighbour list, for
    callers that evaluate it several times per step on one list.

    Args:
      query: ``(Q, D)`` trial positions in m.
      query_index: ``(Q,)`` int; rows with an index ``>= N`` get zero force.
      others: ``(Q, M)`` int, the neighbour-list row of each query's particle
        (``N`` marks an empty slot).
      table: ``(N + 1, D + 2)`` from :func:`neighbor_table`.
      config: physics parameters (``cutoff`` in m).

    Returns:
      ``(Q, D)`` forces in N.
    """
    n = table.shape[0] - 1
    dim = table.shape[1] - 2
    query_row = table[jnp.minimum(query_index, n)]
    query_valid = query_row[:, dim + 1] > 0
    a_i = query_row[:, dim]
    # Loop over slots up to a machine-dependent size, (Q, M) arrays above (dispgns.tuning.Thresholds).
    if others.size <= thresholds().slot_loop_max_pairs:
        # Small lists: one slot at a time on (Q,) vectors. XLA fuses each
        # slot's gather and arithmetic, which beats (Q, M) arrays while the
        # data sits in cache; for large Q x M the (Q, M) form below is faster.
        force = [jnp.zeros_like(a_i) for _ in range(dim)]
        for slot in range(others.shape[1]):
            other = others[:, slot]
            neighbor = table[other]
            displacement = [query[:, d] - neighbor[:, d] for d in range(dim)]
            valid = (neighbor[:, dim + 1] > 0) & (other != query_index) & query_valid
            coeff = _pair_coefficient(displacement, valid, a_i, neighbor[:, dim], config)
            force = [f + coeff * component for f, component in zip(force, displacement)]
        return jnp.stack(force, axis=-1)
    # One gather of whole rows replaces separate position, radius and mask
    # gathers and the clamping of empty slots (they point at the padding row).
    neighbor = table[others]
    displacement = [query[:, d][:, None] - neighbor[..., d] for d in range(dim)]
    valid = (neighbor[..., dim + 1] > 0) & (others != query_index[:, None]) & query_valid[:, None]
    return _sum_pair_forces(displacement, valid, a_i[:, None], neighbor[..., dim], config)


def _pair_coefficient(
    displacement: list, valid: jnp.ndarray, a_i: jnp.ndarray, a_j: jnp.ndarray, config: PhysicsConfig
) -> jnp.ndarray:
    """``-U'(r) / r`` (N/m) of every pair, 0 for pairs that do not interact.

    ``displacement`` is a list of ``D`` arrays of ``query - x_j`` in m;
    ``valid`` marks pairs that interact before the cut-off is applied; all
    arrays, radii included, broadcast to one shape.
    """
    r2 = sum(component * component for component in displacement)
    if config.cutoff is not None:
        valid = valid & (r2 < config.cutoff**2)
    # Masked pairs get r2 = 1 so that no inf/nan enters the (discarded) branch,
    # which keeps gradients finite as well.
    r2_safe = jnp.where(valid & (r2 > 0), r2, 1.0)
    return jnp.where(valid, pair_force_over_distance(r2_safe, a_i, a_j, config), 0.0)


def _sum_pair_forces(
    displacement: list, valid: jnp.ndarray, a_i: jnp.ndarray, a_j: jnp.ndarray, config: PhysicsConfig
) -> jnp.ndarray:
    """Sum of pair forces over the last axis: ``(Q, D)`` in N.

    Arguments as in :func:`_pair_coefficient`, with ``(Q, K)`` pair arrays.
    """
    coeff = _pair_coefficient(displacement, valid, a_i, a_j, config)
    return jnp.stack([jnp.sum(coeff * component, axis=1) for component in displacement], axis=-1)
