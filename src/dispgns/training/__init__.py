"""Training: batches of examples, noise and targets, normalisation statistics, loss, the step and the loop.

The loop (:func:`train`) reports through ``on_log(record)``, the hook for your own logging; the
loggers of :mod:`dispgns.training.loggers` (TensorBoard, W&B) are such callables.
"""

from dispgns.training.batches import Batch, BatchStream, example_index, quarter_turns
from dispgns.training.loggers import LoggerGroup, TensorBoardLogger, WandbLogger, json_safe
from dispgns.training.loop import LoopResult, NonFiniteLossError, Validator, train
from dispgns.training.noise import random_walk_noise, target_acceleration
from dispgns.training.normalization import compute_normalization, identity_normalization
from dispgns.training.step import (
    TrainConfig,
    TrainState,
    create_train_state,
    learning_rate_schedule,
    loss_fn,
    make_optimizer,
    train_step,
    train_step_checked,
)

__all__ = [
    "Batch",
    "BatchStream",
    "quarter_turns",
    "example_index",
    "random_walk_noise",
    "target_acceleration",
    "compute_normalization",
    "identity_normalization",
    "TrainConfig",
    "TrainState",
    "create_train_state",
    "learning_rate_schedule",
    "loss_fn",
    "make_optimizer",
    "train_step",
    "train_step_checked",
    "LoggerGroup",
    "TensorBoardLogger",
    "WandbLogger",
    "json_safe",
    "LoopResult",
    "NonFiniteLossError",
    "Validator",
    "train",
]
