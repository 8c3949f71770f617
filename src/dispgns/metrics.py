"""Evaluation metrics for rollouts of particle suspensions (arrays in, numbers out).

Conventions shared by every function here:

* positions are normalised by the box half-size ``L`` (the box is
  ``[-1, 1]^D``), shape ``(T, N, D)``; ``radius`` is ``(N,)``, also divided by
  ``L``; ``mask`` is an optional ``(N,)`` bool, ``False`` for padding
  particles, which never count in any metric (``None`` = all real);
* the first ``C = input_frames`` frames (6 in the paper) are the inputs given
  to the model and frames ``C .. T-1`` are predicted; every "per-frame" curve
  below covers the predicted frames only, so its entry ``k`` is frame
  ``C + k`` (``k + 1`` model steps after the last input);
* ``frame_dt`` is the time between frames in seconds (1.5e-3 in the paper);
  the box half-size ``L`` is in metres (0.1 in the paper).

The array functions (:func:`per_frame_mse`, :func:`wall_violations`,
:func:`overlap_counts`, :func:`kinetic_energy`, :func:`mean_height`,
:func:`constant_velocity_rollout`, ...) are pure ``jax.numpy`` and work under
``jax.jit`` / ``jax.vmap`` with the integer arguments static. The host-level
functions :func:`horizon_mse`, :func:`rollout_metrics` and :func:`summarize`
return plain Python floats and lists (JSON-ready). Nothing here runs a
simulation: the chaos-floor trajectory is computed by
:func:`dispgns.evaluation.chaos_floor_rollout` and passed in.

The paper (Hashemi & Izadkhah 2025) reports its rollout MSE in
normalised units and converts an MSE of 6.6e-4 into "0.066 mm", which
multiplies a squared length by ``L`` and is not a length. The root-mean-square
error is ``sqrt(MSE) * L`` (2.6 mm for that example); :func:`rollout_metrics`
reports it in millimetres and in mean particle diameters, and keeps the
paper's number only under the explicit name ``mse_times_L_mm``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import ArrayLike, Bool, Float, Int

from dispgns.arrays import Box, Frame, ParticleMask, PerFrame, Positions, Radii, Scalar, pad_particles
from dispgns.physics import PhysicsConfig, particle_mass

# Shapes of this module's other arrays (jaxtyping annotations, no runtime check); C input frames.
_Values = Float[ArrayLike, "*shape"]  # any shape, e.g. a scalar MSE or a per-frame curve
_Curve = Float[ArrayLike, "T-C"]  # one value per predicted frame
_Steps = Float[ArrayLike, "T-1"]  # one value per frame-to-frame step
_FrameCounts = Int[ArrayLike, "T"]
_Bins = Float[ArrayLike, "bins"]
_BinCounts = Int[ArrayLike, "bins"]
_OtherCloud = Float[ArrayLike, "M D"]
_OtherMask = Bool[ArrayLike, "M"]

__all__ = [
    "DEFAULT_HORIZONS",
    "RDF_PAIRS",
    "STATISTICS_DEFAULTS",
    "bed_area_fraction",
    "front_height",
    "height_profile",
    "maximum_mean_discrepancy",
    "radial_distribution",
    "settling_velocity",
    "sinkhorn_divergence",
    "constant_velocity_rollout",
    "horizon_mse",
    "kinetic_energy",
    "mean_height",
    "mse_times_L_mm",
    "overlap_counts",
    "per_frame_mse",
    "rmse_diameters",
    "rmse_mm",
    "rollout_metrics",
    "rollout_mse",
    "squared_error_per_frame",
    "summarize",
    "wall_violations",
]

DEFAULT_HORIZONS: tuple[int, ...] = (1, 10, 50, 100)
"""Horizons (in predicted frames) reported by :func:`rollout_metrics`."""


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------


def _weights(mask, n: int, dtype) -> jnp.ndarray:
    """``(N,)`` float weights: 1 for real particles, 0 for padding."""
    if mask is None:
        return jnp.ones((n,), dtype)
    mask = jnp.asarray(mask)
    if mask.shape != (n,):
        raise ValueError(f"mask must have shape ({n},), got {mask.shape}")
    return mask.astype(dtype)


def _as_trajectory(name: str, positions) -> jnp.ndarray:
    positions = jnp.asarray(positions)
    if positions.ndim != 3:
        raise ValueError(f"{name} must have shape (T, N, D), got {positions.shape}")
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        positions = positions.astype(jnp.float32)
    return positions


def _as_radius(radius, n: int, dtype) -> jnp.ndarray:
    radius = jnp.asarray(radius, dtype)
    if radius.shape != (n,):
        raise ValueError(f"radius must have shape ({n},), got {radius.shape}")
    return radius


def _check_pair(prediction, truth, input_frames: int):
    prediction = _as_trajectory("prediction", prediction)
    truth = _as_trajectory("truth", truth)
    if prediction.shape != truth.shape:
        raise ValueError(f"prediction {prediction.shape} and truth {truth.shape} must have the same shape (T, N, D)")
    if not 1 <= input_frames < truth.shape[0]:
        raise ValueError(
            f"input_frames must lie in [1, T - 1] = [1, {truth.shape[0] - 1}] so that some frames are predicted, "
            f"got {input_frames}"
        )
    return prediction, truth


# ----------------------------------------------------------------------------
# position errors
# ----------------------------------------------------------------------------


def squared_error_per_frame(prediction: Positions, truth: Positions, mask: ParticleMask | None = None) -> PerFrame:
    """Mean squared position error of every frame.

    Args:
      prediction, truth: ``(T, N, D)`` positions (normalised units).
      mask: optional ``(N,)`` bool; padding particles are excluded.

    Returns:
      ``(T,)``: for each frame the mean over real particles and the ``D`` axes
      of the squared difference (normalised units squared).
    """
    prediction = _as_trajectory("prediction", prediction)
    truth = _as_trajectory("truth", truth)
    if prediction.shape != truth.shape:
        raise ValueError(f"prediction {prediction.shape} and truth {truth.shape} must have the same shape (T, N, D)")
    _, n, dim = truth.shape
    weight = _weights(mask, n, truth.dtype)
    squared = jnp.sum((prediction - truth) ** 2, axis=-1)
    # where, not a product: padding rows may hold anything, NaN included.
    squared = jnp.where(weight > 0, squared, 0.0)
    return squared @ weight / (jnp.sum(weight) * dim)


def per_frame_mse(
    prediction: Positions, truth: Positions, *, input_frames: int = 6, mask: ParticleMask | None = None
) -> _Curve:
    """Per-frame MSE curve over the predicted frames.

    Args:
      prediction, truth: ``(T, N, D)`` normalised positions; frames
        ``0 .. C-1`` are inputs (``C = input_frames``, static).
      mask: optional ``(N,)`` bool.

    Returns:
      ``(T - C,)``: entry ``k`` is the MSE of frame ``C + k`` (normalised units
      squared).
    """
    prediction, truth = _check_pair(prediction, truth, input_frames)
    return squared_error_per_frame(prediction[input_frames:], truth[input_frames:], mask)


def rollout_mse(
    prediction: Positions,
    truth: Positions,
    *,
    input_frames: int = 6,
    mask: ParticleMask | None = None,
    horizon: int | None = None,
) -> Scalar:
    """The paper's rollout MSE: mean squared position error (normalised units).

    The mean runs over all predicted frames (or the first ``horizon`` of them),
    all real particles and all axes.

    Args:
      prediction, truth: ``(T, N, D)`` normalised positions.
      input_frames: static; number of given input frames ``C``.
      mask: optional ``(N,)`` bool.
      horizon: static; ``None`` for all ``T - C`` predicted frames, else the
        first ``horizon`` predicted frames (frames ``C .. C + horizon - 1``).
        A horizon longer than the rollout is an error here (see
        :func:`horizon_mse` for the lenient version).

    Returns:
      scalar MSE.
    """
    curve = per_frame_mse(prediction, truth, input_frames=input_frames, mask=mask)
    if horizon is not None:
        if not 1 <= horizon <= curve.shape[0]:
            raise ValueError(f"horizon must lie in [1, {curve.shape[0]}] (predicted frames), got {horizon}")
        curve = curve[:horizon]
    # Every frame holds the same particles, so the mean of the per-frame means
    # is the mean over all particle-frames.
    return jnp.mean(curve)


def horizon_mse(curve: _Curve, horizons: Sequence[int] = DEFAULT_HORIZONS) -> dict[str, float | None]:
    """MSE over the first ``h`` predicted frames, for several horizons.

    Args:
      curve: ``(T - C,)`` per-frame MSE from :func:`per_frame_mse`.
      horizons: horizons ``h >= 1`` in predicted frames.

    Returns:
      ``{str(h): mse or None, ..., "full": mse}`` as Python floats. A horizon
      longer than the rollout (``h > T - C``) is ``None`` (JSON ``null``):
      it is skipped rather than silently truncated.
    """
    curve = np.asarray(curve, np.float64)
    if curve.ndim != 1 or curve.size == 0:
        raise ValueError(f"curve must be a non-empty 1-D per-frame MSE, got shape {curve.shape}")
    out: dict[str, float | None] = {}
    for h in horizons:
        h = int(h)
        if h < 1:
            raise ValueError(f"horizons must be >= 1, got {h}")
        out[str(h)] = float(np.mean(curve[:h])) if h <= curve.size else None
    out["full"] = float(np.mean(curve))
    return out


def rmse_mm(mse: _Values, box_half_size: float) -> _Values:
    """Root-mean-square position error in millimetres: ``sqrt(mse) * L * 1000``.

    Args:
      mse: MSE in normalised units (scalar or array).
      box_half_size: ``L`` in m.
    """
    return jnp.sqrt(mse) * box_half_size * 1e3


def rmse_diameters(mse: _Values, radius: Radii, mask: ParticleMask | None = None) -> _Values:
    """Root-mean-square position error in mean particle diameters.

    ``sqrt(mse) * L / mean(2 a_i)``; with ``mse`` and ``radius`` both in
    normalised units, ``L`` cancels.

    Args:
      mse: MSE in normalised units (scalar or array).
      radius: ``(N,)`` normalised radii; the mean runs over real particles.
      mask: optional ``(N,)`` bool.
    """
    radius = jnp.asarray(radius)
    weight = _weights(mask, radius.shape[0], radius.dtype)
    mean_diameter = 2.0 * jnp.sum(jnp.where(weight > 0, radius, 0.0)) / jnp.sum(weight)
    return jnp.sqrt(mse) / mean_diameter


def mse_times_L_mm(mse: _Values, box_half_size: float) -> _Values:
    """The paper's conversion ``mse * L * 1000`` ("0.066 mm" for 6.6e-4).

    Kept only to compare with the paper's text: it multiplies a squared length
    by ``L`` and is not a length. Use :func:`rmse_mm` for a real length.
    """
    return mse * box_half_size * 1e3


# ----------------------------------------------------------------------------
# physical plausibility
# ----------------------------------------------------------------------------


def wall_violations(
    positions: Positions,
    radius: Radii,
    *,
    tolerance: float = 0.1,
    mask: ParticleMask | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
) -> _FrameCounts:
    """Particles poking through a wall, per frame.

    A particle is outside when on some axis its centre lies beyond its wall
    contact position ``1 - a_i`` by more than ``tolerance * a_i``, i.e.
    ``|x_d| > 1 - a_i + tolerance a_i``: the disk pokes through the wall by
    more than ``tolerance`` of its radius.

    Args:
      positions: ``(T, N, D)`` normalised. radius: ``(N,)`` normalised.
      tolerance: allowed penetration as a fraction of the radius (0.1 = 10 %).
      mask: optional ``(N,)`` bool; padding never counts.
      bounds: static box ``((lo, hi),) * D`` in normalised units (``None``:
        ``[-1, 1]^D``); the walls are then at ``lo_d`` and ``hi_d``.

    Returns:
      ``(T,)`` int32: number of real particles outside the box in each frame
      (a particle outside on two axes counts once).
    """
    positions = _as_trajectory("positions", positions)
    _, n, _ = positions.shape
    radius = _as_radius(radius, n, positions.dtype)
    if bounds is None or all(tuple(pair) == (-1.0, 1.0) for pair in bounds):
        limit = 1.0 - radius + tolerance * radius
        outside = jnp.any(jnp.abs(positions) > limit[None, :, None], axis=-1)
    else:
        box = np.asarray(bounds, np.float64)
        lo, hi = jnp.asarray(box[:, 0], positions.dtype), jnp.asarray(box[:, 1], positions.dtype)
        slack = (radius - tolerance * radius)[None, :, None]
        outside = jnp.any((positions < lo + slack) | (positions > hi - slack), axis=-1)
    if mask is not None:
        outside = outside & _weights(mask, n, bool)[None, :]
    return jnp.sum(outside, axis=-1, dtype=jnp.int32)


def overlap_counts(
    positions: Positions, radius: Radii, *, coeff: float = 1.75, mask: ParticleMask | None = None
) -> _FrameCounts:
    """Overlapping pairs per frame.

    A pair ``i < j`` of real particles overlaps when its centre distance is
    below ``coeff * min(a_i, a_j)`` (``r_m``, the physics' hard-core distance
    below which the pair force stops growing, for ``coeff = 1.75``).

    Args:
      positions: ``(T, N, D)`` normalised. radius: ``(N,)`` normalised.
      coeff: the coefficient of ``min(a_i, a_j)``.
      mask: optional ``(N,)`` bool; pairs involving padding never count.

    Returns:
      ``(T,)`` int32: overlapping unordered pairs in each frame. Memory is
      ``O(N^2)`` per frame (frames are processed one after another).
    """
    positions = _as_trajectory("positions", positions)
    _, n, dim = positions.shape
    radius = _as_radius(radius, n, positions.dtype)
    real = _weights(mask, n, bool)
    threshold = coeff * jnp.minimum(radius[:, None], radius[None, :])
    upper = jnp.arange(n)[:, None] < jnp.arange(n)[None, :]
    counted = upper & real[:, None] & real[None, :]

    def frame(x):
        # Per-axis (N, N) arrays: cheaper on CPU than an (N, N, D) array.
        dist2 = sum((x[:, d, None] - x[None, :, d]) ** 2 for d in range(dim))
        return jnp.sum((dist2 < threshold**2) & counted, dtype=jnp.int32)

    return lax.map(frame, positions)


def kinetic_energy(
    positions: Positions,
    radius: Radii,
    *,
    box_half_size: float,
    frame_dt: float,
    mask: ParticleMask | None = None,
    config: PhysicsConfig | None = None,
) -> _Steps:
    """Total kinetic energy in joules from finite-difference velocities.

    The velocity at frame ``k >= 1`` is the backward difference
    ``(x_k - x_{k-1}) L / frame_dt`` (m/s), the one the learned simulator
    itself uses; the mass is the physics' ``m_i = pi a_i^2 s rho`` for disks
    (``D = 2``, thickness and density from ``config``) or ``4/3 pi a_i^3 rho``
    for spheres (``D = 3``). Ratios of energies do not depend on ``s`` or
    ``rho``, only on ``m_i ∝ a_i^2``.

    Args:
      positions: ``(T, N, D)`` normalised. radius: ``(N,)`` normalised.
      box_half_size: ``L`` in m. frame_dt: frame spacing in s.
      mask: optional ``(N,)`` bool.
      config: physics parameters for the mass (default :class:`PhysicsConfig`).

    Returns:
      ``(T - 1,)``: entry ``k - 1`` is the kinetic energy ``sum_i m_i |v_i|^2 / 2``
      of frame ``k`` in J.
    """
    config = PhysicsConfig() if config is None else config
    positions = _as_trajectory("positions", positions)
    _, n, dim = positions.shape
    radius = _as_radius(radius, n, positions.dtype)
    weight = _weights(mask, n, positions.dtype)
    mass = jnp.where(weight > 0, particle_mass(radius * box_half_size, config, dim), 0.0)
    velocity = (positions[1:] - positions[:-1]) * (box_half_size / frame_dt)
    speed2 = jnp.where(weight > 0, jnp.sum(velocity**2, axis=-1), 0.0)
    return 0.5 * speed2 @ mass


def mean_height(positions: Positions, mask: ParticleMask | None = None) -> PerFrame:
    """Mean over real particles of the last coordinate (height, against gravity).

    Args:
      positions: ``(T, N, D)`` normalised. mask: optional ``(N,)`` bool.

    Returns:
      ``(T,)`` mean height per frame in normalised units.
    """
    positions = _as_trajectory("positions", positions)
    weight = _weights(mask, positions.shape[1], positions.dtype)
    height = jnp.where(weight > 0, positions[..., -1], 0.0)
    return height @ weight / jnp.sum(weight)


# ----------------------------------------------------------------------------
# statistics of the suspension (what chaos cannot hide)
# ----------------------------------------------------------------------------


def _default_bounds(dim: int, dtype) -> jnp.ndarray:
    return jnp.tile(jnp.asarray([[-1.0, 1.0]], dtype), (dim, 1))


def _particle_volume(radius, dim: int):
    """Area (``D = 2``) or volume (``D = 3``) of each particle, in the radius' units to the power ``D``."""
    return math.pi * radius**2 if dim == 2 else (4.0 / 3.0) * math.pi * radius**3


def front_height(positions: Positions, mask: ParticleMask | None = None, *, quantile: float = 0.95) -> PerFrame:
    """Height of the suspension front: the ``quantile`` of the particles' heights, per frame.

    The front of a settling suspension is the level below which nearly all
    particles lie; a quantile (``np.quantile``'s linear interpolation) rather
    than the maximum, so that one straggler does not move it.

    Args:
      positions: ``(T, N, D)`` normalised; the last axis is the height.
      mask: optional ``(N,)`` bool, ``False`` for padding.
      quantile: static, in ``[0, 1]``.

    Returns:
      ``(T,)`` front height per frame, normalised units.
    """
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"quantile must lie in [0, 1], got {quantile}")
    positions = _as_trajectory("positions", positions)
    n = positions.shape[1]
    weight = _weights(mask, n, positions.dtype)
    # Padding sorts last (+inf) and the quantile index only spans the real particles.
    heights = jnp.sort(jnp.where(weight > 0, positions[..., -1], jnp.inf), axis=-1)
    index = quantile * (jnp.sum(weight) - 1.0)
    lower = jnp.clip(jnp.floor(index).astype(jnp.int32), 0, n - 1)
    upper = jnp.clip(lower + 1, 0, jnp.sum(weight).astype(jnp.int32) - 1)
    fraction = (index - lower).astype(positions.dtype)
    low = jnp.take(heights, lower, axis=-1)
    high = jnp.take(heights, upper, axis=-1)
    return low + fraction * (high - low)


def settling_velocity(heights: PerFrame, *, frame_dt: float, box_half_size: float) -> Scalar:
    """Least-squares slope of a height curve, in m/s (negative when settling).

    Args:
      heights: ``(T,)`` normalised heights at frames spaced ``frame_dt`` s
        apart (e.g. :func:`mean_height` or :func:`front_height`).
      frame_dt: frame spacing in s. box_half_size: ``L`` in m.

    Returns:
      Scalar velocity in m/s (multiply by 1e3 for mm/s).
    """
    heights = jnp.asarray(heights)
    if heights.ndim != 1 or heights.shape[0] < 2:
        raise ValueError(f"heights must have shape (T,) with T >= 2, got {heights.shape}")
    t = jnp.arange(heights.shape[0], dtype=heights.dtype) * frame_dt
    t = t - jnp.mean(t)
    slope = jnp.sum(t * (heights - jnp.mean(heights))) / jnp.sum(t * t)
    return slope * box_half_size


def height_profile(
    frame: Frame,
    radius: Radii,
    mask: ParticleMask | None = None,
    *,
    bins: int = 20,
    bounds: Box | None = None,
) -> tuple[_BinCounts, _Bins]:
    """Particle count and area (volume) fraction per height bin of one frame.

    The box's height range is cut into ``bins`` equal slabs; a particle counts
    in the slab of its centre, with all of its area (``D = 2``) or volume
    (``D = 3``) (slabs several diameters thick make the split negligible).

    Args:
      frame: ``(N, D)`` normalised positions. radius: ``(N,)`` normalised.
      mask: optional ``(N,)`` bool.
      bins: static number of slabs.
      bounds: ``(D, 2)`` box in normalised units (default ``[-1, 1]^D``).

    Returns:
      ``(counts, fraction)``, both ``(bins,)``: particles per slab (float) and
      the fraction of the slab's area (volume) they fill. Slab ``k`` spans
      heights ``lo + k h .. lo + (k + 1) h``, ``h = (hi - lo) / bins``.
    """
    frame = jnp.asarray(frame)
    if frame.ndim != 2:
        raise ValueError(f"frame must have shape (N, D), got {frame.shape}")
    n, dim = frame.shape
    bounds = _default_bounds(dim, frame.dtype) if bounds is None else jnp.asarray(bounds, frame.dtype)
    radius = _as_radius(radius, n, frame.dtype)
    weight = _weights(mask, n, frame.dtype)
    lo, hi = bounds[-1, 0], bounds[-1, 1]
    slab = (hi - lo) / bins
    index = jnp.clip(jnp.floor((frame[:, -1] - lo) / slab).astype(jnp.int32), 0, bins - 1)
    one_hot = jax.nn.one_hot(index, bins, dtype=frame.dtype) * weight[:, None]
    counts = jnp.sum(one_hot, axis=0)
    width = jnp.prod(bounds[:-1, 1] - bounds[:-1, 0])
    fraction = (_particle_volume(radius, dim) @ one_hot) / (slab * width)
    return counts, fraction


def bed_area_fraction(
    frame: Frame,
    radius: Radii,
    mask: ParticleMask | None = None,
    *,
    quantile: float = 0.95,
    bounds: Box | None = None,
) -> Scalar:
    """Area (volume) fraction of a bed: the particles' total area over the box below the front.

    Args:
      frame: ``(N, D)`` normalised positions. radius: ``(N,)`` normalised.
      mask: optional ``(N,)`` bool. quantile: see :func:`front_height`.
      bounds: ``(D, 2)`` box (default ``[-1, 1]^D``).

    Returns:
      Scalar: ``sum_i V(a_i) / (W (h_front - lo))`` with ``W`` the box's
      horizontal extent and ``lo`` its floor.
    """
    frame = jnp.asarray(frame)
    n, dim = frame.shape
    bounds = _default_bounds(dim, frame.dtype) if bounds is None else jnp.asarray(bounds, frame.dtype)
    radius = _as_radius(radius, n, frame.dtype)
    weight = _weights(mask, n, frame.dtype)
    front = front_height(frame[None], mask, quantile=quantile)[0]
    width = jnp.prod(bounds[:-1, 1] - bounds[:-1, 0])
    return (_particle_volume(radius, dim) @ weight) / (width * (front - bounds[-1, 0]))


def radial_distribution(
    frame: Frame,
    *,
    r_max: float,
    bins: int,
    volume: float,
    mask: ParticleMask | None = None,
    query_mask: ParticleMask | None = None,
) -> tuple[_Bins, _Bins]:
    """Radial distribution function g(r) of one frame (no periodic images).

    Counts, for every query particle ``i`` (``query_mask``), the particles
    ``j != i`` (``mask``) at distance ``r`` in each shell, and divides by the
    ideal-gas count ``N_query (N / volume) shell``: freud's
    ``freud.density.RDF`` with ``normalization_mode="exact"`` on a box large
    enough to have no images (tested). Two size classes give the partial
    g(r) of the pair with ``query_mask`` = one class and ``mask`` = the other.

    Args:
      frame: ``(N, D)`` positions (any length unit; ``r_max`` and ``volume``
        in the same unit).
      r_max: static largest distance. bins: static number of shells.
      volume: area (``D = 2``) or volume (``D = 3``) the density is taken over.
      mask: optional ``(N,)`` bool, the particles counted as neighbours.
      query_mask: optional ``(N,)`` bool, the particles whose neighbours are
        counted (default ``mask``).

    Returns:
      ``(r, g)``, both ``(bins,)``: shell centres and g(r) (``nan`` when there
      are no query or neighbour particles).
    """
    frame = jnp.asarray(frame)
    if frame.ndim != 2:
        raise ValueError(f"frame must have shape (N, D), got {frame.shape}")
    n, dim = frame.shape
    weight = _weights(mask, n, frame.dtype)
    query = weight if query_mask is None else _weights(query_mask, n, frame.dtype)
    edges = jnp.linspace(0.0, r_max, bins + 1, dtype=frame.dtype)
    dist2 = sum((frame[:, d, None] - frame[None, :, d]) ** 2 for d in range(dim))
    pair = query[:, None] * weight[None, :] * (1.0 - jnp.eye(n, dtype=frame.dtype))
    # Squared distances against squared edges: no sqrt, and [lo, hi) shells as freud. The shell of
    # each pair is searched and its weight added by bincount: a one-hot (N, N, bins) array took
    # ~1 GB per call at N ~ 3,000 (and evaluate vmaps 16 calls), this needs (N, N) only.
    index = jnp.searchsorted(edges[1:] ** 2, dist2, side="right")
    counts = jnp.bincount(index.ravel(), weights=pair.ravel(), length=bins + 1)[:bins]
    shell = (math.pi if dim == 2 else 4.0 * math.pi / 3.0) * (edges[1:] ** dim - edges[:-1] ** dim)
    ideal = jnp.sum(query) * (jnp.sum(weight) / volume) * shell
    return 0.5 * (edges[1:] + edges[:-1]), counts / ideal


def sinkhorn_divergence(
    x: Frame,
    y: _OtherCloud,
    *,
    epsilon: float,
    mask_x: ParticleMask | None = None,
    mask_y: _OtherMask | None = None,
) -> Scalar:
    """Debiased Sinkhorn divergence between two point clouds (``ott-jax``).

    ``S(x, y) = OT_eps(x, y) - (OT_eps(x, x) + OT_eps(y, y)) / 2`` with the
    squared Euclidean cost ``|x - y|^2`` and uniform weights on the real
    points: 0 for identical clouds, ``|t|^2`` for a cloud and its translate by
    ``t``, in the points' unit squared.

    Args:
      x: ``(N, D)``. y: ``(M, D)``.
      epsilon: static entropic regularisation, in the points' unit squared
        (about the squared distance below which points are not told apart).
      mask_x, mask_y: optional bool masks of the real points.

    Returns:
      Scalar divergence.
    """
    from ott.geometry import pointcloud
    from ott.tools import sinkhorn_divergence as ott_divergence

    x, y = jnp.asarray(x), jnp.asarray(y)
    a = _weights(mask_x, x.shape[0], x.dtype)
    b = _weights(mask_y, y.shape[0], y.dtype)
    value, _ = ott_divergence.sinkhorn_divergence(
        pointcloud.PointCloud, x, y, a=a / jnp.sum(a), b=b / jnp.sum(b), epsilon=epsilon
    )
    return value


def maximum_mean_discrepancy(
    x: Frame,
    y: _OtherCloud,
    *,
    bandwidths: Sequence[float],
    mask_x: ParticleMask | None = None,
    mask_y: _OtherMask | None = None,
) -> Scalar:
    """Squared maximum mean discrepancy between two point clouds (biased estimate).

    ``MMD^2 = E k(x, x') + E k(y, y') - 2 E k(x, y)`` with the sum of Gaussian
    kernels ``k(u, v) = sum_s exp(-|u - v|^2 / (2 s^2))`` over ``bandwidths``,
    means over the real points (pairs with themselves included, so it is
    ``>= 0``, symmetric, and 0 for equal clouds).

    Args:
      x: ``(N, D)``. y: ``(M, D)``.
      bandwidths: static kernel widths, in the points' unit.
      mask_x, mask_y: optional bool masks of the real points.

    Returns:
      Scalar ``MMD^2`` (dimensionless; between 0 and ``2 len(bandwidths)``).
    """
    x, y = jnp.asarray(x), jnp.asarray(y)
    a = _weights(mask_x, x.shape[0], x.dtype)
    b = _weights(mask_y, y.shape[0], y.dtype)
    a, b = a / jnp.sum(a), b / jnp.sum(b)

    def mean_kernel(u, wu, v, wv):
        dist2 = sum((u[:, d, None] - v[None, :, d]) ** 2 for d in range(u.shape[1]))
        k = sum(jnp.exp(-dist2 / (2.0 * s * s)) for s in bandwidths)
        return wu @ k @ wv

    return mean_kernel(x, a, x, a) + mean_kernel(y, b, y, b) - 2.0 * mean_kernel(x, a, y, b)


# ----------------------------------------------------------------------------
# baselines
# ----------------------------------------------------------------------------


def constant_velocity_rollout(positions: Positions, *, input_frames: int = 6, n_frames: int | None = None) -> Positions:
    """The constant-velocity baseline.

    Keeps the ``C`` input frames and then moves every particle on with its
    last input velocity: ``x_{C-1+k} = x_{C-1} + k (x_{C-1} - x_{C-2})``.
    Walls and other particles are ignored, so it is the error a model that
    learned nothing about forces would make.

    Args:
      positions: ``(T', N, D)`` with ``T' >= C``; only frames ``C-2, C-1`` are
        used (any unit).
      input_frames: static ``C >= 2``.
      n_frames: static total number of frames returned (default ``T'``).

    Returns:
      ``(n_frames, N, D)`` trajectory, frames ``0 .. C-1`` equal to the input.
    """
    positions = _as_trajectory("positions", positions)
    n_frames = positions.shape[0] if n_frames is None else n_frames
    if not 2 <= input_frames <= positions.shape[0]:
        raise ValueError(f"input_frames must lie in [2, T] = [2, {positions.shape[0]}], got {input_frames}")
    if n_frames < input_frames:
        raise ValueError(f"n_frames ({n_frames}) must be >= input_frames ({input_frames})")
    last = positions[input_frames - 1]
    velocity = last - positions[input_frames - 2]
    steps = jnp.arange(1, n_frames - input_frames + 1, dtype=positions.dtype)
    future = last[None] + steps[:, None, None] * velocity[None]
    return jnp.concatenate([positions[:input_frames], future], axis=0)


# ----------------------------------------------------------------------------
# reports
# ----------------------------------------------------------------------------


def _floats(values) -> list[float]:
    return [float(v) for v in np.asarray(values, np.float64).ravel()]


def _ints(values) -> list[int]:
    return [int(v) for v in np.asarray(values).ravel()]


# Particle counts are padded up to a multiple of this inside rollout_metrics so
# that test sets whose trajectories differ by a few particles share one
# compiled program (padding never changes a metric: it is masked out).
_PARTICLE_BUCKET = 32


def _metric_arrays(
    prediction,
    truth,
    chaos,
    radius,
    mask,
    *,
    input_frames,
    box_half_size,
    frame_dt,
    wall_tolerance,
    overlap_coeff,
    config,
    bounds=None,
):
    """Every per-frame array of :func:`rollout_metrics`, in one XLA program."""
    c = input_frames
    energy = dict(box_half_size=box_half_size, frame_dt=frame_dt, mask=mask, config=config)
    baseline = constant_velocity_rollout(truth, input_frames=c)
    out = {
        "curve": per_frame_mse(prediction, truth, input_frames=c, mask=mask),
        "constant_velocity_curve": per_frame_mse(baseline, truth, input_frames=c, mask=mask),
        "walls": wall_violations(prediction[c:], radius, tolerance=wall_tolerance, mask=mask, bounds=bounds),
        "walls_truth": wall_violations(truth[c:], radius, tolerance=wall_tolerance, mask=mask, bounds=bounds),
        "overlaps": overlap_counts(prediction[c:], radius, coeff=overlap_coeff, mask=mask),
        "overlaps_truth": overlap_counts(truth[c:], radius, coeff=overlap_coeff, mask=mask),
        # kinetic_energy's entry k - 1 is frame k: keep frames c .. T-1.
        "ke_pred": kinetic_energy(prediction, radius, **energy)[c - 1 :],
        "ke_true": kinetic_energy(truth, radius, **energy)[c - 1 :],
        "height_pred": mean_height(prediction[c:], mask),
        "height_true": mean_height(truth[c:], mask),
        "finite": jnp.all(jnp.isfinite(prediction[c:]) | ~mask[None, :, None]),
        "mean_diameter": 2.0 * jnp.sum(jnp.where(mask, radius, 0.0)) / jnp.sum(mask),
    }
    if chaos is not None:
        out["chaos_floor_curve"] = per_frame_mse(chaos, truth, input_frames=c, mask=mask)
    return out


_metric_arrays_jit = jax.jit(
    _metric_arrays,
    static_argnames=(
        "input_frames",
        "box_half_size",
        "frame_dt",
        "wall_tolerance",
        "overlap_coeff",
        "config",
        "bounds",
    ),
)


# Settings of the suspension statistics in rollout_metrics (normalised lengths unless said otherwise).
STATISTICS_DEFAULTS: dict[str, Any] = {
    "front_quantile": 0.95,  # the front is the height below which 95 % of the centres lie
    "profile_bins": 20,  # slabs of the final height profile (1 cm for L = 0.1 m)
    "rdf_bins": 30,
    "rdf_max": 0.3,  # g(r) up to 0.3 L (3 cm, ~4 mean diameters), shells of 1 mm
    "distribution_frames": 10,  # frames (evenly spaced, the last included) of the Sinkhorn / MMD curves
    "sinkhorn_epsilon_position": 1e-3,  # (normalised length)^2: (3.2 mm)^2, about a radius squared
    "sinkhorn_epsilon_velocity": 1e-3,  # (m/s)^2
    "mmd_bandwidths_position": (0.05, 0.2, 0.8),  # normalised: 5 mm, 2 cm, 8 cm
    "mmd_bandwidths_velocity": (0.01, 0.04, 0.16),  # m/s
}
RDF_PAIRS: tuple[str, ...] = ("small_small", "small_large", "large_large")
"""Size-class pairs of the partial g(r): particles below the midpoint of the smallest and largest radius are small."""


def _statistics_of(trajectory, radius, mask, *, c, frame_dt, box_half_size, settings, bounds):
    """Per-trajectory statistics of one (T, N, D) trajectory: curves over the predicted frames, final-frame bed."""
    s = settings
    dim = trajectory.shape[-1]
    final = trajectory[-1]
    front = front_height(trajectory[c:], mask, quantile=s["front_quantile"])
    height = mean_height(trajectory[c:], mask)
    counts, fraction = height_profile(final, radius, mask, bins=s["profile_bins"], bounds=bounds)
    real_radius = jnp.where(mask, radius, jnp.nan)
    middle = 0.5 * (jnp.nanmin(real_radius) + jnp.nanmax(real_radius))
    small = mask & (radius < middle)
    large = mask & (radius >= middle)
    volume = 2.0**dim if bounds is None else float(np.prod([hi - lo for lo, hi in bounds]))
    rdf = dict(r_max=s["rdf_max"], bins=s["rdf_bins"], volume=volume)
    r, g_all = radial_distribution(final, mask=mask, **rdf)
    partial = [
        radial_distribution(final, mask=b, query_mask=a, **rdf)[1]
        for a, b in ((small, small), (small, large), (large, large))
    ]
    return {
        "front": front,
        "height": height,
        "front_velocity": settling_velocity(front, frame_dt=frame_dt, box_half_size=box_half_size),
        "height_velocity": settling_velocity(height, frame_dt=frame_dt, box_half_size=box_half_size),
        "profile": counts,
        "fraction": fraction,
        "bed_fraction": bed_area_fraction(final, radius, mask, quantile=s["front_quantile"], bounds=bounds),
        "rdf_r": r,
        "rdf": jnp.stack([g_all, *partial]),
        "class_counts": jnp.stack([jnp.sum(small), jnp.sum(large)]),
    }


def _distances(trajectory, truth, mask, frames, *, frame_dt, box_half_size, settings, sinkhorn: bool):
    """Sinkhorn divergence (if ``sinkhorn``) and MMD^2 of positions and velocities (m/s) at ``frames``, ``(K,)``."""
    s = settings
    index = jnp.asarray(frames)
    scale = box_half_size / frame_dt

    def clouds(t):
        return t[index], (t[index] - t[index - 1]) * scale

    x, vx = clouds(trajectory)
    y, vy = clouds(truth)
    both = dict(mask_x=mask, mask_y=mask)

    def per_frame(fn, u, v, **kw):
        # One frame after the other (lax.map, not vmap): each frame's MMD kernels and Sinkhorn
        # costs are (N, N), and the K frames side by side, for every trajectory compared, took
        # over 14 GB at N ~ 3,000 (the wide16 container) where one frame at a time needs K x less.
        return jax.lax.map(lambda ab: fn(ab[0], ab[1], **kw, **both), (u, v))

    out = {
        "mmd_position": per_frame(maximum_mean_discrepancy, x, y, bandwidths=s["mmd_bandwidths_position"]),
        "mmd_velocity": per_frame(maximum_mean_discrepancy, vx, vy, bandwidths=s["mmd_bandwidths_velocity"]),
    }
    if sinkhorn:
        out["sinkhorn_position"] = per_frame(sinkhorn_divergence, x, y, epsilon=s["sinkhorn_epsilon_position"])
        out["sinkhorn_velocity"] = per_frame(sinkhorn_divergence, vx, vy, epsilon=s["sinkhorn_epsilon_velocity"])
    return out


def _statistics_arrays(
    trajectories, radius, mask, *, input_frames, frame_dt, box_half_size, frames, settings, sinkhorn_rows, bounds
):
    """Statistics of every trajectory of ``(M, T, N, D)`` (the truth first) and the distances of the others to it.

    Vectorised over the trajectories (the frames inside :func:`_distances` go one after the other, to bound
    the memory of their (N, N) matrices) so that the Sinkhorn solves of a frame are one loop in one program,
    not one copy per trajectory. Only the rows
    ``sinkhorn_rows`` of ``trajectories[1:]`` get Sinkhorn divergences: a vectorised solve runs until its
    slowest member converges, and the constant-velocity cloud, metres outside the box, takes the 2000
    iterations ott allows at this epsilon (10x the model's).
    """
    settings = dict(settings)
    common = dict(frame_dt=frame_dt, box_half_size=box_half_size, settings=settings)
    truth = trajectories[0]
    stats = jax.vmap(lambda t: _statistics_of(t, radius, mask, c=input_frames, bounds=bounds, **common))(trajectories)
    distances = jax.vmap(lambda t: _distances(t, truth, mask, frames, sinkhorn=False, **common))(trajectories[1:])
    rows = trajectories[1:][jnp.asarray(sinkhorn_rows, jnp.int32)]
    sinkhorn = jax.vmap(lambda t: _distances(t, truth, mask, frames, sinkhorn=True, **common))(rows)
    for key in ("sinkhorn_position", "sinkhorn_velocity"):
        full = jnp.full(distances["mmd_position"].shape, jnp.nan, sinkhorn[key].dtype)
        distances[key] = full.at[jnp.asarray(sinkhorn_rows, jnp.int32)].set(sinkhorn[key])
    return stats, distances


_statistics_arrays_jit = jax.jit(
    _statistics_arrays,
    static_argnames=("input_frames", "frame_dt", "box_half_size", "frames", "settings", "sinkhorn_rows", "bounds"),
)


def _statistics_report(prefix: str, mine, truth, distances, *, box_half_size: float, n_real: int) -> dict[str, Any]:
    """The JSON entries of one compared trajectory (model ``""``, ``constant_velocity_``, ``chaos_floor_``)."""
    mm = box_half_size * 1e3
    out: dict[str, Any] = {}
    front_error = np.asarray(mine["front"], np.float64) - np.asarray(truth["front"], np.float64)
    height_error = np.asarray(mine["height"], np.float64) - np.asarray(truth["height"], np.float64)
    out[f"{prefix}front_height_error"] = _floats(front_error)
    out[f"{prefix}front_height_mean_abs_error_mm"] = float(np.mean(np.abs(front_error))) * mm
    out[f"{prefix}front_height_final_error_mm"] = float(front_error[-1]) * mm
    if prefix:  # the model's mean-height entries exist already (rollout_metrics)
        out[f"{prefix}mean_height"] = _floats(mine["height"])
        out[f"{prefix}mean_height_mean_abs_error_mm"] = float(np.mean(np.abs(height_error))) * mm
        out[f"{prefix}mean_height_final_error_mm"] = float(height_error[-1]) * mm
    else:
        out["mean_height_final_error_mm"] = float(height_error[-1]) * mm
    for name, key in (("front_settling_velocity", "front_velocity"), ("settling_velocity", "height_velocity")):
        out[f"{prefix}{name}_mm_s"] = float(mine[key]) * 1e3
        out[f"{prefix}{name}_error_mm_s"] = (float(mine[key]) - float(truth[key])) * 1e3
    profile = np.asarray(mine["profile"], np.float64)
    out[f"{prefix}height_profile"] = _floats(profile)
    # Half the L1 distance of the count profiles over N: the fraction of particles in the wrong slab.
    out[f"{prefix}height_profile_distance"] = 0.5 * float(np.sum(np.abs(profile - truth["profile"]))) / n_real
    out[f"{prefix}area_fraction_profile"] = _floats(mine["fraction"])
    out[f"{prefix}area_fraction_profile_max_error"] = float(np.max(np.abs(mine["fraction"] - truth["fraction"])))
    out[f"{prefix}bed_area_fraction"] = float(mine["bed_fraction"])
    out[f"{prefix}bed_area_fraction_error"] = float(mine["bed_fraction"]) - float(truth["bed_fraction"])
    rdf, rdf_truth = np.asarray(mine["rdf"], np.float64), np.asarray(truth["rdf"], np.float64)
    out[f"{prefix}rdf"] = _floats(rdf[0])
    # Mean |g - g_truth| over the shells (the L1 distance over r_max): dimensionless.
    out[f"{prefix}rdf_l1"] = float(np.mean(np.abs(rdf[0] - rdf_truth[0])))
    small, large = (int(v) for v in np.asarray(truth["class_counts"]))
    if small >= 2 and large >= 2:
        for row, pair in enumerate(RDF_PAIRS, start=1):
            out[f"{prefix}rdf_l1_{pair}"] = float(np.mean(np.abs(rdf[row] - rdf_truth[row])))
    for key, values in distances.items():
        values = np.asarray(values, np.float64)
        if key.startswith("sinkhorn") and prefix == "constant_velocity_":
            continue  # not computed (see _statistics_arrays)
        out[f"{prefix}{key}"] = _floats(values)
        out[f"{prefix}{key}_final"] = float(values[-1])
        out[f"{prefix}{key}_mean"] = float(np.mean(values))
    return out


def _error_family(prefix: str, curve, mean_diameter: float, box_half_size: float, horizons) -> dict[str, Any]:
    curve = np.asarray(curve, np.float64)
    mse = float(np.mean(curve))
    rmse = math.sqrt(mse) if mse >= 0 else float("nan")
    out: dict[str, Any] = {
        f"{prefix}mse": mse,
        f"{prefix}rmse_mm": rmse * box_half_size * 1e3,
        f"{prefix}rmse_diameters": rmse / mean_diameter,
    }
    for h, value in horizon_mse(curve, horizons).items():
        out[f"{prefix}mse_h{h}"] = value
    out[f"{prefix}per_frame_mse"] = _floats(curve)
    return out


def rollout_metrics(
    prediction: Positions,
    truth: Positions,
    radius: Radii,
    *,
    box_half_size: float,
    input_frames: int = 6,
    frame_dt: float = 1.5e-3,
    mask: ParticleMask | None = None,
    horizons: Sequence[int] = DEFAULT_HORIZONS,
    wall_tolerance: float = 0.1,
    overlap_coeff: float = 1.75,
    chaos_floor: Positions | None = None,
    physics_config: PhysicsConfig | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
    statistics: bool = False,
    statistics_settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Every metric of one rollout, as a JSON-ready dict.

    Args:
      prediction, truth: ``(T, N, D)`` normalised positions; frames
        ``0 .. C-1`` are the inputs (the prediction's should equal the truth's).
      radius: ``(N,)`` normalised radii.
      box_half_size: ``L`` in m (0.1 in the paper).
      input_frames: ``C``.
      frame_dt: frame spacing in s (1.5e-3 in the paper).
      mask: optional ``(N,)`` bool; padding particles are excluded everywhere.
      horizons: horizons (predicted frames) for ``mse_h{h}``.
      wall_tolerance: see :func:`wall_violations`.
      overlap_coeff: see :func:`overlap_counts`.
      chaos_floor: optional ``(T, N, D)`` normalised trajectory from
        :func:`dispgns.evaluation.chaos_floor_rollout`; adds the ``chaos_floor_*`` entries.
      bounds: the box ``((lo, hi),) * D`` in normalised units for the wall
        violations (``None``: ``[-1, 1]^D``, the paper's box).
      physics_config: masses for the kinetic energy (default
        :class:`PhysicsConfig`; only ``thickness`` and ``density`` matter).
      statistics: add the suspension statistics below (off by default:
        their program, with its Sinkhorn solves, takes ~20 s to compile
        for each particle-count bucket, then ~1-3 s per trajectory).
      statistics_settings: overrides of :data:`STATISTICS_DEFAULTS`.

    Returns:
      A dict of Python scalars and lists. Per-frame lists have ``T - C``
      entries, entry ``k`` being frame ``C + k``. Keys:

      * ``mse`` (the paper's rollout MSE, normalised units squared),
        ``rmse_mm``, ``rmse_diameters`` (RMSE over the mean diameter
        ``2 mean(a_i)``), ``mse_times_L_mm`` (the paper's "mm" number, not a
        length), ``mse_h1``, ``mse_h10``, ``mse_h50``, ``mse_h100``,
        ``mse_hfull`` (``None`` when a horizon exceeds ``T - C``),
        ``per_frame_mse``;
      * ``constant_velocity_*``: the same error family for
        :func:`constant_velocity_rollout` of the truth, and
        ``mse_over_constant_velocity`` (model MSE / baseline MSE);
      * ``chaos_floor_*``: the same error family for ``chaos_floor`` (only if
        given);
      * ``wall_violations_per_frame``, ``wall_violations_total`` (particle-frames
        of the prediction outside the box, predicted frames only),
        ``wall_violations_truth_total``;
      * ``overlaps_per_frame``, ``overlaps_total``, ``overlaps_max``,
        ``overlaps_truth_total``, ``overlaps_truth_max`` (pairs closer than
        ``overlap_coeff * min(a_i, a_j)``; the truth itself has a few where
        disks pile up);
      * ``kinetic_energy_truth``, ``kinetic_energy_prediction`` (per frame, J,
        see :func:`kinetic_energy`), ``kinetic_energy_relative_error`` (per
        frame, ``(KE_pred - KE_true) / mean_t KE_true``: normalised by the
        truth's mean over the predicted frames because the energy of a settled
        suspension approaches 0), ``kinetic_energy_mean_abs_relative_error``
        and ``kinetic_energy_total_relative_error``
        (``sum_t (KE_pred - KE_true) / sum_t KE_true``, signed);
      * ``mean_height_truth``, ``mean_height_error`` (per frame, prediction
        minus truth, normalised), ``mean_height_mean_abs_error``,
        ``mean_height_final_error`` (normalised), ``mean_height_mean_abs_error_mm``;
      * suspension statistics (with ``statistics``), for the model (no
        prefix), ``constant_velocity_`` and ``chaos_floor_`` (if given) side
        by side, each against the truth: the front (:func:`front_height`)
        ``front_height_truth``, ``*front_height_error`` (per frame,
        normalised), ``*front_height_mean_abs_error_mm``,
        ``*front_height_final_error_mm``; settling velocities (least-squares
        slopes over the predicted frames) of the front and of the mean
        height, ``front_settling_velocity_truth_mm_s``,
        ``settling_velocity_truth_mm_s``, ``*front_settling_velocity_mm_s``,
        ``*front_settling_velocity_error_mm_s``, ``*settling_velocity_mm_s``,
        ``*settling_velocity_error_mm_s``; the mean height of the baselines
        ``*mean_height`` and ``*mean_height_mean_abs_error_mm``,
        ``*mean_height_final_error_mm``; the final bed
        (:func:`height_profile`): ``height_profile_truth``,
        ``*height_profile`` (counts per slab), ``*height_profile_distance``
        (fraction of particles in another slab than the truth's count says),
        ``area_fraction_profile_truth``, ``*area_fraction_profile``,
        ``*area_fraction_profile_max_error``, ``bed_area_fraction_truth``,
        ``*bed_area_fraction``, ``*bed_area_fraction_error``
        (:func:`bed_area_fraction`); g(r) of the final frame
        (:func:`radial_distribution`, density over the box) ``rdf_r``,
        ``rdf_truth``, ``*rdf``, ``*rdf_l1`` (mean ``|g - g_truth|`` over the
        shells) and, when both size classes (:data:`RDF_PAIRS`) have at least
        two particles, ``*rdf_l1_small_small``, ``*rdf_l1_small_large``,
        ``*rdf_l1_large_large``; distribution distances at the predicted
        frames ``distribution_frames``: ``*sinkhorn_position``
        (normalised length squared), ``*sinkhorn_velocity`` ((m/s)^2),
        ``*mmd_position``, ``*mmd_velocity`` (MMD^2, dimensionless), each as a
        list, ``*_final`` and ``*_mean`` (no Sinkhorn divergence for the
        constant-velocity baseline, whose cloud leaves the box: the solve
        would not converge at this epsilon, and its MMD tells the story);
      * ``finite`` (all predicted positions finite) and the settings
        ``n_frames``, ``n_particles``, ``input_frames``, ``frame_dt``,
        ``box_half_size``, ``wall_tolerance``, ``overlap_coeff``.

      Values are ``nan`` where the prediction is not finite. Not jittable
      (host-level; it returns Python numbers).
    """
    if not isinstance(input_frames, (int, np.integer)) or input_frames < 2:
        # The constant-velocity baseline needs a velocity, i.e. two input frames.
        raise ValueError(f"input_frames must be an integer >= 2 for rollout_metrics, got {input_frames!r}")
    prediction, truth = _check_pair(prediction, truth, input_frames)
    n_frames, n, _ = truth.shape
    dtype = truth.dtype
    prediction = np.asarray(prediction, dtype)
    truth = np.asarray(truth, dtype)
    radius = np.asarray(_as_radius(radius, n, dtype))
    real = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    if real.shape != (n,):
        raise ValueError(f"mask must have shape ({n},), got {real.shape}")
    if chaos_floor is not None:
        chaos_floor = np.asarray(_as_trajectory("chaos_floor", chaos_floor), dtype)
        if chaos_floor.shape != truth.shape:
            raise ValueError(f"chaos_floor must have the truth's shape {truth.shape}, got {chaos_floor.shape}")
    c = input_frames

    extra = -n % _PARTICLE_BUCKET
    arrays = _metric_arrays_jit(
        pad_particles(prediction, extra, axis=1, fill=0.0),
        pad_particles(truth, extra, axis=1, fill=0.0),
        None if chaos_floor is None else pad_particles(chaos_floor, extra, axis=1, fill=0.0),
        pad_particles(radius, extra, axis=0, fill=1.0),
        pad_particles(real, extra, axis=0, fill=False),
        input_frames=c,
        box_half_size=float(box_half_size),
        frame_dt=float(frame_dt),
        wall_tolerance=float(wall_tolerance),
        overlap_coeff=float(overlap_coeff),
        config=PhysicsConfig() if physics_config is None else physics_config,
        bounds=None if bounds is None else tuple(tuple(float(v) for v in pair) for pair in bounds),
    )
    arrays = jax.device_get(arrays)
    mean_diameter = float(arrays["mean_diameter"])

    out: dict[str, Any] = {
        "n_frames": int(n_frames),
        "n_particles": int(real.sum()),
        "input_frames": int(c),
        "frame_dt": float(frame_dt),
        "box_half_size": float(box_half_size),
        "wall_tolerance": float(wall_tolerance),
        "overlap_coeff": float(overlap_coeff),
        "finite": bool(arrays["finite"]),
    }
    out.update(_error_family("", arrays["curve"], mean_diameter, box_half_size, horizons))
    out["mse_times_L_mm"] = out["mse"] * box_half_size * 1e3

    out.update(
        _error_family("constant_velocity_", arrays["constant_velocity_curve"], mean_diameter, box_half_size, horizons)
    )
    baseline_mse = out["constant_velocity_mse"]
    out["mse_over_constant_velocity"] = out["mse"] / baseline_mse if baseline_mse > 0 else float("nan")

    if chaos_floor is not None:
        out.update(_error_family("chaos_floor_", arrays["chaos_floor_curve"], mean_diameter, box_half_size, horizons))

    walls, overlaps, overlaps_truth = arrays["walls"], arrays["overlaps"], arrays["overlaps_truth"]
    out["wall_violations_per_frame"] = _ints(walls)
    out["wall_violations_total"] = int(np.sum(walls))
    out["wall_violations_truth_total"] = int(np.sum(arrays["walls_truth"]))
    out["overlaps_per_frame"] = _ints(overlaps)
    out["overlaps_total"] = int(np.sum(overlaps))
    out["overlaps_max"] = int(np.max(overlaps))
    out["overlaps_truth_total"] = int(np.sum(overlaps_truth))
    out["overlaps_truth_max"] = int(np.max(overlaps_truth))

    ke_true = np.asarray(arrays["ke_true"], np.float64)
    ke_pred = np.asarray(arrays["ke_pred"], np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = (ke_pred - ke_true) / np.mean(ke_true)
        total_relative = float(np.sum(ke_pred - ke_true) / np.sum(ke_true))
    out["kinetic_energy_truth"] = _floats(ke_true)
    out["kinetic_energy_prediction"] = _floats(ke_pred)
    out["kinetic_energy_relative_error"] = _floats(relative)
    out["kinetic_energy_mean_abs_relative_error"] = float(np.mean(np.abs(relative)))
    out["kinetic_energy_total_relative_error"] = total_relative

    height_true = np.asarray(arrays["height_true"], np.float64)
    height_error = np.asarray(arrays["height_pred"], np.float64) - height_true
    out["mean_height_truth"] = _floats(height_true)
    out["mean_height_error"] = _floats(height_error)
    out["mean_height_mean_abs_error"] = float(np.mean(np.abs(height_error)))
    out["mean_height_final_error"] = float(height_error[-1])
    out["mean_height_mean_abs_error_mm"] = out["mean_height_mean_abs_error"] * box_half_size * 1e3

    if statistics:
        compared = [
            ("", prediction),
            ("constant_velocity_", np.asarray(constant_velocity_rollout(truth, input_frames=c))),
        ]
        if chaos_floor is not None:
            compared.append(("chaos_floor_", chaos_floor))
        out.update(
            _statistics(
                truth,
                compared,
                radius,
                real,
                input_frames=c,
                frame_dt=float(frame_dt),
                box_half_size=float(box_half_size),
                settings=statistics_settings,
                bounds=None if bounds is None else tuple(tuple(float(v) for v in pair) for pair in bounds),
            )
        )
    return out


def _statistics(
    truth, compared, radius, real, *, input_frames, frame_dt, box_half_size, settings, bounds=None
) -> dict[str, Any]:
    """The suspension statistics of :func:`rollout_metrics` (host side)."""
    unknown = sorted(set(settings or {}) - set(STATISTICS_DEFAULTS))
    if unknown:
        raise ValueError(f"unknown statistics settings {unknown}; expected some of {sorted(STATISTICS_DEFAULTS)}")
    settings = {**STATISTICS_DEFAULTS, **(settings or {})}
    frozen = tuple(sorted((k, tuple(v) if isinstance(v, (list, tuple)) else v) for k, v in settings.items()))
    n_frames, n = truth.shape[:2]
    c = input_frames
    frames = tuple(sorted({int(round(v)) for v in np.linspace(c, n_frames - 1, int(settings["distribution_frames"]))}))
    extra = -n % _PARTICLE_BUCKET
    stacked = np.stack([truth] + [np.asarray(t, truth.dtype) for _, t in compared])
    stats, distances = _statistics_arrays_jit(
        pad_particles(stacked, extra, axis=2, fill=0.0),
        pad_particles(radius, extra, axis=0, fill=1.0),
        pad_particles(real, extra, axis=0, fill=False),
        input_frames=c,
        frame_dt=frame_dt,
        box_half_size=box_half_size,
        frames=frames,
        settings=frozen,
        sinkhorn_rows=tuple(m for m, (prefix, _) in enumerate(compared) if prefix != "constant_velocity_"),
        bounds=bounds,
    )
    stats, distances = jax.device_get((stats, distances))
    one = [{key: value[m] for key, value in stats.items()} for m in range(stacked.shape[0])]
    truth_stats = one[0]
    mm = box_half_size * 1e3
    out: dict[str, Any] = {
        "distribution_frames": [k - c for k in frames],
        "front_height_truth": _floats(truth_stats["front"]),
        "front_settling_velocity_truth_mm_s": float(truth_stats["front_velocity"]) * 1e3,
        "settling_velocity_truth_mm_s": float(truth_stats["height_velocity"]) * 1e3,
        "front_height_truth_final_mm": float(truth_stats["front"][-1]) * mm,
        "height_profile_truth": _floats(truth_stats["profile"]),
        "area_fraction_profile_truth": _floats(truth_stats["fraction"]),
        "bed_area_fraction_truth": float(truth_stats["bed_fraction"]),
        "rdf_r": _floats(truth_stats["rdf_r"]),
        "rdf_truth": _floats(truth_stats["rdf"][0]),
    }
    for m, (prefix, _) in enumerate(compared):
        mine_distances = {key: value[m] for key, value in distances.items()}
        out.update(
            _statistics_report(
                prefix, one[m + 1], truth_stats, mine_distances, box_half_size=box_half_size, n_real=int(real.sum())
            )
        )
    return out


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) or isinstance(value, (bool, np.bool_))


def summarize(metrics: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean and standard deviation of every metric across trajectories.

    Args:
      metrics: dicts from :func:`rollout_metrics`, one per trajectory.

    Returns:
      ``{key: {"mean": m, "std": s, "n": k}}`` for every scalar key (the
      paper's "mean ± std"; ``std`` is the population standard deviation,
      ``ddof = 0``). ``None`` values (horizons longer than a rollout) are left
      out and ``n`` counts the values used; ``nan`` values propagate (a
      diverged rollout is not silently dropped). Booleans give the fraction
      ``True`` as the mean. For list-valued keys (per-frame curves) ``mean``
      and ``std`` are element-wise lists over the common prefix of all
      trajectories that have the key. Strings are ignored.
    """
    metrics = list(metrics)
    if not metrics:
        raise ValueError("summarize needs at least one metrics dict")
    keys: list[str] = []
    for entry in metrics:
        for key in entry:
            if key not in keys:
                keys.append(key)
    out: dict[str, Any] = {"n_trajectories": len(metrics)}
    for key in keys:
        values = [entry[key] for entry in metrics if key in entry and entry[key] is not None]
        if values and all(_is_number(v) for v in values):
            array = np.asarray(values, np.float64)
            out[key] = {"mean": float(np.mean(array)), "std": float(np.std(array)), "n": len(values)}
        elif values and all(isinstance(v, (list, tuple)) and all(_is_number(x) for x in v) for v in values):
            length = min(len(v) for v in values)
            array = np.asarray([list(v)[:length] for v in values], np.float64).reshape(len(values), length)
            out[key] = {
                "mean": _floats(np.mean(array, axis=0)),
                "std": _floats(np.std(array, axis=0)),
                "n": len(values),
            }
    return out
