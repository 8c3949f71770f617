"""dispgns: learned simulation of finite-size particle suspensions with graph networks."""

__version__ = "0.1.0"

from dispgns.physics import (
    PhysicsConfig,
    SimState,
    euler_integrator,
    sample_initial_state,
    simulate,
    simulate_batch,
)
from dispgns.metrics import chaos_floor_rollout, constant_velocity_rollout, rollout_metrics, summarize
from dispgns.data import DatasetError, DatasetMetadata, Trajectory, generate_dataset, load_dataset

__all__ = [
    "__version__",
    "PhysicsConfig",
    "SimState",
    "euler_integrator",
    "sample_initial_state",
    "simulate",
    "simulate_batch",
    "rollout_metrics",
    "summarize",
    "constant_velocity_rollout",
    "chaos_floor_rollout",
    "Trajectory",
    "DatasetMetadata",
    "DatasetError",
    "load_dataset",
    "generate_dataset",
]
