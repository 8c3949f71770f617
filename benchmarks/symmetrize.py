"""What ``ModelConfig(symmetrize=True)`` costs: one learned 3-D step, plain and averaged over the floor symmetries.

A fresh trajectory of the ``paper3d`` protocol (spheres of the paper's training radii in the 8 cm cube), its
frames 34-39 as the input window; one compiled ``predict_step`` of a 3-D model of the shipped size (latent 64,
5 blocks: the shipped 3-D model, or ``--model``, or untrained weights where none ships: the cost does not depend on
them) with ``symmetrize`` off and on, timed in interleaved rounds (the machine's speed drifts; the ratio inside a
round is what counts). Prints one JSON object per round and a summary line.

    python benchmarks/symmetrize.py                 # --model PATH: a 3-D run or exported model; --quick
"""

import argparse
import dataclasses
import json
import os
import statistics
import time

import jax
import numpy as np
from _machine import cpu_model

import dispgns
from dispgns.data.generate import PAPER3D_HALF_SIZE_M, PAPER_TRAIN_RADII_M, paper3d_spec


def _model(path):
    from dispgns.pretrained import MODEL_3D, load_pretrained, shipped_models
    from dispgns.training.checkpoint import load_params

    if path:
        params, config, info = load_params(path)
        return params, config, info["source"]
    if MODEL_3D in shipped_models():
        params, config, _ = load_pretrained(MODEL_3D)
        return params, config, f"dispgns.pretrained:{MODEL_3D}"
    config = dispgns.ModelConfig(
        latent_size=64, hidden_size=64, message_passing_steps=5, dim=3, connectivity_radius=0.5
    )
    norm = {
        "velocity_mean": np.zeros(3),
        "velocity_std": np.ones(3),
        "acceleration_mean": np.zeros(3),
        "acceleration_std": np.ones(3),
    }
    return dispgns.init_params(jax.random.key(0), config, norm), config, "untrained (shipped 3-D size)"


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="a 3-D training run or exported model (default: shipped, else untrained)")
    parser.add_argument("--quick", action="store_true", help="fewer repeats and rounds")
    args = parser.parse_args()
    params, config, source = _model(args.model)
    spec = paper3d_spec()
    physics = spec.physics
    state = dispgns.sample_initial_state(jax.random.key(0), PAPER_TRAIN_RADII_M, physics, dim=3)
    frames = np.asarray(
        dispgns.simulate(state.position, state.velocity, state.radius, physics, n_frames=40, save_every=spec.save_every)
    )
    window = (frames[-6:] / PAPER3D_HALF_SIZE_M).astype(np.float32)
    radius = (np.asarray(state.radius) / PAPER3D_HALF_SIZE_M).astype(np.float32)
    capacity = dispgns.fit_capacity(window[-1], config, margin=0.2)
    steps, compile_s = {}, {}
    for name, symmetrize in (("plain", False), ("symmetrized", True)):
        c = dataclasses.replace(config, symmetrize=symmetrize)
        steps[name] = jax.jit(lambda w, c=c: dispgns.predict_step(params, w, radius, model_config=c, capacity=capacity))
        start = time.perf_counter()
        jax.block_until_ready(steps[name](window))
        compile_s[name] = time.perf_counter() - start
    repeats, rounds = (5, 3) if args.quick else (20, 5)
    ratios = []
    for k in range(rounds):
        plain = _median_s(lambda: steps["plain"](window), repeats)
        symmetric = _median_s(lambda: steps["symmetrized"](window), repeats)
        ratios.append(symmetric / plain)
        row = {"round": k, "plain_step_ms": 1e3 * plain, "symmetrized_step_ms": 1e3 * symmetric}
        print(json.dumps({**row, "ratio": symmetric / plain}), flush=True)
    summary = {
        "benchmark": "symmetrize",
        "model": source,
        "n_particles": int(radius.shape[0]),
        "graph_edges_capacity": int(capacity.edges),
        "first_call_s": compile_s,
        "symmetrized_over_plain_median": statistics.median(ratios),
        "symmetrized_over_plain_range": [min(ratios), max(ratios)],
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
        "jax": jax.__version__,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
