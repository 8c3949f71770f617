"""Standardisation statistics of radius-normalised velocities and accelerations.

DeepMind's GNS standardises the input velocities and the target
accelerations with dataset statistics, adding the training-noise std in
quadrature; the paper's authors dropped it, and it matters (measured in
``experiments/paper/README.md``).
dispgns standardises ``v / a_i`` and ``acc / a_i`` (the quantities the
network sees and predicts). The statistics live in ``params["normalization"]``
and are never trained.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from dispgns.arrays import PerAxis
from dispgns.data import Trajectory
from dispgns.model import identity_normalization

__all__ = ["compute_normalization", "identity_normalization"]


def compute_normalization(trajectories: Iterable[Trajectory], *, noise_std: float = 0.0) -> dict[str, PerAxis]:
    """Per-axis mean and std of ``v / a_i`` and ``acc / a_i`` over every frame of every trajectory.

    Velocities are ``x_{t+1} - x_t`` and accelerations ``x_{t+1} - 2 x_t +
    x_{t-1}`` (normalised units, one frame = one time unit), divided by the
    particle's radius. The training noise perturbs the last input velocity
    and the target by about ``noise_std`` (per axis), i.e. by ``noise_std /
    a_i`` in these units; that term, ``noise_std * sqrt(mean(1 / a_i^2))``, is
    added to both stds in quadrature.

    Args:
      trajectories: objects with ``.position`` ``(T, N, D)`` and ``.radius``
        ``(N,)`` in normalised units (e.g. :class:`dispgns.data.Trajectory`);
        ``T >= 3``.
      noise_std: training noise std (``TrainConfig.noise_std``).

    Returns:
      ``{"velocity_mean", "velocity_std", "acceleration_mean",
      "acceleration_std"}``, each a float32 ``(D,)`` array.
    """
    sums = {}
    count_v = count_a = 0
    inv_a2_sum, inv_a2_count = 0.0, 0
    dim = None
    for k, traj in enumerate(trajectories):
        x = np.asarray(traj.position, np.float64)
        a = np.asarray(traj.radius, np.float64)
        if x.ndim != 3 or a.shape != (x.shape[1],) or x.shape[0] < 3:
            raise ValueError(
                f"trajectory {k}: expected position (T >= 3, N, D) and radius (N,), got {x.shape} and {a.shape}"
            )
        if dim is None:
            dim = x.shape[2]
        elif x.shape[2] != dim:
            raise ValueError(f"trajectory {k} has D = {x.shape[2]}, the others D = {dim}")
        v = np.diff(x, axis=0) / a[None, :, None]
        acc = np.diff(x, n=2, axis=0) / a[None, :, None]
        for name, values in (("v", v), ("a", acc)):
            flat = values.reshape(-1, dim)
            sums[name] = sums.get(name, 0.0) + flat.sum(axis=0)
            sums[name + "2"] = sums.get(name + "2", 0.0) + (flat**2).sum(axis=0)
        count_v += v.shape[0] * v.shape[1]
        count_a += acc.shape[0] * acc.shape[1]
        inv_a2_sum += float(np.sum(1.0 / a**2)) * x.shape[0]
        inv_a2_count += a.size * x.shape[0]
    if dim is None:
        raise ValueError("compute_normalization needs at least one trajectory")
    noise = noise_std**2 * inv_a2_sum / inv_a2_count
    out = {}
    for name, key, count in (("v", "velocity", count_v), ("a", "acceleration", count_a)):
        mean = sums[name] / count
        var = np.maximum(sums[name + "2"] / count - mean**2, 0.0)
        out[f"{key}_mean"] = mean.astype(np.float32)
        out[f"{key}_std"] = np.sqrt(var + noise).astype(np.float32)
    for key in ("velocity_std", "acceleration_std"):
        if not np.all(out[key] > 0):
            raise ValueError(f"{key} is {out[key]}: the trajectories do not move; cannot standardise")
    return out
