"""Training: batches of examples, noise and targets, normalisation statistics, loss, the step and the loop."""

from dispgns.training.batches import Batch, BatchStream, example_index
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
]
