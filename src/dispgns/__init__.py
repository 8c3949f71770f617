"""dispgns: learned simulation of finite-size particle suspensions with graph networks."""

__version__ = "0.1.0"

# First, before jax-md's import starts JAX's CPU backend: see dispgns.runtime.
from dispgns.runtime import tune_at_import as _tune_at_import, tune_host_allocator

_tune_at_import()

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

# Learned simulator core: graph network, one-step prediction, rollout, training step.
from dispgns.graph import GraphCapacity
from dispgns.model import ModelConfig, init_params
from dispgns.simulator import predict_acceleration, predict_position, rollout, rollout_batch
from dispgns.training import (
    TrainConfig,
    TrainState,
    compute_normalization,
    create_train_state,
    make_optimizer,
    train_step,
)
from dispgns.data.examples import Batch, BatchStream

# Evaluation, checkpoints and the shipped model.
from dispgns.evaluation import evaluate_trajectories
from dispgns.pretrained import load_pretrained
from dispgns.training.checkpoint import export_model, load_model, load_params

__all__ += [
    "tune_host_allocator", "GraphCapacity", "ModelConfig", "init_params", "predict_acceleration",
    "predict_position", "rollout", "rollout_batch", "TrainConfig", "TrainState", "compute_normalization",
    "create_train_state", "make_optimizer", "train_step", "Batch", "BatchStream", "evaluate_trajectories",
    "load_pretrained", "export_model", "load_model", "load_params",
]
