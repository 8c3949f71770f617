"""Import the authors' ``.npz`` trajectory files into the dispgns format.

The authors store one ``.npz`` per split; every key holds an object array
``(positions (T, N, D), radii (N,))``, both already divided by L. Object
arrays can only be loaded with pickle, and unpickling a file can run
arbitrary code, so reading one needs an explicit ``trust_pickle=True``
(``--trust-pickle`` on the command line). The imported data has no initial
state: its physics cannot be re-run.
"""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path

import numpy as np

from dispgns.data.format import (
    BOX_TOLERANCE,
    METADATA_FILE,
    SPLITS,
    DatasetError,
    DatasetMetadata,
    Trajectory,
    radii_groups,
    read_metadata,
    split_filename,
    staged_directory,
    training_statistics,
    write_metadata,
    write_split,
)
from dispgns.physics import PhysicsConfig

__all__ = [
    "SOURCE",
    "UntrustedPickleError",
    "import_authors_npz",
    "read_authors_npz",
    "write_imported",
]

SOURCE = "authors_npz"


class UntrustedPickleError(DatasetError):
    """Reading the file needs pickle and the caller did not allow it."""


def _fail(where: str, message: str):
    raise DatasetError(f"{where}: {message}")


def read_authors_npz(path: str | os.PathLike, *, trust_pickle: bool = False) -> list[tuple[str, Trajectory]]:
    """Read and validate every trajectory of one of the authors' ``.npz`` files.

    Args:
      path: the ``.npz`` file.
      trust_pickle: must be ``True``: the file's object arrays are unpickled,
        which can execute arbitrary code; only pass it for files you trust.

    Returns:
      ``[(key, Trajectory), ...]`` in file order; positions ``(T, N, D)`` and
      radii ``(N,)`` as float32 in normalised units, no initial state.

    Raises:
      UntrustedPickleError: ``trust_pickle`` is not set.
      DatasetError: the file is missing, unreadable or malformed.
    """
    path = Path(path)
    name = path.name
    if not trust_pickle:
        raise UntrustedPickleError(
            f"{path}: the authors' .npz files store object arrays that only load with pickle, and unpickling "
            f"a file can run arbitrary code. Pass trust_pickle=True (--trust-pickle) only if you trust this file."
        )
    if not path.is_file():
        raise DatasetError(f"{name}: file not found at {path}")
    # np.load unpickles any non-zip file as a whole: only ever hand it a zip archive.
    if not zipfile.is_zipfile(path):
        raise DatasetError(
            f"{name}: cannot be read as .npz: not a zip archive, expected the authors' .npz file of trajectories"
        )
    try:
        archive = np.load(path, allow_pickle=True)
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise DatasetError(f"{name}: cannot be read as .npz: {error}") from None
    out = []
    with archive:
        keys = list(archive.files)
        if not keys:
            _fail(name, "holds no trajectories, expected at least one key")
        n_frames = dim = None
        for key in keys:
            where = f"{name}: key {key!r}"
            try:
                value = archive[key]
            except Exception as error:  # a corrupt member or pickle payload
                raise DatasetError(f"{where}: cannot be loaded: {error}") from None
            if value.dtype != object or value.shape != (2,):
                _fail(
                    where,
                    f"is an array of dtype {value.dtype} and shape {value.shape}, expected an object "
                    f"array (positions (T, N, D), radii (N,)) of shape (2,)",
                )
            try:
                position = np.asarray(value[0], dtype=np.float64)
                radius = np.asarray(value[1], dtype=np.float64)
            except (TypeError, ValueError) as error:
                raise DatasetError(f"{where}: entries are not numeric arrays: {error}") from None
            if position.ndim != 3 or position.shape[-1] not in (2, 3) or min(position.shape) < 1:
                _fail(where, f"positions have shape {position.shape}, expected (T, N, 2) or (T, N, 3)")
            t, n, d = position.shape
            if radius.shape != (n,):
                _fail(where, f"radii have shape {radius.shape}, expected ({n},) to match positions {position.shape}")
            if n_frames is None:
                n_frames, dim = t, d
            if (t, d) != (n_frames, dim):
                _fail(
                    where,
                    f"positions have shape {position.shape}, expected ({n_frames}, N, {dim}) like "
                    f"the file's first trajectory",
                )
            for label, array in (("positions", position), ("radii", radius)):
                if not np.all(np.isfinite(array)):
                    bad = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
                    _fail(where, f"{label} have a non-finite value at index {bad}, expected finite values")
            if np.any(np.abs(position) > 1.0 + BOX_TOLERANCE):
                frame, particle, axis = (int(i) for i in np.argwhere(np.abs(position) > 1.0 + BOX_TOLERANCE)[0])
                _fail(
                    where,
                    f"position of particle {particle} at frame {frame}, axis {axis} is "
                    f"{position[frame, particle, axis]:.6g}, expected inside the normalised box [-1, 1] "
                    f"(are the positions divided by L?)",
                )
            if not np.all((radius > 0) & (radius < 1)):
                bad = int(np.argmax(~((radius > 0) & (radius < 1))))
                _fail(where, f"radius of particle {bad} is {radius[bad]:.6g}, expected 0 < radius / L < 1")
            out.append(
                (
                    key,
                    Trajectory(
                        position=position.astype(np.float32),
                        radius=radius.astype(np.float32),
                        particle_type=np.zeros((n,), np.int32),
                        attrs={"source_file": name, "source_key": key},
                    ),
                )
            )
    return out


def _statistics_of(metadata: DatasetMetadata | None) -> dict:
    """The motion statistics an earlier import recorded (kept when another split is added)."""
    if metadata is None:
        return {}
    return {name: getattr(metadata, name) for name in ("vel_mean", "vel_std", "acc_mean", "acc_std")}


def _radii_list_m(trajectories: list[Trajectory], length_scale: float) -> list[float]:
    """The distinct radii in m (rounded to 0.1 um, which undoes the float32 normalisation)."""
    values = np.concatenate([t.radius.astype(np.float64) for t in trajectories]) * length_scale
    return [float(r) for r in np.unique(np.round(values, 7))]


def import_authors_npz(
    path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    trust_pickle: bool = False,
    split: str = "train",
    L: float = 0.1,
    save_every: int = 15,
    physics: PhysicsConfig | None = None,
    overwrite: bool = False,
) -> DatasetMetadata:
    """Convert one of the authors' ``.npz`` files into split ``split`` of the dataset ``out_dir``.

    Import the files of several splits one after another into the same
    directory to build a whole dataset; the metadata is updated each time.

    Args:
      path: the authors' ``.npz`` file (positions and radii divided by L).
      out_dir: the dataset directory: new, empty, or an earlier import.
      trust_pickle: required, see :func:`read_authors_npz`.
      split: the split to write (``train``, ``valid``, ``test``, ``test_unseen``).
      L: the box half-size in m the data was normalised by (0.1 for the paper).
      save_every: Euler steps between the stored frames (15 for the paper).
      physics: the physics the data was made with (default: the paper's,
        with ``box_half_size = L``); recorded only, never re-run.
      overwrite: replace the split if the dataset already has it.

    Returns:
      The dataset's updated metadata.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}, expected one of {list(SPLITS)}")
    if not (isinstance(L, (int, float)) and math.isfinite(L) and L > 0):
        raise ValueError(f"L must be a box half-size > 0 in m, got {L!r}")
    physics = PhysicsConfig(box_half_size=float(L)) if physics is None else physics
    if not math.isclose(physics.box_half_size, L, rel_tol=1e-12):
        raise ValueError(f"physics.box_half_size = {physics.box_half_size} m differs from L = {L} m")
    read = read_authors_npz(path, trust_pickle=trust_pickle)
    trajectories = [trajectory for _, trajectory in read]
    return write_imported(
        trajectories,
        out_dir,
        split=split,
        physics=physics,
        save_every=save_every,
        source=SOURCE,
        source_name=Path(path).name,
        overwrite=overwrite,
    )


def write_imported(
    trajectories: list[Trajectory],
    out_dir: str | os.PathLike,
    *,
    split: str,
    physics: PhysicsConfig,
    save_every: int,
    source: str,
    source_name: str,
    overwrite: bool = False,
    length_scale: float | None = None,
) -> DatasetMetadata:
    """Write imported ``trajectories`` (normalised units, no initial state) as split ``split`` of ``out_dir``.

    ``out_dir`` is new, empty, or an earlier import of the same ``source``, whose metadata is updated
    (dimension, frames, box, L and ``save_every`` must agree). ``length_scale`` is L in m, what the
    positions and radii are divided by (default: ``physics.height``, the box's vertical half-size); the box
    in units of L is ``bounds = ((-h_d / L, h_d / L) for each axis d)``. Returns the dataset's metadata.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}, expected one of {list(SPLITS)}")
    dim, n_frames = trajectories[0].dim, trajectories[0].n_frames
    length_scale = physics.height if length_scale is None else float(length_scale)
    path = source_name
    out_dir = Path(out_dir).absolute()
    existing = None
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"{out_dir} exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not (out_dir / METADATA_FILE).is_file():
            raise FileExistsError(
                f"{out_dir} is not empty and holds no dispgns dataset ({METADATA_FILE}); "
                f"choose a new or empty directory"
            )
        existing = read_metadata(out_dir)
        if existing.source != source:
            raise FileExistsError(
                f"{out_dir} holds a {existing.source} dataset; imported splits can only be "
                f"added to a dataset imported the same way ({source})"
            )
        if split in existing.trajectory_counts and not overwrite:
            raise FileExistsError(f"{out_dir} already has a {split!r} split; allow replacing it")
        for field, have, want in (
            ("dim", existing.dim, dim),
            ("sequence_length", existing.sequence_length, n_frames),
            ("box_half_size", existing.box_half_size, physics.box_half_size),
            ("length_scale", existing.length_scale, length_scale),
            ("save_every", existing.save_every, save_every),
        ):
            if have != want:
                raise DatasetError(
                    f"{Path(path).name}: {field} is {want}, expected {have} like the "
                    f"dataset in {out_dir} ({METADATA_FILE})"
                )

    counts = dict(existing.trajectory_counts) if existing else {}
    radii = {s: list(g) for s, g in existing.radii.items()} if existing else {}
    particles = dict(existing.particle_counts or {}) if existing else {}
    counts[split] = len(trajectories)
    group = radii_groups([(len(trajectories), _radii_list_m(trajectories, length_scale))])[0]
    group["source_file"] = source_name
    radii[split] = [group]
    particles[split] = [t.n_particles for t in trajectories]
    seen = radii.get("train") or [g for groups in radii.values() for g in groups]
    largest = max(max(g["radii_m"]) for g in seen)
    ordered = [s for s in SPLITS if s in counts]
    metadata = DatasetMetadata(
        dim=dim,
        sequence_length=n_frames,
        frame_dt=save_every * physics.dt,
        save_every=save_every,
        box_half_size=physics.box_half_size,
        connectivity_radius=float(f"{4.0 * largest / length_scale:.12g}"),
        length_scale=length_scale,
        trajectory_counts={s: counts[s] for s in ordered},
        radii={s: radii[s] for s in ordered},
        physics=physics.to_dict(),
        has_initial_state=False,
        source=source,
        particle_counts={s: particles[s] for s in ordered},
        **(training_statistics({split: trajectories}) if split == "train" else _statistics_of(existing)),
    )

    if existing is None:
        with staged_directory(out_dir) as staging:
            write_split(staging / split_filename(split), trajectories, bounds=metadata.bounds)
            write_metadata(staging, metadata)
        return metadata

    # Adding to an earlier import: each file is replaced atomically; the new
    # split file is removed again if the metadata cannot be updated.
    target = out_dir / split_filename(split)
    added = not target.exists()
    write_split(target, trajectories, bounds=metadata.bounds)
    try:
        write_metadata(out_dir, metadata)
    except BaseException:
        if added:
            target.unlink(missing_ok=True)
        raise
    return metadata
