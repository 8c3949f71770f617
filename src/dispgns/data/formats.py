"""Trajectories in the formats other tools use: extended XYZ (OVITO, ASE), GSD (HOOMD-blue), VTU series
(ParaView), LAMMPS dump text (in only).

Files written here hold **SI metres and seconds**: centres ``position * L``, per-particle radius (XYZ column
``radius``, VTU point data ``radius``) or diameter (GSD ``particles/diameter``), the box per axis (``[-L, L]^D``
for a square one; XYZ ``Lattice`` + ``Origin``, GSD's centred ``configuration/box``, VTU none) and each
frame's time (XYZ ``Time``, GSD log ``dispgns/time_s``, the VTU series' ``time``). 2-D trajectories get
``z = 0`` (GSD ``configuration/dimensions = 2``). Readers return a :class:`~dispgns.data.format.Trajectory`
in normalised units (positions and radii / L); what a file does not say (its length unit, the box, the
dimension) must be given explicitly. Boxes may be rectangular (one width per axis), not tilted (triclinic).
Every problem (a missing field, a particle count that changes, a particle outside the box, a non-finite
value, a time step that disagrees, a tilted box) raises :class:`~dispgns.data.format.DatasetError` naming
the file, the frame and the field.

The maintained readers and writers do the work: ``ase.io`` for extended XYZ, ``gsd.hoomd`` for GSD,
``meshio`` for VTU. LAMMPS dump text has no light maintained reader that keeps a radius or diameter column
(ASE's drops unknown columns), so :func:`read_lammps_dump` is a small parser of that documented format.
These libraries are optional (``pip install dispgns[formats]``) and imported only when used.

Precision: GSD and VTU store float32 metres, extended XYZ 8 decimals of metres; a round trip returns the
normalised float32 positions to one float32 rounding (1e-7 in the box [-1, 1]^D, 1e-8 m at L = 0.1 m), radii
exactly for radii given in whole micrometres.
"""

from __future__ import annotations

import importlib
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import ArrayLike, Float

from dispgns.arrays import PerFrame, Positions, Radii
from dispgns.data.format import BOX_TOLERANCE, DatasetError, DatasetMetadata, Trajectory
from dispgns.files import atomic_path, write_atomic

__all__ = [
    "EXPORT_FORMATS",
    "IMPORT_FORMATS",
    "FileTrajectory",
    "EXPORT_MARKER",
    "export_filename",
    "export_trajectories",
    "import_trajectory_files",
    "read_extxyz",
    "read_gsd",
    "read_lammps_dump",
    "read_trajectory_file",
    "write_extxyz",
    "write_gsd",
    "write_trajectory_file",
    "write_vtu_series",
]

EXPORT_FORMATS = ("extxyz", "gsd", "vtu")
IMPORT_FORMATS = ("extxyz", "gsd", "lammps-dump")
# What a file holds, in its own length unit: centres with z (0 in 2-D) and a box per axis.
_FilePositions = Float[ArrayLike, "T N 3"]
_FileBox = Float[ArrayLike, "3 2"]

_SUFFIX = {"extxyz": ".extxyz", "gsd": ".gsd", "vtu": ".vtu.series"}
_LIBRARY = {"extxyz": "ase", "gsd": "gsd", "vtu": "meshio"}
# GSD log entries dispgns writes (HOOMD files from elsewhere have none: their unit must be given).
GSD_TIME = "dispgns/time_s"
GSD_LENGTH_UNIT = "dispgns/length_unit_m"


def _library(name: str, purpose: str):
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            f"{purpose} needs the '{name.split('.')[0]}' package: pip install 'dispgns[formats]'"
        ) from None


def export_filename(split: str, index: int, fmt: str) -> str:
    """``("test", 3, "gsd")`` -> ``"test_00003.gsd"`` (the VTU series: ``test_00003.vtu.series``)."""
    return f"{split}_{index:05d}{_SUFFIX[fmt]}"


def _check_fmt(fmt: str, known: Sequence[str]) -> None:
    if fmt not in known:
        raise ValueError(f"unknown format {fmt!r}, expected one of {list(known)}")


def _si_frames(position: np.ndarray, length_scale: float) -> np.ndarray:
    """``(T, N, D)`` normalised -> ``(T, N, 3)`` float64 metres (``z = 0`` in 2-D)."""
    t, n, d = position.shape
    out = np.zeros((t, n, 3))
    out[..., :d] = position.astype(np.float64) * length_scale
    return out


def _si_radius(radius: np.ndarray, length_scale: float) -> np.ndarray:
    """``(N,)`` normalised float32 radii -> float64 m, from their shortest decimals (0.04 -> 0.004 m, not
    0.0039999999): a round trip through a file then gives back the same float32 values."""
    return _shortest(radius) * length_scale


def _scale_and_half_sizes(box_half_size, length_scale: float | None, dim: int) -> tuple[float, np.ndarray]:
    """``(L, (D,) half-sizes in m)`` of a box given as one half-size (the square box, ``L`` by default) or one
    per axis (then ``length_scale`` is required: positions are stored divided by ``L``, not by the box)."""
    half = np.broadcast_to(np.asarray(box_half_size, np.float64), (dim,)).copy()
    if length_scale is None:
        if not np.all(half == half[0]):
            raise ValueError(f"box_half_size {tuple(half)} differs per axis: give length_scale (L in m) as well")
        length_scale = float(half[0])
    return float(length_scale), half


# ----------------------------------------------------------------------------- writers


def write_extxyz(
    path: str | os.PathLike,
    position: Positions,
    radius: Radii,
    *,
    box_half_size: float | Sequence[float],
    frame_dt: float,
    length_scale: float | None = None,
) -> Path:
    """Write one trajectory as a multi-frame extended XYZ file (OVITO and ASE read it).

    Args:
      path: the target file (written atomically).
      position: ``(T, N, D)`` normalised centres (positions / L), ``D`` 2 or 3.
      radius: ``(N,)`` normalised radii.
      box_half_size: the box's half-size in m, one for all axes or one per axis.
      frame_dt: time between frames in s.
      length_scale: L in m, what positions and radii are divided by (default: ``box_half_size``, which
        must then be the same on every axis).

    Each frame has species ``X``, ``pos`` in m, a ``radius`` column in m (OVITO's particle radius),
    ``Lattice`` (the box's full size per axis; in 2-D the z extent is the largest diameter) with ``Origin``
    at its lower corner (OVITO's cell origin), ``Time`` in s, ``frame``, ``dim`` and ``length_unit=m``.
    """
    ase = _library("ase", "writing extended XYZ")
    ase_io = _library("ase.io", "writing extended XYZ")
    position, radius = np.asarray(position), np.asarray(radius)
    t, n, d = position.shape
    scale, half = _scale_and_half_sizes(box_half_size, length_scale, d)
    radius_m = _si_radius(radius, scale)
    depth = 2 * half[2] if d == 3 else 2 * float(radius_m.max())
    cell = np.diag([2 * half[0], 2 * half[1], depth])
    origin = np.array([-half[0], -half[1], -depth / 2])
    images = []
    for frame, xyz in enumerate(_si_frames(position, scale)):
        atoms = ase.Atoms(numbers=np.zeros(n, int), positions=xyz, cell=cell, pbc=False)
        atoms.arrays["radius"] = radius_m
        atoms.info.update(Time=frame * frame_dt, frame=frame, dim=d, length_unit="m", Origin=origin)
        images.append(atoms)
    with atomic_path(path) as temporary:
        ase_io.write(temporary, images, format="extxyz")
    return Path(path)


def write_gsd(
    path: str | os.PathLike,
    position: Positions,
    radius: Radii,
    *,
    box_half_size: float | Sequence[float],
    frame_dt: float,
    save_every: int = 1,
    length_scale: float | None = None,
) -> Path:
    """Write one trajectory as a GSD file (HOOMD-blue's format; OVITO reads it too).

    Args: as :func:`write_extxyz`; ``save_every`` numbers the frames' ``configuration/step``.

    Frames hold ``particles/position`` (float32 m, ``z = 0`` in 2-D), ``particles/diameter`` (m), one type
    ``A``, HOOMD's centred box (full sizes ``[Lx, Ly, Lz or 0, 0, 0, 0]``) with ``dimensions`` D, and the log entries
    ``dispgns/time_s`` and ``dispgns/length_unit_m`` (1: metres).
    """
    hoomd = _library("gsd.hoomd", "writing GSD")
    position, radius = np.asarray(position), np.asarray(radius)
    t, n, d = position.shape
    scale, half = _scale_and_half_sizes(box_half_size, length_scale, d)
    with atomic_path(path) as temporary:
        with hoomd.open(name=str(temporary), mode="w") as file:
            for frame, xyz in enumerate(_si_frames(position, scale)):
                snapshot = hoomd.Frame()
                snapshot.configuration.step = frame * save_every
                snapshot.configuration.dimensions = d
                snapshot.configuration.box = [2 * half[0], 2 * half[1], 2 * half[2] if d == 3 else 0.0, 0, 0, 0]
                snapshot.particles.N = n
                snapshot.particles.types = ["A"]
                snapshot.particles.typeid = np.zeros(n, np.uint32)
                snapshot.particles.position = xyz.astype(np.float32)
                snapshot.particles.diameter = (2 * _si_radius(radius, scale)).astype(np.float32)
                snapshot.log[GSD_TIME] = np.array([frame * frame_dt])
                snapshot.log[GSD_LENGTH_UNIT] = np.array([1.0])
                file.append(snapshot)
    return Path(path)


def write_vtu_series(
    path: str | os.PathLike,
    position: Positions,
    radius: Radii,
    *,
    box_half_size: float | Sequence[float],
    frame_dt: float,
    length_scale: float | None = None,
) -> Path:
    """Write one trajectory as a ParaView file series: ``STEM_00000.vtu``, ... and ``path`` (``STEM.vtu.series``).

    Args: as :func:`write_extxyz`; ``path`` must end in ``.vtu.series``.

    Each ``.vtu`` (written by meshio) holds the centres in m as vertex cells with point data ``radius`` (m);
    the JSON ``.vtu.series`` file lists them with their times in s (ParaView opens it as one time series;
    a Glyph filter scaled by ``radius`` draws the particles).
    """
    meshio = _library("meshio", "writing VTU")
    path = Path(path)
    if not path.name.endswith(".vtu.series"):
        raise ValueError(f"{path}: a VTU series file must end in .vtu.series")
    stem = path.name[: -len(".vtu.series")]
    position, radius = np.asarray(position), np.asarray(radius)
    t, n, d = position.shape
    scale, _ = _scale_and_half_sizes(box_half_size, length_scale, d)
    cells = [("vertex", np.arange(n).reshape(-1, 1))]
    radius_m = _si_radius(radius, scale)
    entries = []
    for frame, xyz in enumerate(_si_frames(position, scale)):
        name = f"{stem}_{frame:05d}.vtu"
        mesh = meshio.Mesh(xyz, cells, point_data={"radius": radius_m})
        with atomic_path(path.parent / name) as temporary:
            meshio.write(temporary, mesh, file_format="vtu")
        entries.append({"name": name, "time": frame * frame_dt})
    write_atomic(path, json.dumps({"file-series-version": "1.0", "files": entries}, indent=1) + "\n")
    return path


def write_trajectory_file(
    path: str | os.PathLike,
    fmt: str,
    trajectory: Trajectory,
    *,
    box_half_size: float | Sequence[float],
    frame_dt: float,
    save_every: int = 1,
    length_scale: float | None = None,
) -> Path:
    """Write ``trajectory`` (normalised units) to ``path`` in ``fmt`` (one of :data:`EXPORT_FORMATS`); the box
    and ``length_scale`` as in :func:`write_extxyz`."""
    _check_fmt(fmt, EXPORT_FORMATS)
    kwargs: dict[str, Any] = dict(box_half_size=box_half_size, frame_dt=frame_dt, length_scale=length_scale)
    if fmt == "gsd":
        return write_gsd(path, trajectory.position, trajectory.radius, save_every=save_every, **kwargs)
    writer = write_extxyz if fmt == "extxyz" else write_vtu_series
    return writer(path, trajectory.position, trajectory.radius, **kwargs)


# ----------------------------------------------------------------------------- readers


class FileTrajectory:
    """One trajectory as a file holds it, before normalisation (host arrays, file units).

    Attributes:
      position: ``(T, N, 3)`` float64 centres in the file's length unit.
      radius: ``(N,)`` float64 radii in the file's length unit.
      box: ``(3, 2)`` per-axis ``[lo, hi]`` in the file's unit, or ``None`` (the file has none).
      dim: ``2``/``3`` when the file says, else ``None``.
      length_unit: metres per file length unit when the file says, else ``None``.
      times: ``(T,)`` frame times in s when the file has them, else ``None``.
      where: the file name, for messages.
    """

    def __init__(
        self,
        position: _FilePositions,
        radius: Radii,
        *,
        box: _FileBox | None = None,
        dim: int | None = None,
        length_unit: float | None = None,
        times: PerFrame | None = None,
        where: str = "",
    ):
        self.position, self.radius, self.box = position, radius, box
        self.dim, self.length_unit, self.times, self.where = dim, length_unit, times, where

    def normalised(
        self,
        *,
        length_unit: float | None = None,
        box_half_size: float | Sequence[float] | None = None,
        length_scale: float | None = None,
        dim: int | None = None,
        frame_dt: float | None = None,
    ) -> tuple[Trajectory, tuple[float, ...], float]:
        """``(Trajectory in normalised units, the box's half-sizes (D,) in m, L in m)``; arguments override or
        complete the file.

        Args:
          length_unit: metres per file length unit (required when the file does not say).
          box_half_size: the box's half-size in m, one for every axis or one per axis: required for a file
            without a box (or give ``length_scale`` alone: the box is then ``[-L, L]^D``); with a box in the
            file, it must agree.
          length_scale: ``L`` in m, what positions and radii are divided by (default: the box's half-size
            along the last, vertical axis, as :func:`~dispgns.data.generate_dataset` does; the half-size of
            a square or cubic box).
          dim: 2 or 3 (default: the file's, else 2 when every ``z`` is 0, else 3).
          frame_dt: the time between frames in s, checked against the file's times when it has them.

        The file's box may be rectangular (per-axis widths) but not tilted; positions are re-centred on it,
        so the box becomes ``bounds = ((-h_d / L, h_d / L) for each axis d)``, ``[-1, 1]^D`` for a cube.
        """
        where = self.where
        unit = self.length_unit if length_unit is None else length_unit
        if self.length_unit is not None and length_unit is not None and not math.isclose(length_unit, self.length_unit):
            raise DatasetError(
                f"{where}: the file's length unit is {self.length_unit} m, but {length_unit} m was given"
            )
        if unit is None:
            raise DatasetError(f"{where}: the file does not state its length unit; give it (metres per file unit)")
        if not (math.isfinite(unit) and unit > 0):
            raise DatasetError(f"{where}: length unit {unit!r}, expected a number > 0 (metres per file unit)")
        if length_scale is not None and not (math.isfinite(length_scale) and length_scale > 0):
            raise DatasetError(f"{where}: length scale L = {length_scale!r} m, expected a number > 0")
        position, radius = self.position, self.radius
        if dim is None:
            dim = self.dim if self.dim is not None else (2 if np.all(position[..., 2] == 0) else 3)
        if dim not in (2, 3):
            raise DatasetError(f"{where}: dimension {dim!r}, expected 2 or 3")
        if dim == 2 and np.any(position[..., 2] != 0):
            frame, particle = (int(i) for i in np.argwhere(position[..., 2] != 0)[0])
            raise DatasetError(
                f"{where}: frame {frame} particle {particle}: 'z' is {position[frame, particle, 2]}, expected 0 in 2-D"
            )
        given = None
        if box_half_size is not None:
            given = np.asarray(box_half_size, np.float64).reshape(-1)
            if given.size not in (1, dim) or not np.all(np.isfinite(given) & (given > 0)):
                raise DatasetError(
                    f"{where}: box half-size {given.tolist()} m, expected one number > 0 or {dim} (one per axis)"
                )
            given = np.broadcast_to(given, (dim,))
        if self.box is not None:
            box = np.asarray(self.box, np.float64)[:dim] * unit
            widths = box[:, 1] - box[:, 0]
            if not np.all(widths > 0):
                raise DatasetError(f"{where}: 'box' is {box.tolist()} m, expected a width > 0 on every axis")
            half = widths / 2
            if given is not None and not np.allclose(given, half, rtol=1e-6, atol=0):
                raise DatasetError(f"{where}: 'box' has half-sizes {half.tolist()} m, but {given.tolist()} m was given")
            centre = box.mean(axis=1)
        elif given is not None:
            half, centre = given.copy(), np.zeros(dim)
        elif length_scale is not None:
            half, centre = np.full(dim, float(length_scale)), np.zeros(dim)
        else:
            raise DatasetError(
                f"{where}: the file has no box; give its half-size in m, one or one per axis "
                f"(the box is centred on 0), or the length scale L (the box is then [-L, L]^D)"
            )
        # Half-sizes from float32 files (GSD) at 12 significant digits, so 0.4 stays 0.4 in metadata.json.
        half = np.array([float(f"{h:.12g}") for h in half])
        scale = float(half[-1]) if length_scale is None else float(length_scale)
        limit = half / scale
        scaled = (position[..., :dim] * unit - centre) / scale
        outside = np.abs(scaled) > limit + BOX_TOLERANCE
        if np.any(outside):
            frame, particle, axis = (int(i) for i in np.argwhere(outside)[0])
            raise DatasetError(
                f"{where}: frame {frame} particle {particle}: position axis {axis} is "
                f"{position[frame, particle, axis]:.6g} (file units), outside the box"
            )
        times = self.times
        if times is not None and frame_dt is not None and len(times) > 1:
            steps = np.diff(np.asarray(times, np.float64))
            bad = np.flatnonzero(~np.isclose(steps, frame_dt, rtol=1e-6, atol=0))
            if bad.size:
                frame = int(bad[0]) + 1
                raise DatasetError(
                    f"{where}: frame {frame}: 'time' step is {steps[bad[0]]:.6g} s, expected {frame_dt:.6g} s "
                    f"(save_every * dt)"
                )
        scaled_radius = radius * unit / scale
        trajectory = Trajectory(
            position=scaled.astype(np.float32),
            radius=scaled_radius.astype(np.float32),
            particle_type=np.zeros((position.shape[1],), np.int32),
            attrs={"source_file": Path(where).name},
        )
        return trajectory, tuple(float(h) for h in half), scale


def _check_frames(where: str, frames: list[tuple[np.ndarray, np.ndarray]], field: str) -> tuple[np.ndarray, np.ndarray]:
    """Stack per-frame ``(positions (N, 3), radii (N,))``: same N, same radii, finite."""
    if not frames:
        raise DatasetError(f"{where}: holds no frames, expected at least one")
    n = len(frames[0][0])
    for frame, (xyz, radius) in enumerate(frames):
        if len(xyz) != n:
            raise DatasetError(f"{where}: frame {frame}: {len(xyz)} particles, expected {n} like frame 0")
        for name, value in (("position", xyz), (field, radius)):
            if not np.all(np.isfinite(value)):
                bad = tuple(int(i) for i in np.argwhere(~np.isfinite(value))[0])
                raise DatasetError(f"{where}: frame {frame}: '{name}' has a non-finite value at index {bad}")
        if not np.array_equal(radius, frames[0][1]):
            particle = int(np.argmax(radius != frames[0][1]))
            raise DatasetError(
                f"{where}: frame {frame}: '{field}' of particle {particle} is {radius[particle]}, expected "
                f"{frames[0][1][particle]} as in frame 0 (radii are constant)"
            )
    if n < 1:
        raise DatasetError(f"{where}: frame 0 holds no particles")
    radius = frames[0][1]
    if not np.all(radius > 0):
        particle = int(np.argmax(~(radius > 0)))
        raise DatasetError(f"{where}: frame 0: '{field}' of particle {particle} is {radius[particle]}, expected > 0")
    return np.stack([xyz for xyz, _ in frames]), radius


def read_extxyz(path: str | os.PathLike) -> FileTrajectory:
    """Read a multi-frame extended XYZ file with a ``radius`` (or ``diameter``) column (ase.io)."""
    ase_io = _library("ase.io", "reading extended XYZ")
    path = Path(path)
    where = path.name
    if not path.is_file():
        raise DatasetError(f"{where}: file not found at {path}")
    try:
        images = ase_io.read(path, index=":", format="extxyz")
    except Exception as error:  # ase raises many types for malformed text
        raise DatasetError(f"{where}: cannot be read as extended XYZ: {error}") from None
    frames = []
    for frame, atoms in enumerate(images):
        if "radius" in atoms.arrays:
            radius = np.asarray(atoms.arrays["radius"], np.float64)
        elif "diameter" in atoms.arrays:
            radius = np.asarray(atoms.arrays["diameter"], np.float64) / 2
        else:
            raise DatasetError(
                f"{where}: frame {frame}: no 'radius' or 'diameter' column, found {sorted(atoms.arrays)}"
            )
        frames.append((np.asarray(atoms.positions, np.float64), radius.reshape(-1)))
    position, radius = _check_frames(where, frames, "radius")
    first = images[0]
    box = None
    if first.cell.rank > 0:
        cell = first.cell.array
        if not np.allclose(cell, np.diag(np.diag(cell))):
            raise DatasetError(
                f"{where}: frame 0: 'Lattice' is {cell.tolist()}, a tilted (triclinic) cell: not supported, "
                f"expected a rectangular box (a diagonal Lattice)"
            )
        origin = np.asarray(first.info.get("Origin", np.zeros(3)), np.float64).reshape(-1)
        box = np.stack([origin, origin + np.diag(cell)], axis=1)
    unit = first.info.get("length_unit")
    length_unit = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "nm": 1e-9}.get(unit) if isinstance(unit, str) else None
    times = None
    if all("Time" in atoms.info for atoms in images):
        times = np.array([float(atoms.info["Time"]) for atoms in images])
    dim = first.info.get("dim")
    return FileTrajectory(
        position,
        radius,
        box=box,
        dim=int(dim) if dim in (2, 3) else None,
        length_unit=length_unit,
        times=times,
        where=where,
    )


def _shortest(values) -> np.ndarray:
    """float32 values as the shortest decimals that round-trip (GSD's 0.1 f32 is 0.1, not 0.10000000149)."""
    values = np.asarray(values, np.float32)
    return np.array([float(str(v)) for v in values.reshape(-1)]).reshape(values.shape)


def read_gsd(path: str | os.PathLike) -> FileTrajectory:
    """Read a GSD (HOOMD-blue) trajectory: positions, diameters, the centred box, dimensions (gsd.hoomd)."""
    hoomd = _library("gsd.hoomd", "reading GSD")
    path = Path(path)
    where = path.name
    if not path.is_file():
        raise DatasetError(f"{where}: file not found at {path}")
    try:
        file = hoomd.open(name=str(path), mode="r")
    except Exception as error:  # gsd raises RuntimeError/OSError/ValueError for foreign files
        raise DatasetError(f"{where}: cannot be read as GSD: {error}") from None
    frames, boxes, times, units, dims = [], [], [], [], []
    with file:
        for snapshot in file:
            position = np.asarray(snapshot.particles.position, np.float64).reshape(-1, 3)
            diameter = _shortest(snapshot.particles.diameter).reshape(-1)
            frames.append((position, diameter / 2))
            boxes.append(_shortest(snapshot.configuration.box))
            dims.append(int(snapshot.configuration.dimensions))
            log = snapshot.log
            times.append(float(np.asarray(log[GSD_TIME]).reshape(-1)[0]) if GSD_TIME in log else None)
            units.append(float(np.asarray(log[GSD_LENGTH_UNIT]).reshape(-1)[0]) if GSD_LENGTH_UNIT in log else None)
    position, radius = _check_frames(where, frames, "diameter")
    for frame, box in enumerate(boxes):
        if not np.allclose(box, boxes[0]):
            raise DatasetError(
                f"{where}: frame {frame}: 'configuration/box' is {box.tolist()}, expected {boxes[0].tolist()}"
            )
        if np.any(box[3:] != 0):
            raise DatasetError(
                f"{where}: frame {frame}: 'configuration/box' has tilt factors xy, xz, yz = {box[3:].tolist()}: "
                f"tilted (triclinic) boxes are not supported, expected 0"
            )
    half = boxes[0][:3] / 2
    box = np.stack([-half, half], axis=1)
    return FileTrajectory(
        position,
        radius,
        box=box,
        dim=dims[0],
        length_unit=units[0],
        times=None if None in times else np.array(times),
        where=where,
    )


def read_lammps_dump(path: str | os.PathLike) -> FileTrajectory:
    """Read a LAMMPS text dump (``dump custom``/``atom``) with ``id``, ``x y z`` and ``radius`` or ``diameter``.

    Particles are ordered by ``id`` in every frame. Scaled coordinates (``xs ys zs``) are unscaled with the
    frame's box. LAMMPS does not write its units into the dump: the length unit must be given.
    """
    path = Path(path)
    where = path.name
    if not path.is_file():
        raise DatasetError(f"{where}: file not found at {path}")
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{where}: cannot be read as text: {error}") from None
    frames, boxes, i, frame, first_ids = [], [], 0, 0, None

    def need(condition, message):
        if not condition:
            raise DatasetError(f"{where}: frame {frame}: {message}")

    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        need(lines[i].startswith("ITEM: TIMESTEP"), f"line {i + 1} is {lines[i]!r}, expected 'ITEM: TIMESTEP'")
        try:
            need(lines[i + 2].startswith("ITEM: NUMBER OF ATOMS"), f"line {i + 3}: expected 'ITEM: NUMBER OF ATOMS'")
            n = int(lines[i + 3])
            need(lines[i + 4].startswith("ITEM: BOX BOUNDS"), f"line {i + 5}: expected 'ITEM: BOX BOUNDS'")
            need(
                not any(tilt in lines[i + 4].split() for tilt in ("xy", "xz", "yz")),
                f"'ITEM: BOX BOUNDS' is {lines[i + 4].strip()!r}: tilted (triclinic) boxes are not supported, "
                f"expected an orthogonal box ('ITEM: BOX BOUNDS' without xy xz yz)",
            )
            box = np.array([[float(v) for v in lines[i + 5 + k].split()[:2]] for k in range(3)])
            header = lines[i + 8]
            need(header.startswith("ITEM: ATOMS"), f"line {i + 9}: expected 'ITEM: ATOMS ...'")
            columns = header.split()[2:]
            rows = np.array([[float(v) for v in lines[i + 9 + k].split()] for k in range(n)]).reshape(n, -1)
        except (IndexError, ValueError) as error:
            raise DatasetError(f"{where}: frame {frame}: truncated or malformed near line {i + 1} ({error})") from None
        need(rows.shape[1] == len(columns), f"rows have {rows.shape[1]} values, expected {len(columns)} ({columns})")
        table = dict(zip(columns, rows.T))
        need("id" in table, f"no 'id' column, found {columns}")
        if all(c in table for c in ("x", "y", "z")):
            xyz = np.stack([table["x"], table["y"], table["z"]], axis=1)
        elif all(c in table for c in ("xs", "ys", "zs")):
            scaled = np.stack([table["xs"], table["ys"], table["zs"]], axis=1)
            xyz = box[:, 0] + scaled * (box[:, 1] - box[:, 0])
        else:
            need(False, f"no 'x y z' or 'xs ys zs' columns, found {columns}")
        if "radius" in table:
            radius = table["radius"]
        elif "diameter" in table:
            radius = table["diameter"] / 2
        else:
            need(False, f"no 'radius' or 'diameter' column, found {columns}")
        order = np.argsort(table["id"], kind="stable")
        if first_ids is not None:
            need(
                n == len(frames[0][0]) and np.array_equal(table["id"][order], first_ids),
                f"{n} particles with other ids than frame 0 ({len(frames[0][0])} particles), expected the same",
            )
        else:
            first_ids = table["id"][order]
        frames.append((xyz[order], radius[order]))
        boxes.append(box)
        i += 9 + n
        frame += 1
    position, radius = _check_frames(where, frames, "radius")
    for k, box in enumerate(boxes):
        if not np.allclose(box, boxes[0]):
            raise DatasetError(f"{where}: frame {k}: 'BOX BOUNDS' is {box.tolist()}, expected {boxes[0].tolist()}")
    return FileTrajectory(position, radius, box=boxes[0], where=where)


def read_trajectory_file(path: str | os.PathLike, fmt: str) -> FileTrajectory:
    """Read one trajectory file of ``fmt`` (one of :data:`IMPORT_FORMATS`), in the file's units."""
    _check_fmt(fmt, IMPORT_FORMATS)
    return {"extxyz": read_extxyz, "gsd": read_gsd, "lammps-dump": read_lammps_dump}[fmt](path)


def import_trajectory_files(
    paths: Sequence[str | os.PathLike],
    fmt: str,
    out_dir: str | os.PathLike,
    *,
    split: str = "train",
    length_unit: float | None = None,
    box_half_size: float | Sequence[float] | None = None,
    length_scale: float | None = None,
    dim: int | None = None,
    save_every: int = 15,
    dt: float | None = None,
    overwrite: bool = False,
) -> DatasetMetadata:
    """Import trajectory files (one trajectory each) as split ``split`` of the dataset ``out_dir``.

    Args:
      paths: the files, in trajectory order.
      fmt: one of :data:`IMPORT_FORMATS`.
      out_dir: the dataset directory: new, empty, or an earlier import of the same format.
      split: the split to write.
      length_unit, box_half_size, length_scale, dim: see :meth:`FileTrajectory.normalised` (what the files
        do not say; the box may be rectangular).
      save_every: Euler steps between frames; with ``dt`` (the Euler step in s, default the
        :class:`~dispgns.physics.PhysicsConfig` default) it gives the frame spacing, checked against
        the files' times when they have them.
      overwrite: replace the split if the dataset already has it.

    Returns:
      The dataset's :class:`~dispgns.data.format.DatasetMetadata` (no initial state: the physics cannot
      be re-run): ``box_half_size`` one number for a square or cubic box, else one per axis (m);
      ``length_scale`` L (m) and ``bounds`` (units of L) as :func:`~dispgns.data.generate_dataset` writes them.
    """
    from dispgns.data.importers import write_imported
    from dispgns.physics import PhysicsConfig

    _check_fmt(fmt, IMPORT_FORMATS)
    if not paths:
        raise ValueError("no files given, expected at least one")
    if not (isinstance(save_every, int) and save_every >= 1):
        raise ValueError(f"save_every must be an integer >= 1, got {save_every!r}")
    dt = PhysicsConfig().dt if dt is None else float(dt)
    trajectories, half, scale = [], None, None
    for path in paths:
        trajectory, file_half, file_scale = read_trajectory_file(path, fmt).normalised(
            length_unit=length_unit,
            box_half_size=box_half_size,
            length_scale=length_scale,
            dim=dim,
            frame_dt=save_every * dt,
        )
        if half is None:
            half, scale = file_half, float(f"{file_scale:.12g}")
        elif len(file_half) != len(half) or not np.allclose(file_half, half, rtol=1e-6, atol=0):
            raise DatasetError(
                f"{Path(path).name}: box half-sizes {list(file_half)} m, expected {list(half)} m like "
                f"{Path(paths[0]).name}"
            )
        if trajectories and (trajectory.n_frames, trajectory.dim) != (trajectories[0].n_frames, trajectories[0].dim):
            raise DatasetError(
                f"{Path(path).name}: {trajectory.n_frames} frames in {trajectory.dim}-D, expected "
                f"{trajectories[0].n_frames} frames in {trajectories[0].dim}-D like {Path(paths[0]).name}"
            )
        trajectories.append(trajectory)
    # One number for a square or cubic box (the paper's datasets), one per axis otherwise (like wide4).
    physics_box = half[0] if len(set(half)) == 1 else half
    return write_imported(
        trajectories,
        out_dir,
        split=split,
        physics=PhysicsConfig(box_half_size=physics_box, dt=dt),
        save_every=save_every,
        source=f"imported {fmt}",
        source_name=", ".join(Path(p).name for p in paths),
        overwrite=overwrite,
        length_scale=scale,
    )


EXPORT_MARKER = "export.json"


def export_trajectories(
    source: str | os.PathLike,
    out_dir: str | os.PathLike,
    fmt: str,
    *,
    splits: Sequence[str] | None = None,
    indices: Sequence[int] | None = None,
    metadata: DatasetMetadata | None = None,
    box_half_size: float | None = None,
    frame_dt: float | None = None,
    overwrite: bool = False,
) -> list[Path]:
    """Write trajectories of a dataset, or of one split file (e.g. a rollout), one file each, into ``out_dir``.

    Args:
      source: a dataset directory, or one ``.h5`` split file (a dataset's, or the predictions
        ``dispgns evaluate`` writes), read and validated by dispgns's reader.
      out_dir: the export directory (new or empty; an earlier export only with ``overwrite``),
        written whole or not at all; files are named :func:`export_filename` (the split of a single
        file is its stem) and ``export.json`` records what was written, the units and the source.
      fmt: one of :data:`EXPORT_FORMATS`.
      splits: the splits of a dataset to write (default all).
      indices: the trajectory indices to write in each split (default all).
      metadata: for a split file, the :class:`~dispgns.data.format.DatasetMetadata` of its dataset
        (for L and the frame spacing); or give ``box_half_size`` (m) and ``frame_dt`` (s).
      overwrite: replace an earlier export in ``out_dir``.

    Returns:
      The paths written (one per trajectory).
    """
    from dispgns.data.format import load_dataset, read_split
    from dispgns.files import staged_directory

    _check_fmt(fmt, EXPORT_FORMATS)
    _library(_LIBRARY[fmt], f"writing {fmt}")  # fail before reading anything
    source = Path(source)
    if source.is_dir():
        metadata, data = load_dataset(source, splits)
    else:
        data = {source.stem: read_split(source)}
        if splits is not None and list(splits) != [source.stem]:
            raise DatasetError(f"{source.name}: holds the split {source.stem!r} only, not {list(splits)}")
    length_scale = None
    if metadata is not None:
        if box_half_size is None:
            # The stored positions are divided by the length scale, which differs from the box in a
            # rectangular container (``wide4``: half-sizes (0.4, 0.1) m, L = 0.1 m).
            box_half_size, length_scale = metadata.box_half_size, metadata.length_scale
        frame_dt = metadata.frame_dt if frame_dt is None else frame_dt
    if box_half_size is None or frame_dt is None:
        raise DatasetError(
            f"{source.name}: a split file does not record L and the frame spacing; give the dataset's "
            f"metadata (--data DATASET) or the box half-size and frame time"
        )
    save_every = getattr(metadata, "save_every", 1)
    written, records = [], []
    with staged_directory(out_dir, overwrite=overwrite, marker=EXPORT_MARKER, kind="export") as staging:
        for split, trajectories in data.items():
            chosen = range(len(trajectories)) if indices is None else indices
            for index in chosen:
                if not 0 <= index < len(trajectories):
                    raise DatasetError(
                        f"{source.name}: split {split!r} has {len(trajectories)} trajectories, no index {index}"
                    )
                name = export_filename(split, index, fmt)
                write_trajectory_file(
                    staging / name,
                    fmt,
                    trajectories[index],
                    box_half_size=box_half_size,
                    frame_dt=frame_dt,
                    save_every=save_every,
                    length_scale=length_scale,
                )
                records.append({"file": name, "split": split, "index": index, **trajectories[index].attrs})
                written.append(Path(out_dir) / name)
        info = {
            "format": fmt,
            "source": str(source.absolute()),
            "length_unit": "m",
            "time_unit": "s",
            "box_half_size_m": list(box_half_size) if isinstance(box_half_size, tuple) else box_half_size,
            "length_scale_m": box_half_size if length_scale is None else length_scale,
            "frame_dt_s": frame_dt,
            "trajectories": records,
        }
        write_atomic(staging / EXPORT_MARKER, json.dumps(info, indent=1, default=str) + "\n")
    return written
