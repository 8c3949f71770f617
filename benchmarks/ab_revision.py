"""In-process A/B of this checkout against an earlier git revision: physics step, training step, rollout step.

The machine's speed drifts by 15-30 % within minutes, so two runs of a
benchmark minutes apart cannot show a change of a few per cent. This script
imports both versions into one process (the old one as the package
``dispgns_old``, copied from ``git show REV:src/dispgns``) and times the same
work with each in alternating rounds:

- ``physics``: ``simulate`` of one paper-size trajectory (N = 220, all pairs),
  per Euler step;
- ``train``: the paper network's training step on 2 examples of ~220
  particles (the inputs of ``benchmarks/gnn.py``), both given the same graph
  capacity and edge budget;
- ``rollout``: one rollout step of the trained paper network
  (``benchmarks/data/paper_network``), timed over a chunk of steps.

Each version runs as its own command line runs it: the old revision with what
its ``import dispgns`` switched on, this checkout with dispgns.tuning's
settings (the fused kernels, the XLA options and the host allocator, which is
process-wide and so shared). Prints one JSON line: medians per version and
the per-round ratios new / old (median and 25th-75th percentiles).

    python benchmarks/ab_revision.py --old 249a177 [--rounds 15]
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from dispgns import tuning  # the package imports lazily: nothing of JAX has started yet

tuning.tune_host_allocator()  # first, before jax-md's import starts JAX's CPU backend

import jax
import jax.numpy as jnp
import numpy as np
from gnn import PAPER_NETWORK, machine_info, seconds, trajectories

import dispgns
from dispgns.simulator import fit_capacity, rollout_scan
from dispgns.training import BatchStream, TrainConfig, compute_normalization, create_train_state, train_step
from dispgns.training.checkpoint import load_model

ROOT = Path(__file__).resolve().parents[1]


def import_revision(revision: str, where: Path):
    """``src/dispgns`` of ``revision`` as the importable package ``dispgns_old``."""
    files = subprocess.run(
        ["git", "ls-tree", "-r", "--name-only", revision, "src/dispgns"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    for name in files:
        data = subprocess.run(["git", "show", f"{revision}:{name}"], cwd=ROOT, capture_output=True, check=True).stdout
        target = where / "dispgns_old" / Path(name).relative_to("src/dispgns")
        target.parent.mkdir(parents=True, exist_ok=True)
        if name.endswith(".py"):
            text = re.sub(r"\bdispgns(?=[.\s]|$)", "dispgns_old", data.decode())
            target.write_text(text)
        else:
            target.write_bytes(data)
    sys.path.insert(0, str(where))
    return importlib.import_module("dispgns_old")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--old", required=True, help="the git revision to compare with")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--rollout-steps", type=int, default=20)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        old = import_revision(args.old, Path(tmp))
        report = run(old, args)
    print(json.dumps(report))


def run(old, args) -> dict:
    old_physics = importlib.import_module("dispgns_old.physics")
    old_training = importlib.import_module("dispgns_old.training")
    old_examples = importlib.import_module("dispgns_old.data.examples")
    old_graph = importlib.import_module("dispgns_old.graph")
    old_model = importlib.import_module("dispgns_old.model")
    old_simulator = importlib.import_module("dispgns_old.simulator")

    work = {}
    # Physics: one trajectory of 220 particles, 20 frames of 15 Euler steps.
    config = dispgns.PhysicsConfig()
    state = dispgns.sample_initial_state(
        jax.random.key(0), [r * 1e-3 for r in (2.25, 3.25, 3.75, 4.75)], config, n_particles=220, start_height=-0.025
    )
    frames, options = 21, tuning.physics_compiler_options()
    work["physics"] = (
        lambda: old_physics.simulate(
            state.position, state.velocity, state.radius, old_physics.PhysicsConfig(), n_frames=frames
        ),
        lambda: dispgns.simulate(
            state.position, state.velocity, state.radius, config, n_frames=frames, compiler_options=options
        ),
        (frames - 1) * 15,
    )

    # Training step: the paper network on the batch of benchmarks/gnn.py, same capacity and budget for both.
    trajs = trajectories(220, 110)
    new_config = tuning.tuned_model_config(dispgns.ModelConfig())
    net_options = tuning.network_compiler_options(new_config)
    norm = compute_normalization(trajs, noise_std=TrainConfig().noise_std)
    new_state = create_train_state(jax.random.key(0), new_config, TrainConfig(), norm)
    old_state = old_training.create_train_state(
        jax.random.key(0), old_model.ModelConfig(), old_training.TrainConfig(), norm
    )
    stream = BatchStream(trajs, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=0)
    late = np.flatnonzero(stream.index.start >= stream.index.start.max() - 4)
    new_batch = stream.make_batch([late[0], late[-1]])
    old_batch = old_examples.Batch(
        position=new_batch.position,
        radius=new_batch.radius,
        mask=new_batch.mask,
        example=new_batch.example,
        capacity=old_graph.GraphCapacity(new_batch.capacity.edges, new_batch.capacity.cell),
        edge_budget=new_batch.edge_budget,
    )
    key = jax.random.key(0)
    new_step = tuning.jitted(train_step, net_options)
    work["train"] = (
        lambda: old_training.train_step(old_state, old_batch, key),
        lambda: new_step(new_state, new_batch, key),
        1,
    )

    # Rollout step: the trained paper network (untrained weights if the fixture is missing), same capacity.
    if (PAPER_NETWORK / "model.json").is_file():
        params, trained, _ = load_model(PAPER_NETWORK)
    else:
        params, trained = new_state.params, dispgns.ModelConfig()
    traj = trajs[0]
    start = traj.position.shape[0] - 6
    window, radius = jnp.asarray(traj.position[start - 100 : start - 94]), jnp.asarray(traj.radius)
    mask = jnp.ones(radius.shape, bool)
    capacity = fit_capacity(traj.position[start - 100 :], trained)
    old_capacity = old_graph.GraphCapacity(capacity.edges, capacity.cell)
    old_rollout_config = old_model.ModelConfig.from_dict({k: v for k, v in trained.to_dict().items() if k != "kernels"})
    steps = args.rollout_steps
    scan = tuning.jitted(rollout_scan, net_options, static_argnames=("n_steps", "model_config", "capacity"))
    tuned_trained = tuning.tuned_model_config(trained)
    work["rollout"] = (
        lambda: old_simulator._rollout_chunk(
            params,
            window,
            radius,
            mask,
            jnp.int32(steps),
            length=steps,
            capacity=old_capacity,
            model_config=old_rollout_config,
        ),
        lambda: scan(params, window, radius, n_steps=steps, model_config=tuned_trained, capacity=capacity, mask=mask),
        steps,
    )

    # Same results first (to rounding), then the alternating rounds.
    np.testing.assert_allclose(np.asarray(work["physics"][0]()), np.asarray(work["physics"][1]()), rtol=0, atol=1e-6)
    old_loss = float(work["train"][0]()[1]["loss"])
    new_loss = float(work["train"][1]()[1]["loss"])
    np.testing.assert_allclose(new_loss, old_loss, rtol=1e-5)
    np.testing.assert_allclose(
        np.asarray(work["rollout"][0]()[1][:steps]), np.asarray(work["rollout"][1]()[0]), rtol=0, atol=1e-4
    )
    times = {name: ([], []) for name in work}
    for r in range(args.rounds):
        for name, (old_fn, new_fn, units) in work.items():
            pair = [(0, old_fn), (1, new_fn)] if r % 2 == 0 else [(1, new_fn), (0, old_fn)]
            for which, fn in pair:
                times[name][which].append(seconds(fn) / units)
    report = {"benchmark": "ab_revision", "old": args.old, "rounds": args.rounds, "machine": machine_info()}
    for name, (old_times, new_times) in times.items():
        ratio = np.asarray(new_times) / np.asarray(old_times)
        report[f"{name}_ms_old"] = 1e3 * float(np.median(old_times))
        report[f"{name}_ms_new"] = 1e3 * float(np.median(new_times))
        report[f"{name}_new_over_old"] = [round(float(q), 3) for q in np.quantile(ratio, [0.5, 0.25, 0.75])]
    report["same_results"] = True
    return report


if __name__ == "__main__":
    main()
