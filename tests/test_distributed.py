"""Data parallelism on forced host devices and on two local processes (JAX's own runtime, gloo on the CPU).

Tolerances. The data-parallel step computes the same function as one device
with the same global batch, with float sums in another order (per-device
partial sums, then a sum over devices). Losses and gradient norms agree to
float32 rounding (rtol 1e-5). Parameters after a few dozen Adam steps agree
less tightly: Adam divides each gradient component by its running RMS, so a
component whose gradient is near zero can move by up to the learning rate on
rounding alone; the bound checked is 20 learning rates after 12 steps, and
the measured difference is far below it (printed on failure).
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from dispgns.training.checkpoint import load_model

ROOT = Path(__file__).resolve().parents[1]
FOUR_DEVICES = {"XLA_FLAGS": "--xla_force_host_platform_device_count=4", "JAX_PLATFORMS": "cpu"}

# 12 data-parallel steps next to 12 one-device steps on the same global batches.
_FOUR_DEVICE_TRAINING = r"""
import json, sys
import jax, numpy as np
from dispgns.data import load_dataset
from dispgns.model import ModelConfig
from dispgns.training import BatchStream, TrainConfig, compute_normalization, create_train_state, train_step
from dispgns.training.distributed import DataParallel

trajs = load_dataset(sys.argv[1], ["train"])[1]["train"]
report = {"devices": jax.device_count()}
# The loss unrolled over 2 steps after a pushforward step: its per-device shares sum to the whole batch's too.
# And taken on the unrolled positions, whose reference frames (the corruption kept) are each device's own.
unrolled = {"pushforward_steps": 1, "unroll_steps": 2}
position = {**unrolled, "unroll_loss": "position"}
variants = {
    "plain": ("plain", {}), "fused": ("fused", {}), "unrolled": ("plain", unrolled), "position": ("plain", position)
}
for name, (kernels, extra) in variants.items():
    mc = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, connectivity_radius=0.4, kernels=kernels)
    tc = TrainConfig(batch_size=4, learning_rate=1e-3, mirror_augmentation=True, ema_decay=0.9, **extra)
    one = create_train_state(jax.random.key(0), mc, tc, compute_normalization(trajs, noise_std=tc.noise_std))
    parallel = DataParallel()
    four = parallel.replicate(one)
    start = one.params["network"]  # where the moving average starts
    whole = BatchStream.for_training(trajs, mc, tc)
    split = BatchStream.for_training(trajs, mc, tc, shards=4)
    losses, norms = [], []
    for i in range(12):
        key = jax.random.fold_in(jax.random.key(1), i)
        one, m1 = train_step(one, whole.batch(i), key)
        four, m4 = parallel.train_step(four, parallel.global_batch(split.batch(i)), key)
        assert not bool(m1["overflow"]) and not bool(m4["overflow"])
        losses.append((float(m1["loss"]), float(m4["loss"])))
        norms.append((float(m1["grad_norm"]), float(m4["grad_norm"])))
    leaves = zip(
        jax.tree_util.tree_leaves(one.params), jax.tree_util.tree_leaves(parallel.local(four.params)), strict=True
    )
    averages = list(
        zip(jax.tree_util.tree_leaves(one.ema), jax.tree_util.tree_leaves(parallel.local(four.ema)), strict=True)
    )
    report[name] = {
        "losses": losses,
        "grad_norms": norms,
        "max_param_difference": max(float(np.max(np.abs(np.asarray(a) - b))) for a, b in leaves),
        # The moving average: how far the two runs' averages part, and how far the 4-device one moved at all.
        "max_average_difference": max(float(np.max(np.abs(np.asarray(a) - b))) for a, b in averages),
        "average_moved": max(
            float(np.max(np.abs(b - np.asarray(c))))
            for (_, b), c in zip(averages, jax.tree_util.tree_leaves(start), strict=True)
        ),
        "step": int(four.step),
    }
try:
    parallel.check_batch_size(6)
except ValueError as error:
    report["indivisible"] = str(error)
print(json.dumps(report))
"""


def _python(code: str, *args, env=None, timeout=600) -> str:
    environment = dict(os.environ, **(env or {}))
    done = subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], env=environment, capture_output=True, text=True, timeout=timeout
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


def test_four_devices_train_like_one_device_with_the_same_global_batch(tiny_dataset):
    report = json.loads(_python(_FOUR_DEVICE_TRAINING, tiny_dataset, env=FOUR_DEVICES))
    assert report["devices"] == 4
    for name in ("plain", "fused", "unrolled", "position"):
        run = report[name]
        np.testing.assert_allclose(*np.asarray(run["losses"]).T, rtol=1e-5, err_msg=name)
        # The gradients are summed over the devices exactly once (a double sum would scale them by 4).
        np.testing.assert_allclose(*np.asarray(run["grad_norms"]).T, rtol=1e-5, err_msg=name)
        assert run["max_param_difference"] <= 20 * 1e-3, run["max_param_difference"]
        # An average that a device never updated would not have moved; one updated alike parts by far less.
        assert run["max_average_difference"] <= 0.1 * run["average_moved"], run
        assert run["step"] == 12
    assert "does not split over 4 devices" in report["indivisible"]


_SHARDED_ROLLOUT = r"""
import json, sys
import jax, numpy as np
from dispgns.arrays import stack_padded
from dispgns.data import load_dataset
from dispgns.model import ModelConfig, init_params
from dispgns.simulator import rollout_batch

splits = load_dataset(sys.argv[1])[1]
trajs = [t for split in splits.values() for t in split][:4]
assert len(trajs) == 4
mc = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, connectivity_radius=0.4)
norm = {"velocity_mean": np.zeros(2), "velocity_std": np.full(2, 0.05), "acceleration_mean": np.zeros(2),
        "acceleration_std": np.full(2, 0.002)}
params = init_params(jax.random.key(1), mc, norm)
position, radius, mask = stack_padded(trajs, frames=6)
mesh = jax.make_mesh((4,), ("data",))
plain = np.asarray(rollout_batch(params, position, radius, 12, model_config=mc, mask=mask, chunk_size=5))
sharded = np.asarray(rollout_batch(params, position, radius, 12, model_config=mc, mask=mask, chunk_size=5, mesh=mesh))
grown = np.asarray(rollout_batch(params, position, radius, 12, model_config=mc, mask=mask, chunk_size=5, mesh=mesh,
                                 capacity=16))
try:
    rollout_batch(params, position[:3], radius[:3], 2, model_config=mc, mask=mask[:3], mesh=mesh)
except ValueError as error:
    indivisible = str(error)
print(json.dumps({"sharded": float(np.max(np.abs(sharded - plain) * mask[:, None, :, None])),
                  "grown": float(np.max(np.abs(grown - plain) * mask[:, None, :, None])),
                  "indivisible": indivisible}))
"""


def test_rollouts_spread_over_four_devices_equal_one_device(tiny_dataset):
    report = json.loads(_python(_SHARDED_ROLLOUT, tiny_dataset, env=FOUR_DEVICES))
    assert report["sharded"] <= 1e-6 and report["grown"] <= 1e-6, report
    assert "do not split over the mesh's 4 devices" in report["indivisible"]


# ----------------------------------------------------------------------------- two processes


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


# A global batch of 2, as the default `cpu` configuration's: each of two processes holds one example of a batch
# split over two devices (the case docs/distributed.md shows).
CONFIG = """model:
  latent_size: 16
  hidden_size: 16
  message_passing_steps: 2
train:
  batch_size: 2
  learning_rate: 1.0e-3
  num_steps: 16
  log_every: 4
  validate_every: 8
  checkpoint_every: 8
  validation_examples: 8
  validation_trajectories: 2
  validation_rollout_frames: 8
"""


def _train(data, out, config, *extra, processes=1, port=None):
    """``dispgns train`` in ``processes`` local processes (one CPU device each); returns the Popen objects."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    base = [sys.executable, "-m", "dispgns", "train", "--data", str(data), "--out", str(out)]
    base += ["--config", str(config), "--no-progress", *extra]
    if processes == 1:
        return [subprocess.Popen(base, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)]
    address = f"127.0.0.1:{port or _free_port()}"
    return [
        subprocess.Popen(
            base
            + ["--distributed", "--coordinator", address, "--num-processes", str(processes), "--process-id", str(i)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(processes)
    ]


def _finish(runs, timeout=900):
    for run in runs:
        _, err = run.communicate(timeout=timeout)
        assert run.returncode == 0, err[-3000:]


def _params(run_dir):
    params, _, _ = load_model(Path(run_dir) / "model")
    return jax.tree_util.tree_leaves(params)


@pytest.fixture(scope="module")
def two_process_run(tiny_dataset, tmp_path_factory):
    """The same run in one process and in two processes (same global batch): their directories."""
    where = tmp_path_factory.mktemp("distributed")
    config = where / "config.yaml"
    config.write_text(CONFIG)
    runs = _train(tiny_dataset, where / "one", config) + _train(tiny_dataset, where / "two", config, processes=2)
    _finish(runs)
    return where, config


def test_two_processes_train_like_one_process(two_process_run):
    where, _ = two_process_run
    for a, b in zip(_params(where / "one"), _params(where / "two")):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)
    one = [json.loads(line) for line in (where / "one" / "log.jsonl").read_text().splitlines()]
    two = [json.loads(line) for line in (where / "two" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in one] == [r["step"] for r in two]  # one log, written by process 0 only
    for r1, r2 in zip(one, two):
        for name in ("loss", "grad_norm", "valid_one_step_loss", "valid_rollout_mse"):
            if name in r1:
                np.testing.assert_allclose(r1[name], r2[name], rtol=1e-4, err_msg=name)


@pytest.mark.slow
def test_a_killed_two_process_run_resumes_exactly(tiny_dataset, two_process_run):
    where, config = two_process_run
    out = where / "killed"
    runs = _train(tiny_dataset, out, config, processes=2)
    deadline = time.time() + 900
    while not (out / "checkpoints" / "8").is_dir():
        assert time.time() < deadline and all(run.poll() is None for run in runs), "no checkpoint at step 8"
        time.sleep(0.5)
    time.sleep(1.0)  # the checkpoint's files are renamed into place; the run goes on past it
    for run in runs:
        run.send_signal(signal.SIGKILL)
        run.communicate()
    _finish(_train(tiny_dataset, out, config, "--resume", processes=2))
    for a, b in zip(_params(where / "two"), _params(out)):
        np.testing.assert_array_equal(a, b)
