"""Cheap checks of the inputs of host conveniences: nothing wrong passes silently.

The host conveniences (:func:`dispgns.simulate`, :func:`dispgns.rollout` and
their batch and one-step relatives) call these on their concrete inputs
before compiling anything, and raise a ``ValueError`` that names the
argument, the first offending particle (index, batch index where there is
one) and the expected range. Padding particles (``mask == False``) are never
checked. The pure cores (``simulate_scan``, ``predict_step``,
``rollout_scan``, ``train_step``) stay check-free and fast.

What is checked, and the tolerances:

- **finite**: positions, velocities and radii hold no NaN or inf;
- **radii**: every radius is ``> 0`` (and, for the physics, below the box's
  smallest half-size: a wider particle cannot fit between two walls);
- **inside the box**: every centre lies inside the box ``[lo, hi]`` on every
  axis (the body may overlap a wall by up to its radius, which soft walls
  allow; a centre beyond the wall is outside);
- **overlaps**: no two particles closer than half the sum of their radii
  (``|x_i - x_j| < (a_i + a_j) / 2``; coincident ones included). The data's
  soft collisions keep centres at least ``1.75 min(a_i, a_j)`` apart, so such
  a pair is never a state the physics or the model started from;
- **normalised units** (learned simulator only): positions and radii look
  like metres when every real radius is below ``connectivity_radius / 16``
  (the model's training radii reach ``connectivity_radius / 4``) *and* every
  centre lies within the central fifth of the box (the paper's box is
  ``L = 0.1`` m: metres put every particle within ``+-0.1`` of ``[-1, 1]``).

Under ``jit`` the host checks cannot run (they need concrete arrays). Wrap a
pure core with :func:`jax.experimental.checkify` and :func:`checkify_inputs`
instead::

    from jax.experimental import checkify

    def checked(params, window, radius):
        checkify_inputs(window[-1], radius, bounds=model_config.bounds)
        return dispgns.rollout_scan(params, window, radius, n_steps,
                                    model_config=model_config, capacity=capacity)

    err, out = jax.jit(checkify.checkify(checked))(params, window, radius)
    err.throw()  # ValueError-like JaxRuntimeError naming the failed check
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from dispgns.arrays import Box, Frame, ParticleMask, Radii

__all__ = [
    "OVERLAP_FRACTION",
    "check_finite",
    "check_inside_box",
    "check_normalised_units",
    "check_overlaps",
    "check_particles",
    "check_radii",
    "checkify_inputs",
]

# Centres closer than this fraction of the sum of their radii are refused.
OVERLAP_FRACTION = 0.5
# Metre-like inputs: radii below connectivity_radius / _METRE_RADIUS_DIVISOR and centres inside the
# central _METRE_EXTENT of the box (see the module docstring).
_METRE_RADIUS_DIVISOR = 16.0
_METRE_EXTENT = 0.2

# One state or a batch of them: positions ``(N, D)`` or ``(B, N, D)`` (a leading frame axis is allowed where a
# docstring says so), radii and masks ``(N,)`` or ``(B, N)``; rows of any array with a particle axis.
_States = Float[ArrayLike, "*batch N D"]
_StateRadii = Float[ArrayLike, "*batch N"]
_StateMask = Bool[ArrayLike, "*batch N"]
_ParticleRows = Float[ArrayLike, "*batch N D"] | Float[ArrayLike, "*batch N"]
_StateFrames = Float[ArrayLike, "*batch C N D"]
# A box as an array or as ``((lo, hi),) * D``.
_BoxLike = Box | Sequence[Sequence[float]]


def _where(index: tuple[int, ...], particle_axes: int) -> str:
    """``particle 3`` or ``trajectory 1, particle 3`` (and ``frame 2, ...``) for an index into an array."""
    names = ("particle",) if particle_axes == 1 else ("trajectory", "particle")
    parts = [f"{n} {i}" for n, i in zip(names, index[:particle_axes])]
    return ", ".join(parts)


def _real(mask, shape) -> np.ndarray:
    return np.ones(shape, bool) if mask is None else np.asarray(mask, bool)


def check_finite(array: _ParticleRows, name: str, *, mask: _StateMask | None = None, particle_axis: int = -2) -> None:
    """Raise if a real particle's row of ``array`` holds NaN or inf.

    Args:
      array: ``(..., N, D)`` (``particle_axis = -2``) or ``(..., N)``
        (``particle_axis = -1``) host array.
      name: the argument's name, for the message.
      mask: optional bool array of the particle axes' shape (and the leading
        batch axis if any), ``False`` for padding.
    """
    a = np.asarray(array)
    bad = ~np.isfinite(a)
    if particle_axis == -2:
        bad = bad.any(axis=-1)
    if mask is not None:
        m = np.asarray(mask, bool)
        bad = bad & np.broadcast_to(m.reshape(m.shape[:-1] + (1,) * (bad.ndim - m.ndim) + m.shape[-1:]), bad.shape)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        value = a[index]
        raise ValueError(
            f"{name} must be finite: index {index} (particle {index[-1]}) holds {np.asarray(value).tolist()} "
            f"({int(bad.sum())} non-finite row(s)); expected finite numbers for every real particle"
        )


def check_radii(
    radius: _StateRadii,
    name: str = "radius",
    *,
    mask: _StateMask | None = None,
    below: float | None = None,
    box: str = "",
) -> None:
    """Raise if a real particle's radius is not finite and ``> 0`` (``radius``: ``(N,)`` or ``(B, N)``).

    ``below``: also refuse radii ``>= below`` (the box's smallest half-size
    for the physics; ``box`` names it in the message).
    """
    a = np.asarray(radius)
    real = _real(mask, a.shape)
    bad = ~(np.isfinite(a) & (a > 0)) & real
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{name} must be finite and > 0 for every real particle: {_where(index, a.ndim)} has "
            f"{float(a[index])!r} ({int(bad.sum())} bad value(s))"
        )
    if below is not None:
        wide = (a >= below) & real
        if wide.any():
            index = tuple(int(i) for i in np.argwhere(wide)[0])
            raise ValueError(
                f"{name}: {_where(index, a.ndim)} has radius {float(a[index]):.4g}, not below the smallest "
                f"half-size {below:g} of {box or 'the box'} ({int(wide.sum())} such particle(s)); a particle that "
                f"wide cannot fit between two walls (are the radii in the right units?)"
            )


def check_inside_box(
    position: _States, radius: _StateRadii, bounds: _BoxLike, name: str, *, mask: _StateMask | None = None, box: str
) -> None:
    """Raise if a real particle's centre lies outside the box ``bounds`` on some axis.

    Args:
      position: ``(N, D)`` or ``(B, N, D)`` host array (units of ``bounds``).
      radius: ``(N,)`` or ``(B, N)``, for the message.
      bounds: ``((lo, hi),) * D``.
      name: the argument's name. box: what the box is, for the message
        (e.g. ``"the model's bounds"``, ``"the box [-L, L]^D (L = 0.1 m)"``).
    """
    x = np.asarray(position)
    b = np.asarray(bounds, x.dtype if np.issubdtype(x.dtype, np.floating) else float)
    outside = ((x < b[:, 0]) | (x > b[:, 1])).any(axis=-1) & _real(mask, x.shape[:-1])
    if outside.any():
        index = tuple(int(i) for i in np.argwhere(outside)[0])
        spans = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in b.tolist())
        raise ValueError(
            f"{name}: {_where(index, x.ndim - 1)} has its centre at {np.round(x[index], 6).tolist()} "
            f"(radius {float(np.asarray(radius)[index]):.4g}), outside {box} {spans} "
            f"({int(outside.sum())} particle(s) outside); expected every centre inside the box"
        )


def check_overlaps(
    position: _States,
    radius: _StateRadii,
    name: str,
    *,
    mask: _StateMask | None = None,
    fraction: float = OVERLAP_FRACTION,
) -> None:
    """Raise if two real particles' centres are closer than ``fraction * (a_i + a_j)``.

    A k-d tree finds candidate pairs (``O(N log N)``), so this stays cheap for
    large ``N``. ``position``: ``(N, D)`` or ``(B, N, D)``; ``radius``:
    ``(N,)`` or ``(B, N)``.
    """
    from scipy.spatial import cKDTree

    x = np.asarray(position, float)
    a = np.asarray(radius, float)
    m = _real(mask, x.shape[:-1])
    if x.ndim == 2:
        x, a, m = x[None], a[None], m[None]
        batched = False
    else:
        batched = True
    for k in range(x.shape[0]):
        real = np.flatnonzero(m[k])
        if real.size < 2:
            continue
        xr, ar = x[k, real], a[k, real]
        pairs = cKDTree(xr).query_pairs(r=fraction * 2.0 * float(ar.max()), output_type="ndarray")
        if not len(pairs):
            continue
        gap = np.linalg.norm(xr[pairs[:, 0]] - xr[pairs[:, 1]], axis=-1)
        close = gap < fraction * (ar[pairs[:, 0]] + ar[pairs[:, 1]])
        if close.any():
            i, j = (int(real[p]) for p in pairs[np.argmax(close)])
            where = f"trajectory {k}: " if batched else ""
            raise ValueError(
                f"{name}: {where}particles {i} and {j} overlap (centres {float(gap[np.argmax(close)]):.4g} apart, "
                f"radii {float(a[k, i]):.4g} and {float(a[k, j]):.4g}; {int(close.sum())} such pair(s)); "
                f"expected centres at least {fraction:g} x (a_i + a_j) apart"
            )


def check_normalised_units(
    position: _States,
    radius: _StateRadii,
    *,
    bounds: _BoxLike,
    connectivity_radius: float,
    mask: _StateMask | None = None,
) -> None:
    """Raise if positions and radii look like metres rather than normalised units (see the module docstring)."""
    x = np.asarray(position)
    a = np.asarray(radius)
    m = _real(mask, a.shape)
    if not m.any():
        return
    b = np.asarray(bounds, float)
    centre, half = b.mean(axis=1), (b[:, 1] - b[:, 0]) / 2
    small_radii = float(a[m].max()) < connectivity_radius / _METRE_RADIUS_DIVISOR
    central = bool(np.all(np.abs(x[m] - centre) <= _METRE_EXTENT * half))
    if small_radii and central:
        raise ValueError(
            f"positions and radius look like metres, not normalised units: every radius is below "
            f"{connectivity_radius / _METRE_RADIUS_DIVISOR:.4g} (largest {float(a[m].max()):.4g}; the model was "
            f"trained with radii up to about {connectivity_radius / 4:.4g}) and every centre lies in the central "
            f"{_METRE_EXTENT:.0%} of the box; divide positions and radii by the length scale L "
            f"(the box half-size in m, e.g. 0.1)"
        )


def check_particles(
    position: _States | _StateFrames,
    radius: _StateRadii,
    *,
    mask: _StateMask | None = None,
    velocity: _States | None = None,
    bounds: _BoxLike,
    box: str,
    position_name: str,
    velocity_name: str = "velocity",
    radius_name: str = "radius",
    overlaps: bool = True,
    model_connectivity_radius: float | None = None,
    radius_below: float | None = None,
) -> None:
    """Every check above, in order, on one state (``position`` ``(N, D)`` or ``(B, N, D)``; host arrays).

    ``position`` may also carry leading frame axes before ``N`` when
    ``radius`` has none: ``(C, N, D)`` for ``(N,)`` radii, ``(B, C, N, D)``
    for ``(B, N)``; the box, overlap and units checks then use the last frame.
    ``model_connectivity_radius``: check normalised units for a model with
    that graph radius (``None``: no units check). ``radius_below``: refuse
    radii at or above it (:func:`check_radii`).
    """
    x = np.asarray(position)
    a = np.asarray(radius)
    batched = a.ndim == 2
    m = _real(mask, a.shape)
    if x.ndim == a.ndim + 2:  # frames: (C, N, D) or (B, C, N, D)
        frame_mask = m[:, None] if batched else m[None]
        check_finite(x, position_name, mask=np.broadcast_to(frame_mask, x.shape[:-1]))
        x = x[:, -1] if batched else x[-1]
    else:
        check_finite(x, position_name, mask=m)
    check_radii(a, radius_name, mask=m, below=radius_below, box=box)
    if velocity is not None:
        check_finite(velocity, velocity_name, mask=m)
    if model_connectivity_radius is not None:
        check_normalised_units(x, a, bounds=bounds, connectivity_radius=model_connectivity_radius, mask=m)
    check_inside_box(x, a, bounds, position_name, mask=m, box=box)
    if overlaps:
        check_overlaps(x, a, position_name, mask=m)


def checkify_inputs(position: Frame, radius: Radii, *, bounds: _BoxLike, mask: ParticleMask | None = None) -> None:
    """The finite, radius and inside-the-box checks as :func:`jax.experimental.checkify.check` calls.

    For use inside a function wrapped with ``checkify.checkify`` (works under
    ``jit``, ``vmap`` and ``lax.scan``; see the module docstring).
    ``position``: ``(N, D)``; ``radius``, ``mask``: ``(N,)``.
    """
    import jax.numpy as jnp
    from jax.experimental import checkify

    m = jnp.ones(jnp.shape(radius), bool) if mask is None else jnp.asarray(mask, bool)
    b = jnp.asarray(bounds, jnp.result_type(position))
    finite = jnp.all(jnp.isfinite(position), axis=-1) | ~m
    checkify.check(jnp.all(finite), "position must be finite (first bad particle {i})", i=jnp.argmin(finite))
    good_radius = (jnp.isfinite(radius) & (radius > 0)) | ~m
    checkify.check(
        jnp.all(good_radius), "radius must be finite and > 0 (first bad particle {i})", i=jnp.argmin(good_radius)
    )
    inside = jnp.all((position >= b[:, 0]) & (position <= b[:, 1]), axis=-1) | ~m
    checkify.check(jnp.all(inside), "position outside the box (first such particle {i})", i=jnp.argmin(inside))
