"""Logging: JSON never holds NaN, a non-finite loss stops training after checkpointing the last finite state,
TensorBoard and W&B (offline) loggers, ``dispgns train --logger``."""

import json
import math

import jax
import numpy as np
import pytest

import dispgns.training.loop as loop_module
from dispgns.cli import main
from dispgns.data import load_dataset
from dispgns.model import ModelConfig
from dispgns.training import (
    LoggerGroup,
    NonFiniteLossError,
    TrainConfig,
    compute_normalization,
    create_train_state,
    json_safe,
    train,
)
from dispgns.training.batches import BatchStream
from dispgns.training.checkpoint import Checkpointer, JsonlLog, write_json

CONFIG = TrainConfig(
    learning_rate=1e-3, batch_size=2, log_every=1, validate_every=0, checkpoint_every=100, keep_checkpoints=2
)
SMALL = ModelConfig(connectivity_radius=0.4, latent_size=8, hidden_size=8, message_passing_steps=1)


def _strict(text):
    """Parse JSON rejecting the non-standard NaN/Infinity tokens."""

    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_json_files_never_hold_nan(tmp_path):
    record = {"kind": "train", "step": 3, "loss": float("nan"), "grad": [1.0, float("inf")], "x": np.float32("nan")}
    assert json_safe(record) == {"kind": "train", "step": 3, "loss": None, "grad": [1.0, None], "x": None}
    log = JsonlLog(tmp_path / "log.jsonl")
    log.write(record)
    log.write({"kind": "train", "step": 5, "loss": 0.5})
    assert [_strict(line)["loss"] for line in (tmp_path / "log.jsonl").read_text().splitlines()] == [None, 0.5]
    log.truncate_after(4)
    assert _strict((tmp_path / "log.jsonl").read_text())["loss"] is None
    write_json(tmp_path / "c.json", {"best": -math.inf, "ok": 1})
    assert _strict((tmp_path / "c.json").read_text()) == {"best": None, "ok": 1}


@pytest.fixture(scope="module")
def train_trajectories(tiny_dataset):
    return load_dataset(tiny_dataset, ["train"])[1]["train"]


def _fresh(trajectories, model_config):
    norm = compute_normalization(trajectories, noise_std=CONFIG.noise_std)
    init_key, key = jax.random.split(jax.random.key(CONFIG.seed))
    state = create_train_state(init_key, model_config, CONFIG, norm)
    return state, BatchStream.for_training(trajectories, model_config, CONFIG), key


def test_non_finite_loss_stops_after_checkpointing_the_last_finite_state(train_trajectories, tmp_path, monkeypatch):
    real_step = loop_module.train_step_checked

    def poisoned(state, batch, key, **kwargs):
        new_state, metrics, extra = real_step(state, batch, key, **kwargs)
        if int(state.step) == 2:  # the 3rd step
            metrics = {**metrics, "loss": jax.numpy.float32(float("nan"))}
        return new_state, metrics, extra

    monkeypatch.setattr(loop_module, "train_step_checked", poisoned)
    state, stream, key = _fresh(train_trajectories, SMALL)
    records = []
    checkpointer = Checkpointer(tmp_path / "run", keep=2)
    with pytest.raises(NonFiniteLossError, match=r"the loss is nan .* at step 3; a checkpoint of step 2") as caught:
        train(state, stream, key, until_step=5, checkpointer=checkpointer, on_log=LoggerGroup([records.append]))
    checkpointer.close()
    assert caught.value.step == 3 and int(caught.value.state.step) == 2
    assert [r["step"] for r in records] == [1, 2]  # nothing logged for the failed step
    # The checkpoint is the last finite state, and equals the uninterrupted run's state at step 2.
    monkeypatch.setattr(loop_module, "train_step_checked", real_step)
    template, stream, _ = _fresh(train_trajectories, SMALL)
    again = Checkpointer(tmp_path / "run", keep=2)
    restored, _, _ = again.restore(template, key)
    again.close()
    state, stream, key = _fresh(train_trajectories, SMALL)
    two = train(state, stream, key, until_step=2).state
    assert int(restored.step) == 2
    for a, b in zip(jax.tree_util.tree_leaves(restored.params), jax.tree_util.tree_leaves(two.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.all(np.isfinite(np.asarray(a)))


def test_tensorboard_and_wandb_offline_loggers(tmp_path, monkeypatch):
    pytest.importorskip("tensorboardX")
    pytest.importorskip("wandb")
    from dispgns.training.loggers import make_logger

    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    group = LoggerGroup(
        [make_logger("tensorboard", tmp_path, {"a": 1}), make_logger("wandb", tmp_path, {"a": 1}, project="test")]
    )
    group({"kind": "train", "step": 2, "loss": 0.25, "learning_rate": 1e-3})
    group({"kind": "validation", "step": 2, "valid_rollout_mse": float("nan")})
    group.close()
    events = list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1 and b"train/loss" in events[0].read_bytes()
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("*.wandb"))


@pytest.mark.slow
def test_cli_train_with_tensorboard(tiny_dataset, tmp_path):
    pytest.importorskip("tensorboardX")
    tiny = ["--set", "model.latent_size=8", "--set", "model.hidden_size=8", "--set", "model.message_passing_steps=1"]
    args = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "run"), "--steps", "4", "--no-progress"]
    assert main([*args, *tiny, "--set", "train.log_every=2", "--logger", "tensorboard"]) == 0
    assert b"train/loss" in next((tmp_path / "run" / "tensorboard").glob("events.*")).read_bytes()
    assert [_strict(line)["step"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()][:2] == [2, 4]
