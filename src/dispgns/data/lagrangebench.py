"""Export a dispgns dataset as a directory LagrangeBench 0.2.0 reads without edits.

LagrangeBench (``lagrangebench.data.H5Dataset`` and
``lagrangebench.case_setup.case_builder``) needs, beyond dispgns's own files:

- the splits ``train``, ``valid`` and ``test`` only (``H5Dataset`` asserts
  it). ``test_unseen`` is exported as a second dataset directory
  ``OUT/test_unseen/`` whose ``test.h5`` and ``valid.h5`` both hold the unseen
  trajectories and whose ``train.h5`` is the main export's (LagrangeBench's
  runner opens all three and takes its statistics from ``train``); its
  ``metadata.json`` carries the training statistics, so a model trained on
  ``OUT`` is evaluated on ``OUT/test_unseen`` with the same normalisation.
- one particle count: its batches stack trajectories, so every trajectory is
  padded to the largest count of the whole export (``num_particles_max``),
  the padding at the end of the particle axis with ``particle_type`` =
  :data:`~dispgns.data.format.PAD_TYPE` (-1, LagrangeBench's
  ``NodeType.PAD_VALUE``: its neighbour lists, noise and losses skip those
  particles) and ``radius`` 0.
  dispgns's own reader drops that padding, so the export is also a valid
  dispgns dataset (:func:`~dispgns.data.format.load_dataset`).
- the twelve ``metadata.json`` keys of
  :data:`~dispgns.data.format.LAGRANGEBENCH_KEYS`, with the motion statistics
  of the training split.

Radius: LagrangeBench has no notion of it (its particle types 1 and 2 are
walls, so radius cannot travel as a type). Every trajectory group keeps
dispgns's ``radius`` dataset, ``(N_max,)`` radii / L (0 for padding), next to
``position`` and ``particle_type``: a LagrangeBench user reads it with
``h5py.File(path)[key]["radius"]``, e.g. in a subclass of ``H5Dataset``
whose ``__getitem__`` returns it as a node feature.

Positions are dispgns's normalised centres (/ L) shifted by +1, so the box
is ``[0, 2]^D`` (``bounds`` in ``metadata.json``, ``position_offset`` 1 there
and as a file attribute, subtracted again by dispgns's reader): the jax-md
cell list behind LagrangeBench's default ``jaxmd_vmap`` neighbour search
assumes coordinates in ``[0, box)`` and misses pairs at negative
coordinates. Padding particles sit outside the box, beyond the connectivity
radius from it and from each other's real neighbours, so they get no edge to
a real particle with either neighbour backend (``jaxmd_vmap`` does not mask
padding; ``matscipy`` does). ``tools/check_lagrangebench.py`` checks all this
with LagrangeBench's own code.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Float, Int

from dispgns.data.format import (
    FORMAT_VERSION,
    PAD_TYPE,
    DatasetError,
    DatasetMetadata,
    Trajectory,
    hdf5_written_whole,
    load_dataset,
    motion_statistics,
    split_filename,
    staged_directory,
    trajectory_name,
    write_metadata,
)

__all__ = ["LAGRANGEBENCH_SPLITS", "OFFSET", "UNSEEN_DIRECTORY", "export_lagrangebench", "pad_trajectory"]

LAGRANGEBENCH_SPLITS = ("train", "valid", "test")
UNSEEN_DIRECTORY = "test_unseen"
# Positions are shifted from [-1, 1] to [0, 2]: jax-md's cell lists assume coordinates in [0, box).
OFFSET = 1.0


# One array of a padded trajectory group (M = n_max particles): position, or particle_type and radius.
_GroupArray = Float[np.ndarray, "T M D"] | Int[np.ndarray, "M"] | Float[np.ndarray, "M"]


def pad_trajectory(
    trajectory: Trajectory, n_max: int, pad_position: Sequence[float], offset: float = OFFSET
) -> dict[str, _GroupArray]:
    """The arrays of one LagrangeBench trajectory group, padded to ``n_max`` particles.

    Args:
      trajectory: the real particles, ``position (T, N, D)`` and ``radius (N,)``
        in normalised units.
      n_max: the common particle count (``>= N``).
      pad_position: ``(D,)`` where padding particles sit, in the shifted
        units of the export.
      offset: added to every real position (the export's ``position_offset``).

    Returns:
      ``{"position": (T, n_max, D) float32, "particle_type": (n_max,) int32,
      "radius": (n_max,) float32}``; padding has type ``PAD_TYPE`` and radius 0.
    """
    t, n, d = trajectory.position.shape
    if n_max < n:
        raise ValueError(f"n_max = {n_max} is smaller than the trajectory's {n} particles")
    position = np.empty((t, n_max, d), np.float32)
    position[:, :n] = trajectory.position + np.float32(offset)
    position[:, n:] = np.asarray(pad_position, np.float32)
    kinds = np.full((n_max,), PAD_TYPE, np.int32)
    kinds[:n] = 0
    radius = np.zeros((n_max,), np.float32)
    radius[:n] = trajectory.radius
    return {"position": position, "particle_type": kinds, "radius": radius}


def _write_padded_split(path: Path, trajectories: Sequence[Trajectory], n_max: int, pad_position) -> None:
    dim = trajectories[0].dim
    with hdf5_written_whole(path) as file:
        file.attrs["format_version"] = FORMAT_VERSION
        file.attrs["num_particles_max"] = n_max
        file.attrs["position_offset"] = np.full((dim,), OFFSET)
        for index, trajectory in enumerate(trajectories):
            group = file.create_group(trajectory_name(index))
            for name, value in pad_trajectory(trajectory, n_max, pad_position).items():
                # Checksums as in dispgns datasets: h5py (LagrangeBench reads with it) checks them on read.
                group.create_dataset(name, data=value, fletcher32=bool(np.ndim(value) and np.size(value)))
            group.attrs["n_particles"] = trajectory.n_particles
            for key, value in trajectory.attrs.items():
                if value is not None and key != "n_particles":
                    group.attrs[key] = value


def _link_or_copy(source: Path, target: Path) -> None:
    """A hard link (no second copy on disk), or a copy where the file system has none."""
    try:
        os.link(source, target)
    except OSError:
        import shutil

        shutil.copyfile(source, target)


def _export_metadata(
    metadata: DatasetMetadata,
    split_map: Mapping[str, str],
    n_max: int,
    statistics: Mapping[str, Sequence[float]],
    source: str,
) -> DatasetMetadata:
    """Metadata of an export directory whose split ``new`` holds the original split ``split_map[new]``."""

    def per_split(values):
        return None if values is None else {new: values[old] for new, old in split_map.items()}

    return dataclasses.replace(
        metadata,
        trajectory_counts=per_split(metadata.trajectory_counts),
        radii=per_split(metadata.radii),
        particle_counts=per_split(metadata.particle_counts),
        split_ids=None if metadata.split_ids is None else per_split(metadata.split_ids),
        has_initial_state=False,
        source=source,
        num_particles_max=n_max,
        position_offset=(OFFSET,) * metadata.dim,
        **{name: tuple(values) for name, values in statistics.items()},
    )


def export_lagrangebench(
    dataset_dir: str | os.PathLike, out_dir: str | os.PathLike, *, overwrite: bool = False
) -> dict[str, DatasetMetadata]:
    """Write ``dataset_dir`` as LagrangeBench dataset directories under ``out_dir`` (see the module doc).

    Args:
      dataset_dir: a dispgns dataset with a ``train`` split (the statistics
        come from it) and any of ``valid``, ``test``, ``test_unseen``.
      out_dir: the export directory (new or empty; a former export only with
        ``overwrite``). Written whole or not at all.
      overwrite: replace an earlier export in ``out_dir``.

    Returns:
      ``{"": metadata of out_dir, "test_unseen": metadata of out_dir/test_unseen}``
      (the second only when the dataset has that split).

    Raises:
      DatasetError: the dataset is invalid, or lacks what LagrangeBench needs
        (a train split, at least 3 frames).
      FileExistsError: ``out_dir`` holds something and ``overwrite`` is off.
    """
    metadata, splits = load_dataset(dataset_dir)
    where = Path(dataset_dir) / "metadata.json"
    if "train" not in splits:
        raise DatasetError(
            f"{where}: no 'train' split, expected one: LagrangeBench takes its normalisation statistics "
            f"from train.h5 (the dataset has {list(metadata.splits)})"
        )
    if metadata.sequence_length < 3:
        raise DatasetError(
            f"{where}: 'sequence_length' is {metadata.sequence_length}, expected at least 3 frames "
            f"(LagrangeBench needs a velocity and an acceleration)"
        )
    # The statistics of the positions LagrangeBench will read: shifted, in float32 (the shift's rounding
    # changes the tiny accelerations' statistics by ~1e-4 relative).
    statistics = motion_statistics([t.position + np.float32(OFFSET) for t in splits["train"]])
    n_max = max(t.n_particles for group in splits.values() for t in group)
    # Padding sits beyond the box's upper corner by 1.5 connectivity radii: no real particle within reach.
    pad_position = [hi + OFFSET + 1.5 * metadata.connectivity_radius for _, hi in metadata.bounds]
    source = f"lagrangebench export of {Path(dataset_dir).absolute().name} ({metadata.source})"
    main_splits = {s: s for s in LAGRANGEBENCH_SPLITS if s in splits}
    result = {}
    with staged_directory(out_dir, overwrite=overwrite) as staging:
        for split in main_splits:
            _write_padded_split(staging / split_filename(split), splits[split], n_max, pad_position)
        result[""] = _export_metadata(metadata, main_splits, n_max, statistics, source)
        write_metadata(staging, result[""])
        if "test_unseen" in splits:
            unseen = staging / UNSEEN_DIRECTORY
            unseen.mkdir()
            _write_padded_split(unseen / split_filename("test"), splits["test_unseen"], n_max, pad_position)
            _link_or_copy(unseen / split_filename("test"), unseen / split_filename("valid"))
            _link_or_copy(staging / split_filename("train"), unseen / split_filename("train"))
            split_map = {"train": "train", "valid": "test_unseen", "test": "test_unseen"}
            result[UNSEEN_DIRECTORY] = _export_metadata(metadata, split_map, n_max, statistics, source)
            write_metadata(unseen, result[UNSEEN_DIRECTORY])
    return result
