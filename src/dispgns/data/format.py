"""The dispgns dataset format: one HDF5 file per split plus ``metadata.json``.

A dataset directory holds ``train.h5``, ``valid.h5``, ``test.h5`` and
``test_unseen.h5`` (any subset) and ``metadata.json``. Each split file has one
group per trajectory, named ``00000``, ``00001``, ..., holding:

============================ =========== ======= ===============================
dataset                      shape       dtype   content
============================ =========== ======= ===============================
``position``                 (T, N, D)   float32 centres / L (box ``bounds``)
``radius``                   (N,)        float32 radii / L
``particle_type``            (N,)        int     0 = particle, -1 = padding (see below)
``initial_position``         (N, D)      float64 centres in m the physics started from
``initial_velocity``         (N, D)      float64 velocities in m/s it started from
``initial_radius``           (N,)        float64 radii in m it ran with
============================ =========== ======= ===============================

``L`` is the dataset's length scale (``metadata.json`` ``length_scale``, the
paper's 0.1 m) and ``bounds`` the box in those units, one ``(lo, hi)`` per
axis: ``[-1, 1]^D`` for the paper's square box of half-size ``L``,
``((-4, 4), (-1, 1))`` for a container of half-sizes ``(0.4, 0.1)`` m.
Datasets written before the two were separated hold neither key: there
``L = box_half_size`` and ``bounds = [-1, 1]^D``.

The three ``initial_*`` datasets are present together or not at all (imported
data has no initial state, so it cannot be re-run). Group attributes carry
provenance (seed, split, index, radii list, ...).

``metadata.json`` holds dispgns's own fields (:class:`DatasetMetadata`) and,
next to them, the keys LagrangeBench 0.2.0 reads (:data:`LAGRANGEBENCH_KEYS`;
each is described in :meth:`DatasetMetadata.lagrangebench_keys`). The motion
statistics among them are computed from the training split
(:func:`motion_statistics`); datasets written before they existed load as
before and simply lack them (``dispgns export lagrangebench`` computes them).

Padding: particles whose ``particle_type`` is :data:`PAD_TYPE` (-1,
LagrangeBench's ``NodeType.PAD_VALUE``) pad a trajectory to a common particle
count (``dispgns export lagrangebench`` writes them, at the end of the particle
axis); :func:`read_split` drops them, so every reader of dispgns sees only real
particles.

Every file is written under a temporary name in its target directory and
renamed into place, so a reader never sees a half-written file. Every reader
validates what it reads and raises :class:`DatasetError` naming the file,
the trajectory and field, and the expected value.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from jaxtyping import ArrayLike, Int

from dispgns import files
from dispgns.arrays import Frame, Positions, Radii
from dispgns.files import write_atomic
from dispgns.physics import PhysicsConfig

# Per particle, an integer type (zeros; LagrangeBench reads it).
_ParticleTypes = Int[ArrayLike, "N"]

__all__ = [
    "BOX_TOLERANCE",
    "DatasetError",
    "DatasetMetadata",
    "FORMAT_VERSION",
    "INITIAL_STATE_TOLERANCE",
    "LAGRANGEBENCH_KEYS",
    "METADATA_FILE",
    "PAD_TYPE",
    "SPLITS",
    "Trajectory",
    "hdf5_written_whole",
    "load_dataset",
    "motion_statistics",
    "radii_groups",
    "read_metadata",
    "read_split",
    "split_filename",
    "staged_directory",
    "trajectory_name",
    "training_statistics",
    "validate_trajectory",
    "write_metadata",
    "write_split",
]

FORMAT_VERSION = 1
SPLITS = ("train", "valid", "test", "test_unseen")
METADATA_FILE = "metadata.json"
# Centres lie in [-1 + a, 1 - a]; the tolerance only absorbs float32 rounding
# and the tiny overshoot of the authors' collision handling.
BOX_TOLERANCE = 1e-4
# position[0] is the float32 image of initial_position / L.
INITIAL_STATE_TOLERANCE = 1e-5
# LagrangeBench's NodeType.PAD_VALUE: its loaders and losses skip particles of this type.
PAD_TYPE = -1
# Every metadata.json key LagrangeBench 0.2.0 reads (H5Dataset, case_builder, runner, metrics).
LAGRANGEBENCH_KEYS = (
    "dim",
    "bounds",
    "dt",
    "write_every",
    "dx",
    "default_connectivity_radius",
    "num_particles_max",
    "periodic_boundary_conditions",
    "vel_mean",
    "vel_std",
    "acc_mean",
    "acc_std",
)
# The LagrangeBench keys derived from dispgns's own fields: checked on reading, never stored twice.
_DERIVED_KEYS = ("dt", "write_every", "dx", "default_connectivity_radius", "periodic_boundary_conditions")
_STAT_KEYS = ("vel_mean", "vel_std", "acc_mean", "acc_std")


class DatasetError(ValueError):
    """A dataset file or its metadata is missing, malformed or inconsistent."""


def split_filename(split: str) -> str:
    """``"train"`` -> ``"train.h5"``."""
    return f"{split}.h5"


def trajectory_name(index: int) -> str:
    """``3`` -> ``"00003"``: the HDF5 group name of trajectory ``index``."""
    return f"{index:05d}"


# ----------------------------------------------------------------------------- trajectories


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """One stored trajectory (numpy arrays, not copied).

    Attributes:
      position: ``(T, N, D)`` float32 centres normalised by L (box ``[-1, 1]^D``).
      radius: ``(N,)`` float32 radii normalised by L.
      initial_position: ``(N, D)`` float64 centres in m the physics was
        started from, or ``None`` (imported data).
      initial_velocity: ``(N, D)`` float64 velocities in m/s, or ``None``.
      particle_type: ``(N,)`` integer, zeros (``None``: made so).
      initial_radius: ``(N,)`` float64 radii in m the physics ran with (the
        exact values from the radii list), or ``None``. The three
        ``initial_*`` fields are given together or not at all.
      attrs: provenance (JSON-compatible values), e.g. ``seed``, ``split``,
        ``index``, ``radii_m``.
    """

    position: Positions
    radius: Radii
    initial_position: Frame | None = None
    initial_velocity: Frame | None = None
    particle_type: _ParticleTypes | None = None
    initial_radius: Radii | None = None
    attrs: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.particle_type is None:
            n = np.shape(self.radius)[0] if np.ndim(self.radius) >= 1 else 0
            object.__setattr__(self, "particle_type", np.zeros((n,), np.int32))

    @property
    def n_frames(self) -> int:
        return int(self.position.shape[0])

    @property
    def n_particles(self) -> int:
        return int(self.position.shape[1])

    @property
    def dim(self) -> int:
        return int(self.position.shape[2])

    @property
    def has_initial_state(self) -> bool:
        return self.initial_position is not None


_INITIAL_FIELDS = ("initial_position", "initial_velocity", "initial_radius")


def _fail(where: str, message: str):
    raise DatasetError(f"{where}: {message}")


def _check_array(where: str, name: str, value, shape: tuple, kind: str, dtype=None) -> np.ndarray:
    """Check one field's type, shape (``None`` = any size) and dtype; return it as an array."""
    if not isinstance(value, np.ndarray):
        _fail(where, f"'{name}' must be a numpy array, got {type(value).__name__}")
    shown = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
    if value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
        _fail(where, f"'{name}' has shape {value.shape}, expected {shown}")
    if dtype is not None and value.dtype != np.dtype(dtype):
        _fail(where, f"'{name}' has dtype {value.dtype}, expected {np.dtype(dtype)}")
    if kind == "int" and not np.issubdtype(value.dtype, np.integer):
        _fail(where, f"'{name}' has dtype {value.dtype}, expected an integer dtype")
    if kind == "float" and not np.all(np.isfinite(value)):
        bad = np.argwhere(~np.isfinite(value))[0]
        _fail(
            where,
            f"'{name}' has a non-finite value {value[tuple(bad)]} at index {tuple(int(i) for i in bad)}, "
            f"expected finite values",
        )
    return value


def validate_trajectory(
    trajectory: Trajectory,
    where: str,
    *,
    dim: int | None = None,
    n_frames: int | None = None,
    box_half_size: float | None = None,
    predicted: bool = False,
    bounds: Sequence[Sequence[float]] | None = None,
) -> None:
    """Check every field of ``trajectory``; raise :class:`DatasetError` prefixed with ``where``.

    Args:
      trajectory: the trajectory to check.
      where: the location used in messages, e.g. ``"train.h5: trajectory 00003"``.
      dim, n_frames: expected ``D`` and ``T`` (``None``: not checked).
      box_half_size: the length scale L in m the positions are divided by,
        to check that the initial state lies in the box and agrees with
        ``position[0]`` (``None``: not checked).
      predicted: the positions are a model's prediction (a rollout written
        by ``dispgns evaluate``): they may leave the box or diverge to
        non-finite values, which are then stored as they are.
      bounds: the box ``((lo, hi),) * D`` in units of L (``None``: ``[-1, 1]^D``).
    """
    position = _check_array(
        where, "position", trajectory.position, (n_frames, None, dim), "any" if predicted else "float", np.float32
    )
    t, n, d = position.shape
    if t < 1 or n < 1 or d < 1:
        _fail(where, f"'position' has shape {position.shape}, expected at least one frame, particle and axis")
    box = np.array([[-1.0, 1.0]] * d if bounds is None else bounds, np.float64)
    if box.shape != (d, 2):
        _fail(where, f"'position' has {d} axes, expected {box.shape[0]} (the box {box.tolist()})")
    lo, hi = box[:, 0], box[:, 1]
    # The tolerance is relative to the box's scale (1 for [-1, 1]).
    tolerance = BOX_TOLERANCE * np.maximum(np.abs(lo), np.abs(hi))
    outside = (position < lo - tolerance) | (position > hi + tolerance)
    if outside.any() and not predicted:
        frame, particle, axis = (int(i) for i in np.argwhere(outside)[0])
        _fail(
            where,
            f"'position' frame {frame} particle {particle} axis {axis} is "
            f"{position[frame, particle, axis]:.6g}, expected inside the box [{lo[axis]:g}, {hi[axis]:g}]",
        )
    radius = _check_array(where, "radius", trajectory.radius, (n,), "float", np.float32)
    largest = float(np.min(hi - lo)) / 2.0
    if not np.all((radius > 0) & (radius < largest)):
        bad = int(np.argmax(~((radius > 0) & (radius < largest))))
        _fail(where, f"'radius' of particle {bad} is {radius[bad]:.6g}, expected 0 < radius / L < {largest:g}")
    _check_array(where, "particle_type", trajectory.particle_type, (n,), "int")
    present = [name for name in _INITIAL_FIELDS if getattr(trajectory, name) is not None]
    if present and len(present) != len(_INITIAL_FIELDS):
        missing = [name for name in _INITIAL_FIELDS if name not in present]
        _fail(where, f"missing field {missing[0]!r}, expected all of {list(_INITIAL_FIELDS)} or none")
    if not present:
        return
    x0 = _check_array(where, "initial_position", trajectory.initial_position, (n, d), "float", np.float64)
    _check_array(where, "initial_velocity", trajectory.initial_velocity, (n, d), "float", np.float64)
    a0 = _check_array(where, "initial_radius", trajectory.initial_radius, (n,), "float", np.float64)
    if not np.all(a0 > 0):
        bad = int(np.argmax(~(a0 > 0)))
        _fail(where, f"'initial_radius' of particle {bad} is {a0[bad]:.6g} m, expected > 0")
    if box_half_size is not None:
        scaled = x0 / box_half_size
        outside = (scaled < lo - tolerance) | (scaled > hi + tolerance)
        if np.any(outside):
            particle, axis = (int(i) for i in np.argwhere(outside)[0])
            _fail(
                where,
                f"'initial_position' particle {particle} axis {axis} is {x0[particle, axis]:.6g} m, "
                f"expected inside the box [{lo[axis] * box_half_size:g}, {hi[axis] * box_half_size:g}] m",
            )
        gap = np.abs(scaled - position[0])
        if np.any(gap > INITIAL_STATE_TOLERANCE):
            particle, axis = (int(i) for i in np.argwhere(gap > INITIAL_STATE_TOLERANCE)[0])
            _fail(
                where,
                f"'initial_position' / L differs from 'position' frame 0 by {gap.max():.3g} "
                f"(particle {particle}, axis {axis}), expected at most {INITIAL_STATE_TOLERANCE}",
            )
        radius_gap = np.abs(a0 / box_half_size - radius)
        if np.any(radius_gap > INITIAL_STATE_TOLERANCE):
            particle = int(np.argmax(radius_gap))
            _fail(
                where,
                f"'initial_radius' / L differs from 'radius' by {radius_gap.max():.3g} "
                f"(particle {particle}), expected at most {INITIAL_STATE_TOLERANCE}",
            )


# ----------------------------------------------------------------------------- metadata


@dataclasses.dataclass(frozen=True)
class DatasetMetadata:
    """Everything a reader needs to interpret a dataset directory (``metadata.json``).

    Attributes:
      dim: spatial dimension D.
      sequence_length: frames per trajectory T.
      frame_dt: time between stored frames in s (``save_every * physics.dt``).
      save_every: Euler steps between stored frames.
      box_half_size: the physics box's half-size in m (``physics.box_half_size``):
        a float for the paper's square box, one per axis for a rectangular one.
      connectivity_radius: default graph radius in normalised units
        (4 x the largest training radius / L; 0.2 for the paper).
      length_scale: ``L`` in m; stored positions and radii are divided by it
        (``None`` when read: ``box_half_size``, the only length of datasets
        written before rectangular boxes; always written).
      trajectory_counts: trajectories per split, e.g. ``{"train": 16, ...}``.
      radii: per split, the radii groups the trajectories were drawn from:
        a list of ``{"count", "radii_m", "radii_mm"}`` mappings.
      physics: the full :class:`PhysicsConfig` as a dict
        (see :attr:`physics_config`).
      has_initial_state: whether every trajectory stores the SI initial state
        the physics was started from (so it can be re-run).
      seed: the generation seed, or ``None`` (imported data).
      key_derivation: how each trajectory's PRNG key derives from ``seed``.
      split_ids: the integer folded into the key for each split.
      precision: ``"float32"`` or ``"float64"``, the simulation precision
        (``None`` when unknown).
      source: ``"generated"`` or a description of the imported file(s).
      preset: the preset name the dataset was generated from, if any.
      particle_counts: per split, the particle count N of every trajectory
        (``None``: not recorded).
      bounds: the box in units of L, ``((-h_d / L, h_d / L) for each axis d)``
        (``None``: computed; ``((-1, 1),) * D`` for the paper's box).
      batch_size: the most trajectories simulated together when generating
        (``None``: no limit, or not recorded). In float32 the grouping changes
        the rounding of the chaotic dynamics, so reproducing the files needs
        it as well as the seed.
      num_particles_max: the particle count every trajectory is padded to
        for LagrangeBench (LagrangeBench's ``num_particles_max``); ``None``:
        the largest of ``particle_counts`` (no padding).
      vel_mean, vel_std, acc_mean, acc_std: per axis, ``(D,)``, the mean and
        standard deviation over the training split of the frame-to-frame
        displacement ``x[t] - x[t-1]`` and of its difference
        ``x[t+1] - 2 x[t] + x[t-1]``, in normalised length units (positions
        / L) per frame, as LagrangeBench normalises its inputs and targets
        (:func:`motion_statistics`); ``None``: not computed (older datasets).
      position_offset: ``(D,)`` or ``None``: the split files store
        ``position + position_offset`` (with the file attribute of the same
        name) and ``bounds`` in ``metadata.json`` is shifted alike; readers
        subtract it. LagrangeBench exports use 1 (box ``[0, 2]^D``), since
        its cell lists assume coordinates in ``[0, box)``.
      dispgns_version: version of dispgns that wrote the dataset.
      format_version: version of this format.
    """

    dim: int
    sequence_length: int
    frame_dt: float
    save_every: int
    box_half_size: float | tuple[float, ...]
    connectivity_radius: float
    trajectory_counts: Mapping[str, int]
    radii: Mapping[str, Sequence[Mapping[str, Any]]]
    physics: Mapping[str, Any]
    has_initial_state: bool = True
    seed: int | None = None
    key_derivation: str | None = None
    split_ids: Mapping[str, int] | None = None
    precision: str | None = None
    source: str = "generated"
    preset: str | None = None
    particle_counts: Mapping[str, Sequence[int]] | None = None
    bounds: tuple[tuple[float, float], ...] | None = None
    batch_size: int | None = None
    num_particles_max: int | None = None
    vel_mean: tuple[float, ...] | None = None
    vel_std: tuple[float, ...] | None = None
    acc_mean: tuple[float, ...] | None = None
    acc_std: tuple[float, ...] | None = None
    position_offset: tuple[float, ...] | None = None
    dispgns_version: str | None = None
    length_scale: float | None = None
    format_version: int = FORMAT_VERSION

    def __post_init__(self):
        half = self.box_half_size
        if isinstance(half, list | tuple):
            half = tuple(float(v) if isinstance(v, int | float) and not isinstance(v, bool) else v for v in half)
            object.__setattr__(self, "box_half_size", half)
        if self.length_scale is None:
            object.__setattr__(self, "length_scale", half[-1] if isinstance(half, tuple) and half else half)
        if self.bounds is None:
            object.__setattr__(self, "bounds", self.expected_bounds())
        else:
            try:
                bounds = tuple(tuple(float(v) for v in pair) for pair in self.bounds)
            except (TypeError, ValueError):
                raise ValueError(
                    f"'bounds' is {self.bounds!r}, expected one [lo, hi] pair of numbers per axis"
                ) from None
            object.__setattr__(self, "bounds", bounds)
        for name in _STAT_KEYS + ("position_offset",):
            value = getattr(self, name)
            if value is not None and not isinstance(value, (str, bytes)) and isinstance(value, Iterable):
                object.__setattr__(self, name, tuple(value))
        if self.dispgns_version is None:
            from dispgns import __version__

            object.__setattr__(self, "dispgns_version", __version__)
        self.validate()

    def expected_bounds(self) -> tuple[tuple[float, float], ...]:
        """The box in units of L from ``box_half_size`` and ``length_scale`` (12 significant digits)."""
        half = self.box_half_size
        sizes = half if isinstance(half, tuple) else (half,) * self.dim
        try:
            return tuple(
                (-float(f"{h / self.length_scale:.12g}"), float(f"{h / self.length_scale:.12g}")) for h in sizes
            )
        except (TypeError, ValueError, ZeroDivisionError):
            return tuple((-1.0, 1.0) for _ in range(self.dim))

    @property
    def physics_config(self) -> PhysicsConfig:
        """The stored physics parameters as a :class:`PhysicsConfig`."""
        return PhysicsConfig.from_dict(dict(self.physics))

    @property
    def splits(self) -> tuple[str, ...]:
        """The splits present, in the canonical order."""
        return tuple(s for s in SPLITS if s in self.trajectory_counts)

    def validate(self, where: str = METADATA_FILE) -> None:
        """Check the fields' values and their mutual consistency."""

        def need(condition, message):
            if not condition:
                _fail(where, message)

        need(isinstance(self.dim, int) and self.dim in (2, 3), f"'dim' is {self.dim!r}, expected 2 or 3")
        need(
            isinstance(self.sequence_length, int) and self.sequence_length >= 1,
            f"'sequence_length' is {self.sequence_length!r}, expected an integer >= 1",
        )
        need(
            isinstance(self.save_every, int) and self.save_every >= 1,
            f"'save_every' is {self.save_every!r}, expected an integer >= 1",
        )
        for name in ("frame_dt", "length_scale", "connectivity_radius"):
            value = getattr(self, name)
            need(
                isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0,
                f"'{name}' is {value!r}, expected a finite number > 0",
            )
        half = self.box_half_size
        sizes = half if isinstance(half, tuple) else (half,)
        need(
            len(sizes) in (1, self.dim)
            and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in sizes
            ),
            f"'box_half_size' is {half!r}, expected a finite number > 0 (m) or {self.dim} of them",
        )
        need(
            self.format_version == FORMAT_VERSION,
            f"'format_version' is {self.format_version!r}, expected {FORMAT_VERSION} (this dispgns reads "
            f"format {FORMAT_VERSION} only)",
        )
        expected_bounds = self.expected_bounds()
        need(
            len(self.bounds) == self.dim
            and all(
                math.isclose(a, b, rel_tol=1e-9)
                for pair, want in zip(self.bounds, expected_bounds)
                for a, b in zip(pair, want)
            ),
            f"'bounds' is {[list(b) for b in self.bounds]!r}, expected {[list(b) for b in expected_bounds]} "
            f"(box_half_size / length_scale)",
        )
        need(
            isinstance(self.trajectory_counts, Mapping) and len(self.trajectory_counts) > 0,
            f"'trajectory_counts' is {self.trajectory_counts!r}, expected a mapping split -> count",
        )
        for split, count in self.trajectory_counts.items():
            need(split in SPLITS, f"'trajectory_counts' has unknown split {split!r}, expected one of {list(SPLITS)}")
            need(
                _is_int(count) and count >= 1, f"'trajectory_counts'[{split!r}] is {count!r}, expected an integer >= 1"
            )
        need(
            isinstance(self.radii, Mapping) and set(self.radii) == set(self.trajectory_counts),
            f"'radii' has splits {sorted(self.radii) if isinstance(self.radii, Mapping) else self.radii!r}, "
            f"expected {sorted(self.trajectory_counts)}",
        )
        for split, groups in self.radii.items():
            total = 0
            for group in groups:
                need(
                    isinstance(group, Mapping) and {"count", "radii_m"} <= set(group),
                    f"'radii'[{split!r}] entry {group!r}, expected a mapping with 'count' and 'radii_m'",
                )
                need(
                    _is_int(group["count"]) and group["count"] >= 0,
                    f"'radii'[{split!r}] count {group['count']!r}, expected an integer >= 0",
                )
                radii_m = group["radii_m"]
                need(
                    isinstance(radii_m, Sequence)
                    and not isinstance(radii_m, str)
                    and len(radii_m) > 0
                    and all(
                        isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r > 0
                        for r in radii_m
                    ),
                    f"'radii'[{split!r}] radii_m {radii_m!r}, expected a non-empty list of radii > 0 (m)",
                )
                total += group["count"]
            need(
                total == self.trajectory_counts[split],
                f"'radii'[{split!r}] groups hold {total} trajectories, expected "
                f"{self.trajectory_counts[split]} (trajectory_counts)",
            )
        need(
            isinstance(self.has_initial_state, bool),
            f"'has_initial_state' is {self.has_initial_state!r}, expected true or false",
        )
        need(
            self.seed is None or (_is_int(self.seed) and 0 <= self.seed < 2**32),
            f"'seed' is {self.seed!r}, expected null or an integer in [0, 2^32)",
        )
        need(
            self.split_ids is None
            or (isinstance(self.split_ids, Mapping) and all(_is_int(v) for v in self.split_ids.values())),
            f"'split_ids' is {self.split_ids!r}, expected null or a mapping split -> integer",
        )
        need(isinstance(self.source, str), f"'source' is {self.source!r}, expected a string")
        need(
            self.batch_size is None or (_is_int(self.batch_size) and self.batch_size >= 1),
            f"'batch_size' is {self.batch_size!r}, expected null or an integer >= 1",
        )
        if self.particle_counts is not None:
            need(
                isinstance(self.particle_counts, Mapping) and set(self.particle_counts) == set(self.trajectory_counts),
                f"'particle_counts' has splits {sorted(self.particle_counts)}, expected "
                f"{sorted(self.trajectory_counts)}",
            )
            for split, values in self.particle_counts.items():
                need(
                    len(values) == self.trajectory_counts[split] and all(isinstance(v, int) and v >= 1 for v in values),
                    f"'particle_counts'[{split!r}] is {list(values)}, expected "
                    f"{self.trajectory_counts[split]} integers >= 1",
                )
        if self.num_particles_max is not None:
            largest = max((max(v) for v in (self.particle_counts or {}).values()), default=1)
            need(
                _is_int(self.num_particles_max) and self.num_particles_max >= largest,
                f"'num_particles_max' is {self.num_particles_max!r}, expected null or an integer >= {largest} "
                f"(the largest particle count)",
            )
        present = [name for name in _STAT_KEYS if getattr(self, name) is not None]
        need(
            self.position_offset is None
            or (
                len(self.position_offset) == self.dim
                and all(isinstance(v, (int, float)) and math.isfinite(v) for v in self.position_offset)
            ),
            f"'position_offset' is {self.position_offset!r}, expected null or {self.dim} finite numbers",
        )
        absent = [name for name in _STAT_KEYS if name not in present]
        need(
            not present or not absent,
            f"'{absent[0] if absent else ''}' is missing, expected all of {list(_STAT_KEYS)} or none",
        )
        for name in present:
            value = getattr(self, name)
            need(
                len(value) == self.dim
                and all(
                    isinstance(v, (int, float))
                    and not isinstance(v, bool)
                    and math.isfinite(v)
                    and (v >= 0 or not name.endswith("_std"))
                    for v in value
                ),
                f"'{name}' is {list(value)!r}, expected {self.dim} finite numbers"
                + (" >= 0" if name.endswith("_std") else ""),
            )
        try:
            config = self.physics_config
        except (TypeError, ValueError) as error:
            _fail(where, f"'physics' is not a valid PhysicsConfig: {error}")
        physics_sizes = _half_sizes_of(config, self.dim)
        own_sizes = sizes * self.dim if len(sizes) == 1 else sizes
        same_box = (
            physics_sizes is not None
            and len(own_sizes) == self.dim
            and all(math.isclose(a, b, rel_tol=1e-12) for a, b in zip(physics_sizes, own_sizes))
        )
        need(
            same_box,
            f"'box_half_size' is {self.box_half_size}, expected physics.box_half_size = {config.box_half_size}",
        )
        need(
            math.isclose(self.frame_dt, self.save_every * config.dt, rel_tol=1e-9),
            f"'frame_dt' is {self.frame_dt}, expected save_every * physics.dt = {self.save_every * config.dt}",
        )
        need(
            self.precision in (None, "float32", "float64"),
            f"'precision' is {self.precision!r}, expected 'float32', 'float64' or null",
        )

    def to_dict(self) -> dict[str, Any]:
        """A JSON-compatible dict (lists instead of tuples)."""
        return {
            "format_version": self.format_version,
            "dispgns_version": self.dispgns_version,
            "source": self.source,
            "preset": self.preset,
            "dim": self.dim,
            "bounds": [[lo + o, hi + o] for (lo, hi), o in zip(self.bounds, self.position_offset or [0.0] * self.dim)],
            "position_offset": None if self.position_offset is None else list(self.position_offset),
            "box_half_size": list(self.box_half_size) if isinstance(self.box_half_size, tuple) else self.box_half_size,
            "length_scale": self.length_scale,
            "frame_dt": self.frame_dt,
            "save_every": self.save_every,
            "sequence_length": self.sequence_length,
            "connectivity_radius": self.connectivity_radius,
            "trajectory_counts": {s: self.trajectory_counts[s] for s in self.splits},
            "radii": {s: [dict(group) for group in self.radii[s]] for s in self.splits},
            "has_initial_state": self.has_initial_state,
            "precision": self.precision,
            "seed": self.seed,
            "batch_size": self.batch_size,
            "key_derivation": self.key_derivation,
            "split_ids": None if self.split_ids is None else dict(self.split_ids),
            "particle_counts": None
            if self.particle_counts is None
            else {s: list(self.particle_counts[s]) for s in self.splits},
            "physics": dict(self.physics),
            **self.lagrangebench_keys(),
        }

    def lagrangebench_keys(self) -> dict[str, Any]:
        """The keys LagrangeBench 0.2.0 reads from ``metadata.json``, with this dataset's values.

        All lengths are in normalised units (positions / L), times in s:

        - ``dim``, ``bounds``: as dispgns's own fields (the box ``[-1, 1]^D``).
        - ``dt``: the physics' Euler step in s (``physics.dt``);
          ``write_every``: Euler steps between stored frames (``save_every``),
          so ``dt * write_every`` is the time between frames (``frame_dt``).
        - ``dx``: the typical particle spacing, here the mean diameter over
          the training radii list, ``2 * mean(radii_m) / L`` (LagrangeBench
          uses it as a length scale in its metrics).
        - ``default_connectivity_radius``: the graph radius
          (``connectivity_radius``).
        - ``num_particles_max``: the particle count trajectories are padded
          to (``num_particles_max``, else the largest of ``particle_counts``;
          absent when neither is known).
        - ``periodic_boundary_conditions``: ``[false] * D`` (walls, no
          periodicity).
        - ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std``: the training
          split's motion statistics (absent when not computed; see the
          attributes).
        """
        radii = [r for group in self.radii.get("train") or self.radii[self.splits[0]] for r in group["radii_m"]]
        keys: dict[str, Any] = {
            "dt": self.physics_config.dt,
            "write_every": self.save_every,
            "dx": float(f"{2.0 * float(np.mean(radii)) / self.length_scale:.12g}"),
            "default_connectivity_radius": self.connectivity_radius,
            "periodic_boundary_conditions": [False] * self.dim,
        }
        if self.num_particles_max is not None:
            keys["num_particles_max"] = self.num_particles_max
        elif self.particle_counts is not None:
            keys["num_particles_max"] = max(max(v) for v in self.particle_counts.values())
        for name in _STAT_KEYS:
            if getattr(self, name) is not None:
                keys[name] = [float(v) for v in getattr(self, name)]
        return keys

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], where: str = METADATA_FILE) -> DatasetMetadata:
        """Inverse of :meth:`to_dict`; raises :class:`DatasetError` on missing or unknown fields."""
        if not isinstance(values, Mapping):
            _fail(where, f"expected a JSON object, got {type(values).__name__}")
        values = dict(values)
        # The LagrangeBench keys derived from dispgns's fields are checked, not stored twice.
        derived = {name: values.pop(name) for name in _DERIVED_KEYS if name in values}
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            _fail(where, f"unknown field(s) {unknown}, expected a subset of {sorted(fields)}")
        required = [
            name
            for name, f in fields.items()
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        ]
        for name in required:
            if name not in values:
                _fail(where, f"missing field {name!r}")
        counts = values.get("particle_counts")
        if isinstance(counts, Mapping) and counts and all(isinstance(v, Sequence) and v for v in counts.values()):
            if values.get("num_particles_max") == max(max(v) for v in counts.values()):
                values.pop("num_particles_max")  # no padding: derived from particle_counts
        if values.get("bounds") is not None:
            raw = values["bounds"]
            if (
                not isinstance(raw, Sequence)
                or isinstance(raw, str)
                or not all(isinstance(p, Sequence) and not isinstance(p, str) for p in raw)
            ):
                _fail(where, f"'bounds' is {raw!r}, expected one [lo, hi] pair of numbers per axis")
            values["bounds"] = tuple(tuple(pair) for pair in raw)
            offset = values.get("position_offset")
            if isinstance(offset, Sequence) and len(offset) == len(values["bounds"]):
                # metadata.json shows the stored (shifted) box; the object keeps the normalised one.
                try:
                    values["bounds"] = tuple((lo - o, hi - o) for (lo, hi), o in zip(values["bounds"], offset))
                except TypeError:
                    _fail(where, f"'position_offset' is {offset!r}, expected {len(offset)} numbers")
        try:
            metadata = cls(**values)
        except DatasetError as error:
            raise DatasetError(str(error).replace(METADATA_FILE, where, 1)) from None
        except (TypeError, ValueError) as error:
            _fail(where, str(error))
        expected = metadata.lagrangebench_keys()
        for name, value in derived.items():
            want = expected[name]
            same = (
                value == want
                if isinstance(want, (list, bool, int)) and not isinstance(want, float)
                else isinstance(value, (int, float)) and math.isclose(value, want, rel_tol=1e-9)
            )
            if not same:
                _fail(where, f"'{name}' is {value!r}, expected {want!r} (LagrangeBench key derived from the dataset)")
        return metadata

    def expected_for(self, split: str) -> dict[str, Any]:
        """``{"dim", "n_frames", "count"[, "particles"]}`` the file of ``split`` must match."""
        if split not in self.trajectory_counts:
            raise DatasetError(f"{METADATA_FILE}: no split {split!r}; the dataset has {list(self.splits)}")
        expected = {"dim": self.dim, "n_frames": self.sequence_length, "count": self.trajectory_counts[split]}
        if self.particle_counts is not None:
            expected["particles"] = list(self.particle_counts[split])
        return expected


def _half_sizes_of(config: PhysicsConfig, dim: int) -> tuple[float, ...] | None:
    try:
        return config.half_sizes(dim)
    except ValueError:
        return None


def _is_int(value) -> bool:
    """An integer in JSON terms (``true`` is not a count)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _json_value(value):
    """HDF5 attributes come back as numpy values; make them plain Python for ``attrs``."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_split(
    path: str | os.PathLike,
    trajectories: Iterable[Trajectory],
    *,
    box_half_size: float | None = None,
    predicted: bool = False,
    bounds: Sequence[Sequence[float]] | None = None,
) -> Path:
    """Validate and write one split file atomically.

    The file is written under a temporary name in the same directory and
    renamed over ``path`` only once complete; on error nothing is left behind.
    Every array is stored with a Fletcher32 checksum, so a flipped bit fails
    :func:`read_split` with a :class:`DatasetError` (files written before
    checksums were added read as before, unchecked).

    Args:
      path: target ``.h5`` file.
      trajectories: the trajectories, stored as groups ``00000``, ``00001``, ...
      box_half_size: the length scale L in m, to also check each initial
        state against its normalised positions (recommended).
      bounds: the box in units of L (``None``: ``[-1, 1]^D``); stored as the
        file attribute ``bounds`` when given.
      predicted: the positions are a model's rollout (see
        :func:`validate_trajectory`); the file attribute ``predicted`` is set.

    Returns:
      ``path`` as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    trajectories = list(trajectories)
    if not trajectories:
        raise DatasetError(f"{path.name}: no trajectories to write, expected at least one")
    dim = trajectories[0].position.shape[-1] if np.ndim(trajectories[0].position) == 3 else None
    for index, trajectory in enumerate(trajectories):
        validate_trajectory(
            trajectory,
            f"{path}: trajectory {trajectory_name(index)}",
            dim=dim,
            box_half_size=box_half_size,
            predicted=predicted,
            bounds=bounds,
        )
    with hdf5_written_whole(path) as file:
        file.attrs["format_version"] = FORMAT_VERSION
        if bounds is not None:
            file.attrs["bounds"] = np.asarray(bounds, np.float64)
        if predicted:
            file.attrs["predicted"] = True
        for index, trajectory in enumerate(trajectories):
            group = file.create_group(trajectory_name(index))
            _put(group, "position", trajectory.position)
            _put(group, "radius", trajectory.radius)
            _put(group, "particle_type", trajectory.particle_type)
            if trajectory.has_initial_state:
                for name in _INITIAL_FIELDS:
                    _put(group, name, getattr(trajectory, name))
            for key, value in trajectory.attrs.items():
                # HDF5 has no null: absent attributes read back as absent.
                if value is not None:
                    group.attrs[key] = value
    return path


@contextlib.contextmanager
def hdf5_written_whole(path: str | os.PathLike) -> Iterator[h5py.File]:
    """Yield a new HDF5 file, built in memory, that is written to ``path`` atomically when the block ends.

    HDF5 writing straight to a disk that fills up fails in its closing flush,
    with a ``RuntimeError`` ("Disable slist on flush dest failure failed")
    that leaves the file open inside the library (a traceback; a segmentation
    fault at exit was reported too). Built in memory (tens of MB for the
    largest presets' splits) and written in one Python write, a full disk is
    one ``OSError`` (ENOSPC), nothing left open or behind. A raise inside the
    block writes nothing.
    """
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as file:
        yield file
    write_atomic(path, buffer.getbuffer())


def _put(group, name: str, data) -> None:
    """One array written with a Fletcher32 checksum (a flipped bit fails the read), when HDF5 allows one."""
    data = np.asarray(data)
    # Checksums need chunked storage, which scalars and empty arrays cannot have.
    group.create_dataset(name, data=data, fletcher32=bool(data.ndim and data.size))


def write_metadata(directory: str | os.PathLike, metadata: DatasetMetadata) -> Path:
    """Write ``metadata.json`` into ``directory`` atomically; returns its path."""
    path = Path(directory) / METADATA_FILE
    metadata.validate()
    return write_atomic(path, json.dumps(metadata.to_dict(), indent=2) + "\n")


def staged_directory(out_dir: str | os.PathLike, *, overwrite: bool = False) -> AbstractContextManager[Path]:
    """:func:`dispgns.files.staged_directory` for a dataset (``metadata.json`` marks one)."""
    return files.staged_directory(out_dir, overwrite=overwrite, marker=METADATA_FILE, kind="dataset")


# ----------------------------------------------------------------------------- reading


def read_metadata(directory: str | os.PathLike) -> DatasetMetadata:
    """Read and validate ``directory/metadata.json``."""
    path = Path(directory) / METADATA_FILE
    where = str(path)
    if not path.is_file():
        raise DatasetError(f"{where}: not found; expected a dispgns dataset directory with {METADATA_FILE}")
    try:
        values = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{where}: cannot be read as JSON: {error}") from None
    return DatasetMetadata.from_dict(values, where=where)


def read_split(path: str | os.PathLike, metadata: DatasetMetadata | None = None) -> list[Trajectory]:
    """Read and validate every trajectory of one split file.

    Args:
      path: the ``.h5`` file; its stem names the split (``train.h5`` -> train).
      metadata: when given, the file must agree with it: dimension, sequence
        length, trajectory count, presence of the initial state, and the
        initial state must lie in the box and match frame 0.

    Returns:
      The trajectories in group order (``00000``, ``00001``, ...).
    """
    path = Path(path)
    name = str(path)
    expected = metadata.expected_for(path.stem) if metadata is not None else {}
    if not path.is_file():
        raise DatasetError(f"{name}: file not found")
    try:
        file = h5py.File(path, "r")
    except OSError as error:
        raise DatasetError(f"{name}: cannot be opened as HDF5: {error}") from None
    try:
        return _read_trajectories(file, name, expected, metadata)
    except DatasetError:
        raise
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as error:
        # h5py reports damage inside a file that opened as any of these.
        raise DatasetError(
            f"{name}: cannot be read, the file is damaged or not written by dispgns ({type(error).__name__}: {error})"
        ) from None


def _read_trajectories(file, name: str, expected: dict, metadata) -> list[Trajectory]:
    trajectories = []
    with file:
        # Rollouts written by `dispgns evaluate` may leave the box (see validate_trajectory).
        predicted = bool(file.attrs.get("predicted", False))
        # Exports for LagrangeBench store positions + offset (DatasetMetadata.position_offset).
        offset = file.attrs.get("position_offset")
        offset = None if offset is None else np.asarray(offset, np.float32)
        groups = sorted(file.keys())
        if "count" in expected and len(groups) != expected["count"]:
            _fail(name, f"holds {len(groups)} trajectories, expected {expected['count']} (metadata.json)")
        if not groups:
            _fail(name, "holds no trajectories, expected at least one")
        dim = expected.get("dim")
        n_frames = expected.get("n_frames")
        # The box: from metadata.json, else from the file (written since rectangular boxes), else [-1, 1]^D.
        bounds = metadata.bounds if metadata is not None else file.attrs.get("bounds")
        bounds = None if bounds is None else np.asarray(bounds, np.float64)
        for index, group_name in enumerate(groups):
            where = f"{name}: trajectory {group_name}"
            if group_name != trajectory_name(index):
                _fail(
                    name,
                    f"group {group_name!r} found where {trajectory_name(index)!r} was expected "
                    f"(groups must be numbered 00000, 00001, ... without gaps)",
                )
            group = file[group_name]
            if not isinstance(group, h5py.Group):
                _fail(where, "is not an HDF5 group")
            fields = {}
            for field in ("position", "radius", "particle_type") + _INITIAL_FIELDS:
                if field in group:
                    if not isinstance(group[field], h5py.Dataset):
                        _fail(where, f"field {field!r} is not an HDF5 dataset")
                    fields[field] = np.asarray(group[field][()])
                elif field in ("position", "radius", "particle_type"):
                    _fail(where, f"missing field {field!r}")
            if metadata is not None:
                has_initial = all(f in fields for f in _INITIAL_FIELDS)
                if metadata.has_initial_state and not has_initial:
                    missing = next(f for f in _INITIAL_FIELDS if f not in fields)
                    _fail(
                        where, f"missing field {missing!r}, expected because metadata.json has has_initial_state = true"
                    )
            fields = _drop_padding(fields)
            if offset is not None and np.ndim(fields["position"]) == 3:
                fields["position"] = fields["position"] - offset
            attrs = {key: _json_value(value) for key, value in group.attrs.items()}
            trajectory = Trajectory(attrs=attrs, **fields)
            if dim is None:
                dim = trajectory.dim if np.ndim(trajectory.position) == 3 else None
            if n_frames is None and np.ndim(trajectory.position) == 3:
                n_frames = trajectory.n_frames
            validate_trajectory(
                trajectory,
                where,
                dim=dim,
                n_frames=n_frames,
                box_half_size=None if metadata is None else metadata.length_scale,
                predicted=predicted,
                bounds=bounds,
            )
            if "particles" in expected and trajectory.n_particles != expected["particles"][index]:
                _fail(
                    where,
                    f"'position' holds {trajectory.n_particles} particles, expected "
                    f"{expected['particles'][index]} (metadata.json particle_counts)",
                )
            trajectories.append(trajectory)
    return trajectories


def _drop_padding(fields: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Remove the particles of type :data:`PAD_TYPE` (written by the LagrangeBench export)."""
    kinds = fields["particle_type"]
    if kinds.ndim != 1 or not np.issubdtype(kinds.dtype, np.integer) or not np.any(kinds == PAD_TYPE):
        return fields
    keep = kinds != PAD_TYPE
    out = {}
    for name, value in fields.items():
        if name == "position" and value.ndim == 3 and value.shape[1] == keep.size:
            out[name] = value[:, keep]
        elif value.ndim >= 1 and value.shape[0] == keep.size:
            out[name] = value[keep]
        else:
            out[name] = value  # a shape error, reported by validate_trajectory
    return out


def motion_statistics(positions: Iterable[Positions], dim: int | None = None) -> dict[str, list[float]]:
    """LagrangeBench's normalisation statistics of a set of trajectories.

    Args:
      positions: trajectories, each ``(T, N, D)`` positions (normalised units,
        only real particles), ``T >= 3``.
      dim: expected ``D`` (``None``: taken from the first trajectory).

    Returns:
      ``{"vel_mean", "vel_std", "acc_mean", "acc_std"}``, each a list of ``D``
      floats: the mean and (population) standard deviation per axis, over
      every particle and frame of every trajectory, of the frame-to-frame
      displacement ``x[t] - x[t-1]`` and of ``x[t+1] - 2 x[t] + x[t-1]``, in
      normalised length units per frame (LagrangeBench divides by no time
      step). Accumulated in float64.
    """
    sums = None
    for index, position in enumerate(positions):
        position = np.asarray(position, np.float64)
        if position.ndim != 3 or position.shape[0] < 3 or (dim is not None and position.shape[2] != dim):
            raise DatasetError(
                f"trajectory {index}: positions have shape {position.shape}, expected (T >= 3, N, "
                f"{dim if dim is not None else 'D'}) for motion statistics"
            )
        dim = position.shape[2]
        velocity = np.diff(position, axis=0).reshape(-1, dim)
        acceleration = np.diff(position, n=2, axis=0).reshape(-1, dim)
        if sums is None:
            sums = np.zeros((6, dim))
        sums += [
            [len(velocity)] * dim,
            velocity.sum(0),
            (velocity**2).sum(0),
            [len(acceleration)] * dim,
            acceleration.sum(0),
            (acceleration**2).sum(0),
        ]
    if sums is None:
        raise DatasetError("no trajectories given for motion statistics, expected at least one")
    out = {}
    for prefix, (count, total, squares) in (("vel", sums[0:3]), ("acc", sums[3:6])):
        mean = total / count
        out[f"{prefix}_mean"] = [float(v) for v in mean]
        out[f"{prefix}_std"] = [float(v) for v in np.sqrt(np.maximum(squares / count - mean**2, 0.0))]
    return out


def training_statistics(splits: Mapping[str, Sequence[Trajectory]]) -> dict[str, list[float] | None]:
    """:class:`DatasetMetadata`'s motion statistics for ``{split: trajectories}``: from ``train``.

    Returns the four fields (see :func:`motion_statistics`), or all ``None``
    when there is no training split or its trajectories have fewer than 3
    frames.
    """
    train = splits.get("train") or []
    if not train or any(t.n_frames < 3 for t in train):
        return dict.fromkeys(_STAT_KEYS)
    return motion_statistics([t.position for t in train])


def load_dataset(
    directory: str | os.PathLike, splits: Sequence[str] | None = None
) -> tuple[DatasetMetadata, dict[str, list[Trajectory]]]:
    """Read ``metadata.json`` and the requested split files, validating everything.

    Args:
      directory: the dataset directory.
      splits: split names to read; ``None`` reads every split the metadata lists.

    Returns:
      ``(metadata, {split: [Trajectory, ...]})``.
    """
    directory = Path(directory)
    metadata = read_metadata(directory)
    if splits is None:
        splits = metadata.splits
    elif isinstance(splits, str):
        splits = (splits,)
    result = {}
    for split in splits:
        if split not in metadata.trajectory_counts:
            raise DatasetError(
                f"{directory / METADATA_FILE}: no split {split!r}; the dataset has {list(metadata.splits)}"
            )
        result[split] = read_split(directory / split_filename(split), metadata)
    return metadata, result


def radii_groups(groups: Iterable[tuple[int, Sequence[float]]]) -> list[dict[str, Any]]:
    """Metadata entries ``{"count", "radii_m", "radii_mm"}`` for ``(count, radii in m)`` pairs."""
    return [
        {
            "count": int(count),
            "radii_m": [float(r) for r in radii],
            "radii_mm": [round(float(r) * 1e3, 9) for r in radii],
        }
        for count, radii in groups
    ]
