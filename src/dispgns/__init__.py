"""dispgns: learned simulation of finite-size particle suspensions with graph networks.

``import dispgns`` changes nothing outside dispgns (no allocator, XLA flag
or environment change); speed tuning is opt-in, in :mod:`dispgns.tuning`.
The public names below load their modules on first use, so the import stays
fast (jax-md, whose import takes seconds, comes with the first name that
needs it).

Pure functions (``jit``, ``vmap``, ``grad``, ``lax.scan``; capacities
static, overflow a returned flag): :func:`euler_integrator`,
:func:`simulate_scan`, :func:`predict_step`, :func:`rollout_scan`,
:func:`train_step`. Host conveniences (concrete arrays; capacities sized
from the data and grown after an overflow): :func:`simulate`,
:func:`simulate_batch`, :func:`predict_acceleration`,
:func:`predict_position`, :func:`rollout`, :func:`rollout_batch`.
"""

from __future__ import annotations

# typing.TYPE_CHECKING without importing typing: the package's import is the start of the ``dispgns`` program,
# the one moment a Ctrl-C still gives a traceback (see dispgns.cli.entry), so it stays short.
TYPE_CHECKING = False

__version__ = "0.1.0"

# Public name -> the module that defines it (a module name maps to itself).
_EXPORTS = {
    # Ground truth: the physics.
    "PhysicsConfig": "dispgns.physics",
    "SimState": "dispgns.physics",
    "euler_integrator": "dispgns.physics",
    "sample_initial_state": "dispgns.physics",
    "simulate": "dispgns.physics",
    "simulate_batch": "dispgns.physics",
    "simulate_scan": "dispgns.physics",
    # Datasets.
    "Trajectory": "dispgns.data",
    "DatasetMetadata": "dispgns.data",
    "DatasetError": "dispgns.data",
    "load_dataset": "dispgns.data",
    "generate_dataset": "dispgns.data",
    # Learned simulator: graph capacity, network, one-step prediction, rollout.
    "GraphCapacity": "dispgns.graph",
    "ModelConfig": "dispgns.model",
    "init_params": "dispgns.model",
    "fit_capacity": "dispgns.simulator",
    "predict_step": "dispgns.simulator",
    "predict_acceleration": "dispgns.simulator",
    "predict_position": "dispgns.simulator",
    "rollout": "dispgns.simulator",
    "rollout_batch": "dispgns.simulator",
    "rollout_scan": "dispgns.simulator",
    # Training.
    "Batch": "dispgns.training",
    "BatchStream": "dispgns.training",
    "TrainConfig": "dispgns.training",
    "TrainState": "dispgns.training",
    "compute_normalization": "dispgns.training",
    "create_train_state": "dispgns.training",
    "make_optimizer": "dispgns.training",
    "train_step": "dispgns.training",
    "train": "dispgns.training",
    "NonFiniteLossError": "dispgns.training",
    "export_model": "dispgns.training.checkpoint",
    "load_model": "dispgns.training.checkpoint",
    "load_params": "dispgns.training.checkpoint",
    # Metrics, evaluation and the shipped model.
    "rollout_metrics": "dispgns.metrics",
    "summarize": "dispgns.metrics",
    "constant_velocity_rollout": "dispgns.metrics",
    "chaos_floor_rollout": "dispgns.evaluation",
    "evaluate_trajectories": "dispgns.evaluation",
    "load_pretrained": "dispgns.pretrained",
    # Opt-in speed settings.
    "tuning": "dispgns.tuning",
}

__all__ = [
    "Batch",
    "BatchStream",
    "DatasetError",
    "DatasetMetadata",
    "GraphCapacity",
    "ModelConfig",
    "PhysicsConfig",
    "SimState",
    "TrainConfig",
    "TrainState",
    "Trajectory",
    "NonFiniteLossError",
    "__version__",
    "chaos_floor_rollout",
    "compute_normalization",
    "constant_velocity_rollout",
    "create_train_state",
    "euler_integrator",
    "evaluate_trajectories",
    "export_model",
    "fit_capacity",
    "generate_dataset",
    "init_params",
    "load_dataset",
    "load_model",
    "load_params",
    "load_pretrained",
    "make_optimizer",
    "predict_acceleration",
    "predict_position",
    "predict_step",
    "rollout",
    "rollout_batch",
    "rollout_metrics",
    "rollout_scan",
    "sample_initial_state",
    "simulate",
    "simulate_batch",
    "simulate_scan",
    "summarize",
    "train",
    "train_step",
    "tuning",
]


def __getattr__(name: str):
    import importlib.util

    module = _EXPORTS.get(name)
    if module is None and not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        # A submodule loads on first use too, so annotations naming one (``dispgns.model.ModelConfig`` in
        # a module that must not import it early) resolve with ``typing.get_type_hints``.
        module = f"{__name__}.{name}"
    if module is None:
        raise AttributeError(f"module 'dispgns' has no attribute {name!r}")
    loaded = importlib.import_module(module)
    value = loaded if module == f"{__name__}.{name}" else getattr(loaded, name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # what static tools and IDEs see
    from dispgns import tuning
    from dispgns.data import DatasetError, DatasetMetadata, Trajectory, generate_dataset, load_dataset
    from dispgns.evaluation import chaos_floor_rollout, evaluate_trajectories
    from dispgns.graph import GraphCapacity
    from dispgns.metrics import constant_velocity_rollout, rollout_metrics, summarize
    from dispgns.model import ModelConfig, init_params
    from dispgns.physics import (
        PhysicsConfig,
        SimState,
        euler_integrator,
        sample_initial_state,
        simulate,
        simulate_batch,
        simulate_scan,
    )
    from dispgns.pretrained import load_pretrained
    from dispgns.simulator import (
        fit_capacity,
        predict_acceleration,
        predict_position,
        predict_step,
        rollout,
        rollout_batch,
        rollout_scan,
    )
    from dispgns.training import (
        Batch,
        BatchStream,
        NonFiniteLossError,
        TrainConfig,
        TrainState,
        compute_normalization,
        create_train_state,
        make_optimizer,
        train,
        train_step,
    )
    from dispgns.training.checkpoint import export_model, load_model, load_params
