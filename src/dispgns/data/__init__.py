"""Datasets: the HDF5 format, generation presets, the authors' npz importer, the LagrangeBench export."""

from dispgns.data.format import (
    FORMAT_VERSION,
    SPLITS,
    DatasetError,
    DatasetMetadata,
    Trajectory,
    load_dataset,
    read_metadata,
    read_split,
    validate_trajectory,
    write_metadata,
    write_split,
)
from dispgns.data.formats import export_trajectories, import_trajectory_files
from dispgns.data.generate import (
    PRESETS,
    DatasetSpec,
    RadiiGroup,
    UnstableSimulationError,
    generate_dataset,
    largest_frame_move,
    paper3d_spec,
    paper_spec,
    preset,
    sample_initial_states,
    tiny_spec,
    trajectory_key,
)
from dispgns.data.importers import import_authors_npz, read_authors_npz
from dispgns.data.lagrangebench import export_lagrangebench

__all__ = [
    "FORMAT_VERSION",
    "SPLITS",
    "DatasetError",
    "DatasetMetadata",
    "Trajectory",
    "load_dataset",
    "read_metadata",
    "read_split",
    "validate_trajectory",
    "write_metadata",
    "write_split",
    "PRESETS",
    "DatasetSpec",
    "RadiiGroup",
    "UnstableSimulationError",
    "generate_dataset",
    "largest_frame_move",
    "paper3d_spec",
    "paper_spec",
    "preset",
    "sample_initial_states",
    "tiny_spec",
    "trajectory_key",
    "import_authors_npz",
    "read_authors_npz",
    "export_lagrangebench",
    "export_trajectories",
    "import_trajectory_files",
]
