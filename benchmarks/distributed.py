"""Data-parallel training speed: steps and examples per second on 1, 2 and 4 devices and on two processes.

Each configuration runs in its own subprocess (the device count is fixed when
JAX starts): 1, 2 and 4 forced CPU devices in one process
(``XLA_FLAGS=--xla_force_host_platform_device_count=N``), and two processes
on 127.0.0.1 with one device each (``jax.distributed``, gloo). Every one
trains the shipped network's configuration (latent 64, 5 blocks) on the
inputs of ``benchmarks/gnn.py`` (220 particles per example) with the same
global batch, with dispgns.tuning's settings, and reports the median of the
timed steps after compilation.

Caveat: forced CPU devices share this machine's cores, so on a 2-core CPU
more devices cannot be faster; the figure that matters comes from a machine
with one accelerator per device, where the script runs unchanged (it then
uses the real devices: ``--real-devices``).

    python benchmarks/distributed.py [--batch-size 4] [--steps 10]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def worker(args) -> None:
    """One configuration: time ``args.steps`` data-parallel steps; process 0 prints a JSON line."""
    from dispgns import tuning

    tuning.tune_host_allocator()  # first, as the command line does
    import jax

    if args.processes > 1:
        jax.distributed.initialize(f"127.0.0.1:{args.port}", args.processes, args.process_id)
    sys.path.insert(0, str(HERE))
    import numpy as np
    from gnn import machine_info, trajectories

    from dispgns import tuning
    from dispgns.model import ModelConfig
    from dispgns.training import BatchStream, TrainConfig, compute_normalization, create_train_state
    from dispgns.training.distributed import DataParallel

    trajs = trajectories(220, 60)
    model_config = tuning.tuned_model_config(ModelConfig(latent_size=64, hidden_size=64, message_passing_steps=5))
    train_config = TrainConfig(batch_size=args.batch_size)
    options = tuning.network_compiler_options(model_config)
    state = create_train_state(
        jax.random.key(0), model_config, train_config, compute_normalization(trajs, noise_std=train_config.noise_std)
    )
    parallel = DataParallel()
    stream = BatchStream.for_training(trajs, model_config, train_config, shards=parallel.devices)
    state = parallel.replicate(state)
    step = parallel.step(options)
    part = parallel.local_examples(args.batch_size)
    batches = [parallel.global_batch(stream.batch(i, part)) for i in range(args.steps + 2)]
    times = []
    for i, batch in enumerate(batches):
        start = time.perf_counter()
        state, metrics = step(state, batch, jax.random.fold_in(jax.random.key(1), i))
        jax.block_until_ready(metrics["loss"])
        if i >= 2:  # after compilation and one warm step
            times.append(time.perf_counter() - start)
    if parallel.is_primary:
        seconds = float(np.median(times))
        print(
            json.dumps(
                {
                    "devices": parallel.devices,
                    "processes": jax.process_count(),
                    "step_ms": 1e3 * seconds,
                    "steps_per_s": 1.0 / seconds,
                    "examples_per_s": args.batch_size / seconds,
                    "machine": machine_info(),
                }
            )
        )


def run(devices: int, processes: int, args) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if not args.real_devices:
        env["JAX_PLATFORMS"] = "cpu"
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    command = [sys.executable, __file__, "--worker", "--batch-size", str(args.batch_size), "--steps", str(args.steps)]
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    runs = [
        subprocess.Popen(
            command + ["--processes", str(processes), "--process-id", str(i), "--port", str(port)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(processes)
    ]
    outputs = [run.communicate() for run in runs]
    for run, (_, err) in zip(runs, outputs):
        if run.returncode:
            raise SystemExit(f"{devices} devices x {processes} processes failed:\n{err[-2000:]}")
    return json.loads(outputs[0][0].strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch-size", type=int, default=4, help="global batch (a multiple of every device count)")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per configuration (median)")
    parser.add_argument("--real-devices", action="store_true", help="the machine's devices (GPUs), not forced CPU ones")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return
    results = {f"{d}_devices": run(d, 1, args) for d in (1, 2, 4)}
    results["2_processes"] = run(1, 2, args)
    base = results["1_devices"]["steps_per_s"]
    report = {
        "benchmark": "distributed",
        "batch_size": args.batch_size,
        "forced_cpu_devices": not args.real_devices,
        "machine": results["1_devices"].pop("machine"),
        **{name: {k: v for k, v in r.items() if k != "machine"} for name, r in results.items()},
        "speedup_over_one_device": {name: r["steps_per_s"] / base for name, r in results.items()},
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
