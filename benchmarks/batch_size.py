"""Training throughput against batch size: examples per second of the shipped model's training step.

Is the recipe's batch of 2 the right one for a CPU? A larger batch costs more
per step but may cost less per example (wider matmuls, one optimizer update per
batch). This times the training step of ``sedimentation-2d``'s network (latent
64, hidden 64, 5 blocks) with its fine-tuning recipe (track J of
``experiments/accuracy``: 2-step pushforward, weight average; the mirror
augmentation is host-side, not timed) on batches of the densest windows of paper-protocol
trajectories (220 particles, as ``benchmarks/gnn.py``), for each batch size,
with dispgns.tuning's settings as the command line uses them.

    taskset -c 0 python benchmarks/batch_size.py             # one core
    python benchmarks/batch_size.py --sizes 1 2 4 8 16       # all cores

The sizes are timed in interleaved rounds (the median over rounds of each
round's median of ``--repeats`` steps, after one untimed warm-up step). Only the
compiled step is timed: the host's share of a step (drawing the batch, the
loop's checks and logging) is not. Prints a line per batch size and ends with one JSON line: per
size the median wall and process-CPU seconds of a step (and the rounds' range),
examples per wall second and per CPU second, and their ratios to batch 2's
(``examples_per_cpu_s_over_batch_2``: the recipe's batch is the comparison).
Throughput only: what a larger batch does to accuracy per example is not
measured here.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import sys

from dispgns import tuning  # nothing of JAX has started yet

if "--no-tuning" not in sys.argv[1:] and __name__ == "__main__":
    tuning.tune_host_allocator()

import jax
import numpy as np
from gnn import machine_info, timed, trajectories  # benchmarks/gnn.py, beside this script

from dispgns.pretrained import load_pretrained
from dispgns.training import TrainConfig, compute_normalization, create_train_state, train_step
from dispgns.training.batches import BatchStream


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4, 8], help="batch sizes to time")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds over the sizes (median)")
    parser.add_argument("--repeats", type=int, default=3, help="timed steps per size and round (median)")
    parser.add_argument("--frames", type=int, default=300, help="frames simulated per trajectory")
    parser.add_argument("--no-tuning", action="store_true", help="plain import dispgns: no opt-in speed settings")
    args = parser.parse_args()
    tuned = not args.no_tuning

    _, shipped_config, _ = load_pretrained()  # sedimentation-2d: the network the recipe fine-tunes
    # The network is trained on single evaluations (symmetrize averages two at rollout time only).
    model_config = dataclasses.replace(shipped_config, symmetrize=False, keep_inside_box=False)
    if tuned:
        model_config = tuning.tuned_model_config(model_config)
    options = tuning.network_compiler_options(model_config) if tuned else {}
    # Track J's recipe (experiments/accuracy/finetune_ema_fast.yaml) with the batch size varied.
    recipe = TrainConfig(noise_std=1e-4, pushforward_steps=2, mirror_augmentation=True, ema_decay=0.9998)
    # Each trajectory gives ~5 windows among the densest (its last frames): enough trajectories for the largest
    # batch to be filled with distinct windows.
    trajs = trajectories(220, args.frames, seeds=tuple(range(max(2, (max(args.sizes) + 4) // 5))))
    norm = compute_normalization(trajs, noise_std=recipe.noise_std)
    step = tuning.jitted(train_step, options) if tuned else jax.jit(train_step)

    # Compile every size first, then time them in interleaved rounds: this machine's speed drifts within
    # minutes (benchmarks/README.md), and sizes timed one after the other would measure the drift.
    compiled, graphs = {}, {}
    for size in args.sizes:
        train_config = dataclasses.replace(recipe, batch_size=size)
        state = create_train_state(jax.random.key(0), model_config, train_config, norm)
        stream = BatchStream.for_training(trajs, model_config, train_config)
        # The densest windows (most neighbour pairs), as many as the batch needs. make_batch applies no mirror
        # flips (BatchStream does them on the host when it draws batches): the compiled step is the same program.
        densest = np.argsort(-stream.pairs, kind="stable")[:size]
        batch = stream.make_batch(densest)
        key = jax.random.key(0)
        compiled[size] = functools.partial(step.lower(state, batch, key).compile(), state, batch, key)
        _, metrics = compiled[size]()
        if bool(metrics["overflow"]):  # a step that drops its update is not the step a run takes
            raise SystemExit(f"batch {size}: the graph overflowed its capacity ({batch.capacity})")
        # Padding differs between sizes (budgets are rounded up a ladder): the edge slots against the real pairs.
        slots = batch.edge_budget or size * (batch.capacity.edges + batch.node_budget)  # None: per example
        graphs[size] = {"edge_slots": int(slots), "pairs": int(stream.pairs[densest].sum())}
    rounds = {size: [] for size in args.sizes}
    for _ in range(args.rounds):
        for size in args.sizes:
            rounds[size].append(timed(compiled[size], args.repeats))

    results = {}
    for size, times in rounds.items():
        walls, cpus = np.array(times).T
        wall, cpu = float(np.median(walls)), float(np.median(cpus))
        results[str(size)] = {
            "step_wall_ms": 1e3 * wall,
            "step_wall_ms_range": [1e3 * float(walls.min()), 1e3 * float(walls.max())],
            "step_cpu_ms": 1e3 * cpu,
            "examples_per_wall_s": size / wall,
            "examples_per_cpu_s": size / cpu,
            **graphs[size],
        }
        print(
            f"batch {size:3d}: {1e3 * wall:7.1f} ms/step wall, {1e3 * cpu:7.1f} ms CPU, "
            f"{size / wall:6.1f} examples/s wall, {size / cpu:6.1f} per CPU-s",
            flush=True,
        )
    if "2" in results:
        for entry in results.values():
            entry["examples_per_cpu_s_over_batch_2"] = entry["examples_per_cpu_s"] / results["2"]["examples_per_cpu_s"]
            entry["examples_per_wall_s_over_batch_2"] = (
                entry["examples_per_wall_s"] / results["2"]["examples_per_wall_s"]
            )
    report = {
        "benchmark": "batch_size",
        "comparison": "examples per second against the recipe's batch of 2",
        "model": {k: getattr(model_config, k) for k in ("latent_size", "hidden_size", "message_passing_steps")},
        "recipe": {k: getattr(recipe, k) for k in ("pushforward_steps", "mirror_augmentation", "ema_decay")},
        "particles": 220,
        "rounds": args.rounds,
        "repeats": args.repeats,
        "tuned": tuned,
        "cpu_affinity": sorted(os.sched_getaffinity(0)),
        "results": results,
        "machine": machine_info(),
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
