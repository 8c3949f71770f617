"""Speed of the ground-truth simulator; prints JSON (the last line is the summary).

Measures, after compilation and as the median of several runs:
- ``euler_step_ms``: one paper-size trajectory (N = 220, float32, all pairs,
  as the paper) per Euler step, against the authors' NumPy generator
  (~10.8 ms per step at N = 220 on the 2-core reference machine);
- ``batch_step_ms_per_trajectory``: the same with 40 trajectories vmapped;
- ``paper_dataset_s``: wall clock of ``dispgns generate --preset paper``
  (40 trajectories x 7500 steps, compilation included);
- ``particle_step_ns``: ns per particle per Euler step with a finite cut-off
  at N = 2,000, 20,000 and 100,000, at the area fraction of the paper's
  settled bed, and the implied Euler steps per second.

The physics runs with dispgns.tuning's settings, as the command line does
(the host allocator, ``physics_compiler_options()``); ``--no-tuning``
measures what a plain ``import dispgns`` gets.

Usage: python benchmarks/simulate.py [--quick] [--skip-dataset] [--no-tuning]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _machine import cpu_model

from dispgns import tuning  # the package imports lazily: nothing of JAX has started yet

# First, before jax-md's import starts JAX's CPU backend: the host allocator (``--no-tuning``: none).
TUNED = "--no-tuning" not in sys.argv[1:]
if TUNED:
    tuning.tune_host_allocator()

from dispgns import PhysicsConfig, sample_initial_state, simulate, simulate_batch

# The physics' XLA options (set in main(); {} with --no-tuning).
OPTIONS: dict = {}

AUTHORS_NUMPY_STEP_MS = 10.8  # measured on this 2-core machine, N = 220
PAPER_RADII = np.arange(2.0, 5.01, 0.5) * 1e-3
UNSEEN_RADII = np.array([2.25, 3.25, 3.75, 4.75]) * 1e-3
REFERENCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "sedimentation.npz"


def machine_info() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "cpu": cpu_model(),
        "host_allocator_tuned": tuning.host_allocator_tuned(),
        "compiler_options": OPTIONS,
    }


def median_seconds(run, repeats: int) -> float:
    run()  # compile and warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def paper_state(n: int, seed: int = 0):
    return sample_initial_state(
        jax.random.PRNGKey(seed), UNSEEN_RADII, PhysicsConfig(), n_particles=n, start_height=-0.025, max_rounds=256
    )


def euler_step_ms(repeats: int, frames: int) -> float:
    state = paper_state(220)
    config = PhysicsConfig()

    def run():
        simulate(
            state.position, state.velocity, state.radius, config, n_frames=frames + 1, compiler_options=OPTIONS
        ).block_until_ready()

    return 1e3 * median_seconds(run, repeats) / (frames * 15)


def batch_step_ms(repeats: int, frames: int, batch: int = 40) -> float:
    states = [paper_state(220, seed) for seed in range(batch)]
    x = jnp.stack([s.position for s in states])
    v = jnp.stack([s.velocity for s in states])
    a = jnp.stack([s.radius for s in states])
    mask = jnp.ones(a.shape, bool)
    config = PhysicsConfig()

    def run():
        simulate_batch(x, v, a, mask, config, n_frames=frames + 1, compiler_options=OPTIONS).block_until_ready()

    return 1e3 * median_seconds(run, repeats) / (frames * 15 * batch)


def settled_bed_area_fraction() -> float:
    """Area fraction of the bed at the end of the reference sedimentation run."""
    data = np.load(REFERENCE)
    y, a, half = data["frames"][-1][:, 1], data["radius"], float(data["L"])
    top = np.quantile(y + a, 0.95)
    return float(np.sum(np.pi * a**2) / (2 * half * (top + half)))


def bed_state(n: int, area_fraction: float, seed: int = 0):
    """N particles on a jittered hexagonal lattice filling a square box at the bed's area fraction.

    Returns positions (m), radii (m) and the box half-size L (m) for this N.
    """
    rng = np.random.default_rng(seed)
    radius = rng.choice(PAPER_RADII, size=n)
    spacing = np.sqrt(np.mean(np.pi * radius**2) / area_fraction / (np.sqrt(3) / 2))
    spacing = max(spacing, 2 * PAPER_RADII.max() * 1.02)  # never overlap on the lattice
    per_row = int(np.ceil(np.sqrt(n / (np.sqrt(3) / 2))))
    rows = int(np.ceil(n / per_row))
    ix, iy = np.meshgrid(np.arange(per_row), np.arange(rows))
    x = (ix + 0.5 * (iy % 2)) * spacing
    y = iy * spacing * np.sqrt(3) / 2
    points = np.stack([x.ravel(), y.ravel()], -1)[:n]
    half = 0.5 * max(points[:, 0].max(), points[:, 1].max()) + spacing
    points = points - points.max(0) / 2
    jitter = rng.uniform(-1, 1, points.shape) * 0.5 * (spacing - 2 * PAPER_RADII.max())
    return (points + jitter).astype(np.float32), radius.astype(np.float32), float(half)


def particle_step_ns(sizes, repeats: int, frames: int) -> dict:
    fraction = settled_bed_area_fraction()
    results = {}
    for n in sizes:
        position, radius, half = bed_state(n, fraction)
        config = PhysicsConfig(box_half_size=half, cutoff=2 * 2 * float(PAPER_RADII.max()))
        velocity = np.zeros_like(position)

        def run(position=position, velocity=velocity, radius=radius, config=config):
            simulate(
                position, velocity, radius, config, n_frames=frames + 1, save_every=15, compiler_options=OPTIONS
            ).block_until_ready()

        seconds = median_seconds(run, repeats)
        results[n] = {
            "ns": 1e9 * seconds / (frames * 15 * n),
            "steps_per_s": frames * 15 / seconds,
            "box_half_size_m": half,
        }
    return results


def paper_dataset_seconds() -> float | None:
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            "-m",
            "dispgns",
            *(["--no-tuning"] if not OPTIONS else []),
            "generate",
            "--preset",
            "paper",
            "--seed",
            "0",
            "--out",
            str(Path(tmp) / "paper"),
        ]
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        elapsed = time.perf_counter() - start
    if done.returncode != 0:
        print(json.dumps({"paper_dataset_error": done.stderr.strip()[-500:]}))
        return None
    return elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and sizes (smoke run)")
    parser.add_argument("--skip-dataset", action="store_true", help="do not time the paper dataset generation")
    parser.add_argument("--no-tuning", action="store_true", help="plain import dispgns: no opt-in speed settings")
    args = parser.parse_args()
    global OPTIONS
    if TUNED:
        OPTIONS = tuning.physics_compiler_options()
    repeats = 3 if args.quick else 5
    sizes = [2000, 20000] if args.quick else [2000, 20000, 100000]

    summary = {"machine": machine_info()}
    summary["euler_step_ms"] = euler_step_ms(repeats, frames=20 if args.quick else 100)
    summary["speedup_vs_authors_numpy"] = AUTHORS_NUMPY_STEP_MS / summary["euler_step_ms"]
    print(json.dumps({"euler_step_ms": summary["euler_step_ms"]}))
    summary["batch_step_ms_per_trajectory"] = batch_step_ms(repeats, frames=10 if args.quick else 40)
    print(json.dumps({"batch_step_ms_per_trajectory": summary["batch_step_ms_per_trajectory"]}))
    scaling = particle_step_ns(sizes, repeats=max(2, repeats - 2), frames=4 if args.quick else 10)
    summary["particle_step_ns"] = {str(n): round(r["ns"], 2) for n, r in scaling.items()}
    summary["euler_steps_per_s"] = {str(n): round(r["steps_per_s"], 1) for n, r in scaling.items()}
    per_particle = [r["ns"] for r in scaling.values()]
    summary["particle_step_ns_max_over_min"] = max(per_particle) / min(per_particle)
    print(json.dumps({"particle_step_ns": summary["particle_step_ns"]}))
    if not args.skip_dataset:
        summary["paper_dataset_s"] = paper_dataset_seconds()
    summary["targets"] = {
        "euler_step_ms": 0.1,
        "paper_dataset_s": 60,
        "particle_step_ns_max_over_min": 2.0,
        "euler_steps_per_s_at_100000": 20,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
