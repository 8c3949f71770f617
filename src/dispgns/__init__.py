"""dispgns: learned simulation of finite-size particle suspensions with graph networks.

The public names below load their modules on first use: ``import dispgns``
(and ``dispgns --help``) stays fast, while jax-md, whose import takes
seconds, is imported with the first name that needs it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# First, before anything starts JAX's CPU backend: see dispgns.runtime.
from dispgns.runtime import network_compiler_options, physics_compiler_options, tune_host_allocator
from dispgns.runtime import tune_at_import as _tune_at_import

_tune_at_import()

# Public name -> the module that defines it.
_EXPORTS = {
    # Ground truth: the physics, datasets and metrics.
    "PhysicsConfig": "dispgns.physics",
    "SimState": "dispgns.physics",
    "euler_integrator": "dispgns.physics",
    "sample_initial_state": "dispgns.physics",
    "simulate": "dispgns.physics",
    "simulate_batch": "dispgns.physics",
    "rollout_metrics": "dispgns.metrics",
    "summarize": "dispgns.metrics",
    "constant_velocity_rollout": "dispgns.metrics",
    "chaos_floor_rollout": "dispgns.metrics",
    "Trajectory": "dispgns.data",
    "DatasetMetadata": "dispgns.data",
    "DatasetError": "dispgns.data",
    "load_dataset": "dispgns.data",
    "generate_dataset": "dispgns.data",
    # Learned simulator core: graph network, one-step prediction, rollout, training step.
    "GraphCapacity": "dispgns.graph",
    "ModelConfig": "dispgns.model",
    "init_params": "dispgns.model",
    "predict_acceleration": "dispgns.simulator",
    "predict_position": "dispgns.simulator",
    "rollout": "dispgns.simulator",
    "rollout_batch": "dispgns.simulator",
    "TrainConfig": "dispgns.training",
    "TrainState": "dispgns.training",
    "compute_normalization": "dispgns.training",
    "create_train_state": "dispgns.training",
    "make_optimizer": "dispgns.training",
    "train_step": "dispgns.training",
    "Batch": "dispgns.data.examples",
    "BatchStream": "dispgns.data.examples",
    # Evaluation, checkpoints and the shipped model.
    "evaluate_trajectories": "dispgns.evaluation",
    "load_pretrained": "dispgns.pretrained",
    "export_model": "dispgns.training.checkpoint",
    "load_model": "dispgns.training.checkpoint",
    "load_params": "dispgns.training.checkpoint",
}

__all__ = ["__version__", "tune_host_allocator", "physics_compiler_options", "network_compiler_options", *_EXPORTS]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'dispgns' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # what static tools and IDEs see
    from dispgns.data import DatasetError, DatasetMetadata, Trajectory, generate_dataset, load_dataset
    from dispgns.data.examples import Batch, BatchStream
    from dispgns.evaluation import evaluate_trajectories
    from dispgns.graph import GraphCapacity
    from dispgns.metrics import chaos_floor_rollout, constant_velocity_rollout, rollout_metrics, summarize
    from dispgns.model import ModelConfig, init_params
    from dispgns.physics import (
        PhysicsConfig,
        SimState,
        euler_integrator,
        sample_initial_state,
        simulate,
        simulate_batch,
    )
    from dispgns.pretrained import load_pretrained
    from dispgns.simulator import predict_acceleration, predict_position, rollout, rollout_batch
    from dispgns.training import (
        TrainConfig,
        TrainState,
        compute_normalization,
        create_train_state,
        make_optimizer,
        train_step,
    )
    from dispgns.training.checkpoint import export_model, load_model, load_params
