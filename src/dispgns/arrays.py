"""Host-side array helpers shared by every layer: concrete inputs and particle padding.

Host conveniences (the functions that size capacities from data and grow
them) need concrete arrays; :func:`host_array` turns a traced one into a
clear error that names the pure core to use instead. Batches of
trajectories with different particle counts are padded to one particle
budget with :func:`pad_particles` / :func:`stack_padded` (padding rows:
position 0, radius 1, ``mask == False``; every consumer masks them out).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import ArrayLike, Bool, Float, Int, PRNGKeyArray, PyTree, Shaped

__all__ = [
    "BatchFrame",
    "BatchMask",
    "BatchPositions",
    "BatchRadii",
    "BatchWindow",
    "Box",
    "Count",
    "Flag",
    "Frame",
    "FrameFlags",
    "Params",
    "ParticleMask",
    "PerAxis",
    "PerFrame",
    "PositionWindow",
    "Positions",
    "PRNGKey",
    "Radii",
    "Scalar",
    "host_array",
    "node_budget",
    "pad_particles",
    "stack_padded",
]

# Array shapes of the public API (jaxtyping annotations: documentation for readers, IDEs and type checkers;
# no runtime check). T frames, C input frames, N particles, D = 2 or 3 axes, B trajectories of a batch;
# normalised units unless a docstring says SI. A module's rarer shapes are aliases at its top.
Positions = Float[ArrayLike, "T N D"]
PositionWindow = Float[ArrayLike, "C N D"]
Frame = Float[ArrayLike, "N D"]
Radii = Float[ArrayLike, "N"]
ParticleMask = Bool[ArrayLike, "N"]
Flag = Bool[ArrayLike, ""]
Scalar = Float[ArrayLike, ""]
Count = Int[ArrayLike, ""]
PerFrame = Float[ArrayLike, "T"]
PerAxis = Float[ArrayLike, "D"]
FrameFlags = Bool[ArrayLike, "T"]
# A box as an array: ``(lo, hi)`` per axis.
Box = Float[ArrayLike, "D 2"]
# Batches of trajectories padded to one particle count N (``mask`` marks the real particles).
BatchPositions = Float[ArrayLike, "B T N D"]
BatchWindow = Float[ArrayLike, "B C N D"]
BatchFrame = Float[ArrayLike, "B N D"]
BatchRadii = Float[ArrayLike, "B N"]
BatchMask = Bool[ArrayLike, "B N"]
# A ``jax.random`` key (new-style typed key or legacy ``uint32[2]``).
PRNGKey = PRNGKeyArray
# The network's parameters: a pytree of float arrays of any shape (``init_params``, checkpoints).
Params = PyTree[Float[ArrayLike, "..."]]
# Any shape and dtype (the host helpers below work on every array).
_AnyArray = Shaped[ArrayLike, "..."]
_HostArray = Shaped[np.ndarray, "..."]


def host_array(x: _AnyArray, name: str, *, pure: str | None = None) -> _HostArray:
    """``x`` as a numpy array; a clear ``ValueError`` when it is traced (inside ``jit``, ``vmap``, ``grad``).

    Args:
      x: an array-like.
      name: the argument's name, for the message.
      pure: the pure function to use under a transformation, for the message.
    """
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        hint = f"; under jit/vmap/grad use {pure}, which takes its capacities explicitly" if pure else ""
        raise ValueError(f"{name} must be a concrete array here (got a traced one){hint}") from None


def node_budget(counts: Sequence[int], *, multiple: int = 8) -> int:
    """Particle slots for trajectories of ``counts`` particles: the largest, rounded up to ``multiple``."""
    return int(multiple * math.ceil(max(int(c) for c in counts) / multiple))


def pad_particles(array: _AnyArray, count: int, *, axis: int, fill: float | bool) -> _HostArray:
    """``array`` with ``count`` padding rows of ``fill`` appended along the particle ``axis``."""
    array = np.asarray(array)
    if count <= 0:
        return array
    shape = list(array.shape)
    shape[axis] = count
    return np.concatenate([array, np.full(shape, fill, array.dtype)], axis=axis)


def stack_padded(
    trajectories: Sequence[Any], *, frames: int, budget: int | None = None, dtype: DTypeLike = np.float32
) -> tuple[BatchPositions, BatchRadii, BatchMask]:
    """The first ``frames`` frames of trajectories of any particle counts, stacked on one particle budget.

    Args:
      trajectories: objects with ``.position`` ``(T, N, D)`` (``T >= frames``)
        and ``.radius`` ``(N,)``.
      frames: frames kept from each.
      budget: particle slots (``None``: :func:`node_budget` of the counts).

    Returns:
      ``(position (B, frames, budget, D), radius (B, budget), mask (B, budget))``;
      padding rows hold position 0 and radius 1.
    """
    counts = [t.position.shape[1] for t in trajectories]
    budget = node_budget(counts) if budget is None else int(budget)
    dim = trajectories[0].position.shape[2]
    position = np.zeros((len(trajectories), frames, budget, dim), dtype)
    radius = np.ones((len(trajectories), budget), dtype)
    mask = np.zeros((len(trajectories), budget), bool)
    for k, (traj, n) in enumerate(zip(trajectories, counts)):
        position[k, :, :n] = np.asarray(traj.position[:frames])
        radius[k, :n] = np.asarray(traj.radius)
        mask[k, :n] = True
    return position, radius, mask
