"""Cost at scale: physics and learned simulator at N = 10^3, 10^4, 10^5 in wide containers; prints JSON.

Each size runs in its own subprocess (so that its peak resident memory is its
own) in a container of the paper's height (0.2 m) and a width chosen for ``N``
disks of the paper's training radii, filled by :func:`dispgns.sample_initial_state`
with the paper's protocol:

- physics: ns per particle per Euler step (20 mm cut-off, cell lists, the
  settling suspension of the first frames), median of ``--repeats`` runs;
- learned simulator: ns per particle per predicted frame of the shipped model
  (:func:`dispgns.rollout`, the box's bounds given to the model, graphs from
  cell lists), median of ``--repeats`` runs, after compilation;
- ``surrogate_over_physics``: the learned simulator's cost per frame over the
  physics' cost of the 15 Euler steps a frame stands for (< 1: the surrogate
  is faster than the physics it replaces);
- ``peak_rss_gb``: the subprocess's peak resident memory (sampling, physics,
  rollout and compilation together).

One JSON line per size, then the summary (the last line) with the machine
(CPU model, cores, load average) and the spread of the per-particle costs
across sizes (``*_max_over_min``: linear cost means close to 1).

Usage: python benchmarks/scale.py [--sizes 1000 10000 100000] [--frames 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import subprocess
import sys
import time

import _machine

PAPER_RADII_M = [2.0e-3, 2.5e-3, 3.0e-3, 3.5e-3, 4.0e-3, 4.5e-3, 5.0e-3]
HEIGHT_M = 0.1  # the paper's half-height, also the length scale L
CUTOFF_M = 0.02
SEED = 0


def machine_info() -> dict:
    return _machine.machine_info(python=platform.python_version())


def one_size(n_target: int, frames: int, repeats: int) -> dict:
    """Measure one size in this process (called in a subprocess by main)."""
    import dataclasses

    import jax
    import numpy as np

    from dispgns import tuning

    tuning.tune_host_allocator()
    from dispgns import PhysicsConfig, rollout, sample_initial_state, simulate
    from dispgns.pretrained import load_pretrained

    # The protocol puts ~0.7 x (area / (2 a_max)^2) x (1.0-1.25 H) / (2 H) disks in the box.
    width = n_target * (2 * max(PAPER_RADII_M)) ** 2 / (0.7 * 1.125 * HEIGHT_M)
    config = PhysicsConfig(box_half_size=(width / 2, HEIGHT_M), cutoff=CUTOFF_M)
    start = time.perf_counter()
    state = sample_initial_state(jax.random.PRNGKey(SEED), PAPER_RADII_M, config)
    sample_s = time.perf_counter() - start
    x0, v0, a = (np.asarray(t) for t in (state.position, state.velocity, state.radius))
    n = x0.shape[0]
    params, model_config, _ = load_pretrained()
    # The network's own step, as the dated tables were measured (the default model ships with the mirror
    # average on, which doubles a step's network work).
    model_config = dataclasses.replace(model_config, symmetrize=False)
    c = model_config.input_sequence_length
    bounds = tuple((-h / HEIGHT_M, h / HEIGHT_M) for h in config.half_sizes(2))
    model_config = dataclasses.replace(model_config, bounds=bounds)
    compute_config = tuning.tuned_model_config(model_config)  # the CPU kernels, as the command line uses

    options = tuning.physics_compiler_options()

    def physics():
        return simulate(x0, v0, a, config, n_frames=max(frames + 1, c), save_every=15, compiler_options=options)

    truth = np.asarray(physics())  # also compiles
    times = []
    for _ in range(repeats):
        begin = time.perf_counter()
        physics().block_until_ready()
        times.append(time.perf_counter() - begin)
    physics_s = statistics.median(times)

    inputs = (truth[:c] / HEIGHT_M).astype(np.float32)
    radius = (a / HEIGHT_M).astype(np.float32)
    network = tuning.network_compiler_options(compute_config)

    def learned():
        return rollout(params, inputs, radius, frames, model_config=compute_config, compiler_options=network)

    predicted = np.asarray(learned())
    times = []
    for _ in range(repeats):
        begin = time.perf_counter()
        np.asarray(learned())
        times.append(time.perf_counter() - begin)
    learned_s = statistics.median(times)
    physics_ns = 1e9 * physics_s / ((max(frames + 1, c) - 1) * 15 * n)
    learned_ns = 1e9 * learned_s / (frames * n)
    return {
        "n_particles": n,
        "box_half_size_m": list(config.half_sizes(2)),
        "sample_initial_state_s": sample_s,
        "physics_ns_per_particle_step": physics_ns,
        "learned_ns_per_particle_frame": learned_ns,
        "surrogate_over_physics": learned_ns / (15 * physics_ns),
        "learned_finite": bool(np.all(np.isfinite(predicted))),
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "frames": frames,
        "repeats": repeats,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--frames", type=int, default=20, help="frames per timed run (15 Euler steps each)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(one_size(args.one, args.frames, args.repeats)))
        return
    results = []
    for n in args.sizes:
        command = [sys.executable, __file__, "--one", str(n), "--frames", str(args.frames)]
        command += ["--repeats", str(args.repeats)]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            print(json.dumps({"n_target": n, "error": done.stderr.strip()[-800:]}), flush=True)
            continue
        result = json.loads(done.stdout.strip().splitlines()[-1])
        results.append(result)
        print(json.dumps(result), flush=True)
    summary = {"machine": machine_info(), "seed": SEED, "cutoff_m": CUTOFF_M, "sizes": results}
    for key in ("physics_ns_per_particle_step", "learned_ns_per_particle_frame"):
        values = [r[key] for r in results]
        if values:
            summary[f"{key}_max_over_min"] = max(values) / min(values)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
