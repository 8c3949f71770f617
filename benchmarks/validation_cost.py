"""What the host conveniences' input checks cost, against the work they guard.

For a paper-size state (about 200 disks) and one with ~10x more, in one process: the median time of
``dispgns.validation.check_particles`` (every check the physics runs, overlaps included), and its ratio to one
compiled learned step of the shipped model (``predict_step``) and to a 50-frame ``simulate`` (after compilation).
Prints one JSON object per size and a summary line.

    python benchmarks/validation_cost.py            # --quick: fewer repeats
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
from dispgns.validation import check_particles


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _measure(radius_m, params, model_config, config, repeats) -> dict:
    half = config.box_half_size
    state = dispgns.sample_initial_state(jax.random.key(0), [radius_m * 0.6, radius_m], config)
    x, v, a = (np.asarray(t) for t in (state.position, state.velocity, state.radius))
    bounds = ((-half, half),) * 2

    def check():
        check_particles(x, a, velocity=v, bounds=bounds, box="the box", position_name="x0")

    window = np.repeat((x / half)[None], model_config.input_sequence_length, axis=0).astype(np.float32)
    capacity = dispgns.fit_capacity(window[-1], model_config, margin=0.2)
    step = jax.jit(lambda w: dispgns.predict_step(params, w, a / half, model_config=model_config, capacity=capacity))
    physics = lambda: dispgns.simulate(x, v, a, config, n_frames=51, save_every=1)  # noqa: E731
    step(window)
    physics()
    # Interleaved rounds: the machine's speed drifts, ratios inside one round are what count.
    check_s, step_s, physics_s = [], [], []
    for _ in range(3):
        check_s.append(_median_s(check, repeats))
        step_s.append(_median_s(lambda: step(window), repeats))
        physics_s.append(_median_s(physics, max(3, repeats // 3)))
    row = {
        "n_particles": int(x.shape[0]),
        "check_ms": 1e3 * statistics.median(check_s),
        "learned_step_ms": 1e3 * statistics.median(step_s),
        "simulate_50_frames_ms": 1e3 * statistics.median(physics_s),
    }
    row["check_over_learned_step"] = row["check_ms"] / row["learned_step_ms"]
    row["check_over_simulate_50_frames"] = row["check_ms"] / row["simulate_50_frames_ms"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    repeats = 5 if args.quick else 15
    config = dispgns.PhysicsConfig()
    params, model_config, _ = dispgns.load_pretrained()
    # The network's own step, as the dated tables were measured (the default model ships with the mirror
    # average on, which doubles a step's network work).
    model_config = dataclasses.replace(model_config, symmetrize=False)
    results = []
    for radius_m in (4.75e-3, 1.5e-3):  # a paper-size state and one with ~10x more particles
        row = _measure(radius_m, params, model_config, config, repeats)
        print(json.dumps(row), flush=True)
        results.append(row)
    print(
        json.dumps(
            {
                "benchmark": "validation_cost",
                "cpu": cpu_model(),
                "cores": os.cpu_count(),
                "load_average": os.getloadavg(),
                "jax": jax.__version__,
                "sizes": results,
            }
        )
    )


if __name__ == "__main__":
    main()
