"""What dispgns.tuning's opt-in settings are worth: tuned vs plain, in alternating rounds of one process.

A plain ``import dispgns`` computes with the spec's kernels (``ModelConfig.kernels
= "plain"``) and XLA's default options; the command line, the demo and the
benchmarks opt in to the fused kernels, the XLA options of
``network_compiler_options``/``physics_compiler_options`` and the host
allocator. Kernels and options can be switched within one process, so they
are timed in alternating rounds: the physics step (N = 220), the paper
network's training step and rollout step (the inputs of ``benchmarks/gnn.py``).
The host allocator is process-wide: run the script twice, with and without
``--no-allocator``, and compare the two runs (its ``page_faults_per_train_step``
shows which one is which). Prints one JSON line; ratios are plain / tuned per
round (median, 25th and 75th percentiles).

    python benchmarks/tuning_cost.py [--rounds 10] [--no-allocator]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys

from dispgns import tuning  # the package imports lazily: nothing of JAX has started yet

ALLOCATOR = "--no-allocator" not in sys.argv[1:]
if ALLOCATOR:
    tuning.tune_host_allocator()  # first, before jax-md's import starts JAX's CPU backend

import jax
import jax.numpy as jnp
import numpy as np
from gnn import PAPER_NETWORK, machine_info, seconds, trajectories

import dispgns
from dispgns.simulator import fit_capacity, rollout_scan
from dispgns.training import BatchStream, TrainConfig, compute_normalization, create_train_state, train_step
from dispgns.training.checkpoint import load_model


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--no-allocator", action="store_true", help="leave glibc's allocator as it is")
    parser.add_argument("--rollout-steps", type=int, default=20)
    args = parser.parse_args()

    config = dispgns.PhysicsConfig()
    state = dispgns.sample_initial_state(
        jax.random.key(0), [r * 1e-3 for r in (2.25, 3.25, 3.75, 4.75)], config, n_particles=220, start_height=-0.025
    )
    physics = {
        name: lambda options=options: dispgns.simulate(
            state.position, state.velocity, state.radius, config, n_frames=21, compiler_options=options
        )
        for name, options in (("plain", {}), ("tuned", tuning.physics_compiler_options()))
    }

    trajs = trajectories(220, 110)
    norm = compute_normalization(trajs, noise_std=TrainConfig().noise_std)
    stream = BatchStream(trajs, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=0)
    late = np.flatnonzero(stream.index.start >= stream.index.start.max() - 4)
    batch, key = stream.make_batch([late[0], late[-1]]), jax.random.key(0)
    if (PAPER_NETWORK / "model.json").is_file():
        params, trained, _ = load_model(PAPER_NETWORK)
    else:
        params, trained = None, dispgns.ModelConfig()
    traj = trajs[0]
    start = traj.position.shape[0] - 6
    window, radius = jnp.asarray(traj.position[start - 100 : start - 94]), jnp.asarray(traj.radius)
    capacity = fit_capacity(traj.position[start - 100 :], trained)
    train, rollout = {}, {}
    for name in ("plain", "tuned"):
        model_config = tuning.tuned_model_config(trained) if name == "tuned" else trained
        options = tuning.network_compiler_options(model_config) if name == "tuned" else {}
        train_state = create_train_state(jax.random.key(0), model_config, TrainConfig(), norm)
        step = tuning.jitted(train_step, options)
        train[name] = lambda step=step, train_state=train_state: step(train_state, batch, key)
        scan = tuning.jitted(rollout_scan, options, static_argnames=("n_steps", "model_config", "capacity"))
        weights = train_state.params if params is None else params
        rollout[name] = lambda scan=scan, model_config=model_config, weights=weights: scan(
            weights, window, radius, n_steps=args.rollout_steps, model_config=model_config, capacity=capacity
        )

    work = {"physics": (physics, 20 * 15), "train": (train, 1), "rollout": (rollout, args.rollout_steps)}
    for fns, _ in work.values():
        for fn in fns.values():
            jax.block_until_ready(fn())  # compile
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    jax.block_until_ready(train["tuned"]())
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    times = {(kind, name): [] for kind in work for name in ("plain", "tuned")}
    for r in range(args.rounds):
        for kind, (fns, units) in work.items():
            for name in ("plain", "tuned") if r % 2 == 0 else ("tuned", "plain"):
                times[kind, name].append(seconds(fns[name]) / units)
    report = {
        "benchmark": "tuning_cost",
        "rounds": args.rounds,
        "host_allocator_tuned": tuning.host_allocator_tuned(),
        "page_faults_per_train_step": faults,
        "machine": machine_info(),
    }
    for kind in work:
        plain, tuned = np.asarray(times[kind, "plain"]), np.asarray(times[kind, "tuned"])
        report[f"{kind}_ms_plain"] = 1e3 * float(np.median(plain))
        report[f"{kind}_ms_tuned"] = 1e3 * float(np.median(tuned))
        report[f"{kind}_plain_over_tuned"] = [round(float(q), 3) for q in np.quantile(plain / tuned, [0.5, 0.25, 0.75])]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
