"""Speed of the learned simulator: training step, rollout step, FLOPs and achieved GFLOP/s.

Inputs of the size the paper's authors' code was timed on (~220 particles,
~2,400 edges per example including self-loops): the paper's initial-state
protocol with radii {2.25, 3.25, 3.75, 4.75} mm and 220 particles, simulated
for a while so the packing is realistic.

    python benchmarks/gnn.py            # float32 and bfloat16-matmul variants
    python benchmarks/gnn.py --quick    # float32 only, no full 494-step rollout

The rollouts run on trained weights (``benchmarks/data/paper_network``, see
``benchmarks/paper_network.py``; ``--rollout-model none``: untrained ones),
from frames 4-9 of the trajectory for the timed 50-step chunk (the ~2,200
pairs the authors timed) and from its first 6 frames for the full 494-step
rollout, in which the bed settles and the graph doubles (its sizes are
reported: ``rollout_494_pairs_max``/``_mean``, ordered pairs without
self-loops).

Prints a few human-readable lines and ends with one JSON line. Timings are
wall-clock medians after compilation; CPU time of the process is reported
too, because on a shared machine the wall time also measures the others.
``*_matmul_floor_ms`` is the time the step's dense-layer FLOPs would take at
the rate of a chain of 20 dependent edge-sized matmuls (the rollout's edge
slots x L x L, L the latent size; one jit) timed in alternation with the
rollout chunk: a lower bound for the step at the machine's speed of that
minute (``rollout_over_floor`` is the ratio). ``*_at_fma_peak`` and
``rollout_fraction_of_fma_peak*`` compare with the CPU's peak rate
(``benchmarks/cpu_peak.py``): no software can beat that time, and the
fraction needed for the 15 ms target is what the whole step, gathers and
LayerNorms included, would have to reach. ``page_faults_per_train_step``
shows whether :func:`dispgns.tuning.tune_host_allocator` is in effect (near 0) or
not (~125,000 for the paper network). ``edge_mlp_fraction_of_matmul`` compares
a stack of per-edge MLPs (forward + backward) with an edge-sized matmul timed
in alternation with it; ``edge_mlp_fraction_of_large_matmul`` with the
2048^2 matmul. Matmuls and MLP stacks are compiled with
:func:`dispgns.tuning.network_compiler_options` of their dtype, as the network is.

The network runs with dispgns.tuning's settings, as the command line does
(host allocator, ``tuned_model_config``: the fused CPU kernels, and
``network_compiler_options``); ``--no-tuning`` measures what a plain
``import dispgns`` gets.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

import _machine  # benchmarks/_machine.py, beside this script
import jax
import jax.numpy as jnp
import numpy as np
from cpu_peak import fma_peak  # benchmarks/cpu_peak.py, beside this script

from dispgns import tuning  # the package imports lazily: nothing of JAX has started yet

# First, before jax-md's import starts JAX's CPU backend: the host allocator (``--no-tuning``: none).
# Scripts that import this one decide for themselves.
TUNED = "--no-tuning" not in sys.argv[1:]
if TUNED and __name__ == "__main__":
    tuning.tune_host_allocator()

import dispgns
from dispgns.graph import host_count_pairs
from dispgns.kernels import MLP
from dispgns.model import ModelConfig, count_parameters
from dispgns.physics import PhysicsConfig, sample_initial_state, simulate
from dispgns.simulator import fit_capacity, rollout_scan
from dispgns.training import TrainConfig, compute_normalization, create_train_state, train_step
from dispgns.training.batches import BatchStream
from dispgns.training.checkpoint import load_model

RADII_MM = (2.25, 3.25, 3.75, 4.75)
# The authors' PyTorch code with its default hyper-parameters, measured on this 2-core machine:
# a training step on 2 examples of ~220 particles, and one rollout step of one example.
AUTHORS_TRAIN_STEP_MS = 330.0
AUTHORS_ROLLOUT_STEP_MS = 49.0
# The paper's network trained for a while (benchmarks/paper_network.py says how): its particles go
# where real ones go, so its graphs are the data's size.
PAPER_NETWORK = Path(__file__).resolve().parent / "data" / "paper_network"


def paper_network(directory: Path | None):
    """``(params, model_config)`` of a trained paper-size model, or ``(None, None)`` for untrained weights.

    The rollouts are timed with trained weights because untrained ones move
    the particles unphysically: in the full rollout they all leave the box
    and the graph empties (369 pairs on average, against the ground truth's
    2,839 as its bed settles), so the steps would be timed on graphs the
    simulator never meets.
    """
    if directory is None or str(directory).lower() == "none":
        return None, None
    if not (Path(directory) / "model.json").is_file():
        if Path(directory) != PAPER_NETWORK:
            raise SystemExit(
                f"--rollout-model {directory}: no model.json there; expected a model directory "
                "written by dispgns train (RUN/model) or 'none'"
            )
        print(f"no trained paper-size model in {directory}: rollouts use untrained weights", flush=True)
        return None, None
    params, config, _ = load_model(directory)
    expected = ModelConfig()
    shape = (
        "latent_size",
        "hidden_layers",
        "hidden_size",
        "message_passing_steps",
        "input_sequence_length",
        "dim",
        "activation",
        "connectivity_radius",
    )
    wrong = {f: getattr(config, f) for f in shape if getattr(config, f) != getattr(expected, f)}
    if wrong:
        raise SystemExit(
            f"{directory}/model.json: not the paper's network ({wrong}; expected "
            f"{ {f: getattr(expected, f) for f in wrong} })"
        )
    return params, config


def timed(fn, repeats: int):
    """Median wall and process-CPU seconds of ``fn()`` (blocked), after one warm-up call."""
    jax.block_until_ready(fn())
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        cpus.append(time.process_time() - c)
        walls.append(time.perf_counter() - w)
    return float(np.median(walls)), float(np.median(cpus))


def seconds(fn) -> float:
    """Wall seconds of one call of ``fn()``, its result blocked on."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def machine_info() -> dict:
    """The shared machine fields (``_machine.py``) and JAX's; the other network benchmarks import this."""
    return _machine.machine_info(
        jax=jax.__version__,
        devices=[str(d) for d in jax.devices()],
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        host_allocator_tuned=tuning.host_allocator_tuned(),
    )


def trajectories(n_particles: int, frames: int, seeds=(0, 1)):
    """Paper-protocol packings simulated for ``frames`` frames, in normalised units."""
    cfg = PhysicsConfig()
    out = []
    for seed in seeds:
        state = sample_initial_state(
            jax.random.key(seed), [r * 1e-3 for r in RADII_MM], cfg, n_particles=n_particles, start_height=-0.03
        )
        x = np.asarray(simulate(state.position, state.velocity, state.radius, cfg, n_frames=frames))
        out.append(
            dispgns.Trajectory(
                position=(x / cfg.box_half_size).astype(np.float32),
                radius=(np.asarray(state.radius) / cfg.box_half_size).astype(np.float32),
            )
        )
    return out


def network_options(dtype) -> dict:
    """The XLA options the network's jits use for this matmul dtype (so floors and network share kernels)."""
    name = "float32" if jnp.dtype(dtype) == jnp.float32 else "bfloat16"
    return tuning.network_compiler_options(ModelConfig(matmul_dtype=name)) if TUNED else {}


def computed(model_config: ModelConfig) -> ModelConfig:
    """The config the network is computed with: the fused CPU kernels when tuned (same function)."""
    return tuning.tuned_model_config(model_config) if TUNED else model_config


def matmul_rate(m: int, k: int, n: int, dtype=jnp.float32) -> float:
    a = jax.random.normal(jax.random.key(0), (m, k)).astype(dtype)
    b = jax.random.normal(jax.random.key(1), (k, n)).astype(dtype)
    f = (
        jax.jit(lambda a, b: jnp.dot(a, b, preferred_element_type=jnp.float32))
        .lower(a, b)
        .compile(compiler_options=network_options(dtype))
    )
    wall, _ = timed(lambda: f(a, b), 20)
    return 2.0 * m * k * n / wall / 1e9


def matmul_chain(rows: int, width: int = 128, dtype=jnp.float32, length: int = 20):
    """A jitted chain of ``length`` dependent ``rows x width x width`` products and its FLOPs.

    In one executable, as the network's layers are: no dispatch between the
    products, so its rate is what the network's dots can reach at best.
    """
    x = jax.random.normal(jax.random.key(0), (rows, width)).astype(dtype)
    w = (jax.random.normal(jax.random.key(1), (length, width, width)) / np.sqrt(width)).astype(dtype)

    def chain(x, w):
        for i in range(length):
            x = jnp.dot(x, w[i], preferred_element_type=jnp.float32).astype(dtype)
        return x

    compiled = jax.jit(chain).lower(x, w).compile(compiler_options=network_options(dtype))
    return (lambda: compiled(x, w)), 2.0 * length * rows * width * width


def network_flops(config: ModelConfig, nodes: int, edges: int) -> float:
    """Forward FLOPs (multiply-adds x 2) of the network's dense layers on one graph."""
    L, H, hl = config.latent_size, config.hidden_size, config.hidden_layers

    def mlp(rows, fan_in, out):
        sizes = [fan_in] + [H] * hl + [out]
        return 2.0 * rows * sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))

    total = mlp(nodes, config.node_feature_size, L) + mlp(edges, config.edge_feature_size, L)
    per_block = (
        2.0 * nodes * L * 2 * H  # node parts of the message MLP's first layer, once per node
        + 2.0 * edges * L * H
        + mlp(edges, H, L)
        - 2.0 * edges * H * H  # the rest of the message MLP
        + mlp(nodes, 2 * L, L)
        + mlp(nodes, L, L)
        + mlp(edges, L, L)
    )
    # The last block's edge update feeds nothing (the decoder reads nodes only): XLA drops it.
    return total + config.message_passing_steps * per_block - mlp(edges, L, L) + mlp(nodes, L, config.dim)


def xla_flops(compiled) -> float | None:
    try:
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        value = float(cost.get("flops", 0.0))
        return value if value > 0 else None
    except Exception:  # cost analysis is best-effort on CPU
        return None


def edge_mlp_rate(edges: int, dtype: str, repeats: int = 15) -> tuple[float, float]:
    """GFLOP/s of a stack of per-edge MLPs (forward + backward), the bulk of a training step.

    Returns ``(mlp_rate, matmul_rate)``: the matmul is an ``edges x 128 x 128``
    product of the same dtype, timed in alternation with the MLP stack (per
    round one MLP call and the mean of ten matmul calls; medians over rounds)
    so that both see the same machine (its speed drifts by +-15 % within a
    minute here).
    """
    low = None if dtype == "float32" else jnp.bfloat16
    mlp = MLP(128, (128, 128), 128, matmul_dtype=low)
    x = jax.random.normal(jax.random.key(0), (edges, 128))
    params = mlp.init(jax.random.key(1), x)
    depth = 4

    def loss(p, x):
        for _ in range(depth):
            x = x + mlp.apply(p, x)
        return jnp.sum(x * x)

    options = network_options(jnp.float32 if low is None else low)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1))).lower(params, x).compile(compiler_options=options)
    a = x.astype(jnp.float32 if low is None else low)
    b = jax.random.normal(jax.random.key(2), (128, 128)).astype(a.dtype)
    product = (
        jax.jit(lambda a, b: jnp.dot(a, b, preferred_element_type=jnp.float32))
        .lower(a, b)
        .compile(compiler_options=options)
    )
    jax.block_until_ready(grad(params, x))
    jax.block_until_ready(product(a, b))
    mlp_times, matmul_times = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(grad(params, x))
        mlp_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        for _ in range(10):
            jax.block_until_ready(product(a, b))
        matmul_times.append((time.perf_counter() - t) / 10)
    mlp_flops = 3.0 * depth * 3 * 2.0 * edges * 128 * 128
    return mlp_flops / np.median(mlp_times) / 1e9, 2.0 * edges * 128 * 128 / np.median(matmul_times) / 1e9


def run(
    dtype: str,
    trajs,
    args,
    report: dict,
    model_config: ModelConfig | None = None,
    tag: str | None = None,
    rollout_params=None,
    peak: dict | None = None,
):
    """Time one configuration; ``rollout_params``: trained weights for the rollouts (default: the initial ones).

    ``peak``: :func:`cpu_peak.fma_peak` of this machine (``None``: not
    measured), for the times the steps' FLOPs would take at the CPU's peak.

    Untrained weights move particles unphysically, so a long rollout with them
    can pack far more edges than real data (capacity grows, steps get dearer).
    """
    model_config = computed(ModelConfig(matmul_dtype=dtype) if model_config is None else model_config)
    options = network_options(jnp.float32 if dtype == "float32" else jnp.bfloat16)
    train_config = TrainConfig()
    norm = compute_normalization(trajs, noise_std=train_config.noise_std)
    state = create_train_state(jax.random.key(0), model_config, train_config, norm)
    stream = BatchStream(trajs, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=0)
    # Batches from the end of the trajectories (the settled, densest packings).
    late = np.flatnonzero(stream.index.start >= stream.index.start.max() - 4)
    ids = [late[0], late[-1]]
    batch = stream.make_batch(ids)
    pairs = stream.pairs[ids]
    key = jax.random.key(0)

    compiled = tuning.jitted(train_step, options).lower(state, batch, key).compile()
    flops_xla = xla_flops(compiled)
    train_wall, train_cpu = timed(lambda: compiled(state, batch, key), args.repeats)
    nodes = batch.node_budget
    slots = batch.capacity.edges + nodes
    flops_train = 3.0 * network_flops(model_config, 2 * (nodes + 1), 2 * slots)

    traj = trajs[0]
    start = traj.position.shape[0] - 6
    window = jnp.asarray(traj.position[start - 100 : start - 94])
    radius = jnp.asarray(traj.radius)
    mask = jnp.ones(radius.shape, bool)
    capacity = fit_capacity(traj.position[start - 100 :], model_config)
    params = state.params if rollout_params is None else rollout_params
    steps = args.rollout_steps
    # The pure rollout, compiled with the network's options: what dispgns.rollout runs between
    # its overflow checks.
    scan = tuning.jitted(rollout_scan, options, static_argnames=("n_steps", "model_config", "capacity"))
    chunk = lambda p, w: scan(p, w, radius, n_steps=steps, model_config=model_config, capacity=capacity, mask=mask)
    n_real = int(radius.shape[0])
    flops_rollout = network_flops(model_config, n_real, capacity.edges + n_real)
    # The machine drifts within a minute: the rollout chunk (about a second)
    # and the matmul chain that gives its floor are timed in alternation.
    chain, chain_flops = matmul_chain(
        capacity.edges + n_real, model_config.latent_size, jnp.float32 if dtype == "float32" else jnp.bfloat16
    )
    _, overflow = jax.block_until_ready(chunk(params, window))
    if bool(np.any(overflow)):
        raise SystemExit(
            f"the timed rollout chunk outgrew its graph capacity ({capacity}) at step {int(np.argmax(overflow))}"
        )
    jax.block_until_ready(chain())
    roll_walls, roll_cpus, chain_walls = [], [], []
    for _ in range(7):
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        jax.block_until_ready(chunk(params, window))
        roll_cpus.append(time.process_time() - cpu_start)
        roll_walls.append(time.perf_counter() - wall_start)
        wall_start = time.perf_counter()
        for _ in range(5):
            jax.block_until_ready(chain())
        chain_walls.append((time.perf_counter() - wall_start) / 5)
    roll_wall, roll_cpu = float(np.median(roll_walls)), float(np.median(roll_cpus))
    rollout_step = roll_wall / steps
    chain_rate = chain_flops / float(np.median(chain_walls))

    full = full_pairs = None
    if args.full:
        x0 = jnp.asarray(traj.position[:6])
        full_rollout = lambda: dispgns.rollout(
            params, x0, radius, 494, model_config=model_config, compiler_options=options
        )
        full_rollout()  # compile
        t = time.perf_counter()
        predicted = jax.block_until_ready(full_rollout())
        full = time.perf_counter() - t
        # The graphs the rollout met (the ground truth's grow as the bed settles): the cost of a
        # step follows them.
        full_pairs = host_count_pairs(predicted, connectivity_radius=model_config.connectivity_radius)

    # The time the dense layers alone would take at the rate of the matmul
    # chain timed next to the rollout: no step can be faster then.
    matmul_rate_now = chain_rate
    faults_before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(3):
        jax.block_until_ready(compiled(state, batch, key))
    faults_per_step = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults_before) / 3

    mlp_rate, edge_matmul_rate = edge_mlp_rate(2 * int(np.mean(pairs) + nodes), dtype)

    if tag is None:
        tag = "" if dtype == "float32" else "_bf16"
    report.update(
        {
            f"train_step_ms{tag}": 1e3 * train_wall,
            f"train_step_cpu_ms{tag}": 1e3 * train_cpu,
            f"rollout_step_ms{tag}": 1e3 * rollout_step,
            f"rollout_step_cpu_ms{tag}": 1e3 * roll_cpu / steps,
            f"rollout_494_steps_s{tag}": full,
            f"rollout_494_pairs_max{tag}": None if full_pairs is None else int(full_pairs.max()),
            f"rollout_494_pairs_mean{tag}": None if full_pairs is None else float(full_pairs.mean()),
            f"train_gflop{tag}": flops_train / 1e9,
            f"train_gflop_xla{tag}": None if flops_xla is None else flops_xla / 1e9,
            f"train_gflops_per_s{tag}": flops_train / train_wall / 1e9,
            f"rollout_gflop_per_step{tag}": flops_rollout / 1e9,
            f"rollout_gflops_per_s{tag}": flops_rollout / rollout_step / 1e9,
            f"train_step_matmul_floor_ms{tag}": 1e3 * flops_train / matmul_rate_now,
            f"rollout_step_matmul_floor_ms{tag}": 1e3 * flops_rollout / matmul_rate_now,
            f"rollout_over_floor{tag}": rollout_step / (flops_rollout / matmul_rate_now),
            f"matmul_chain_gflops_per_s{tag}": chain_rate / 1e9,
            f"page_faults_per_train_step{tag}": faults_per_step,
            f"edge_mlp_gflops_per_s{tag}": mlp_rate,
            f"edge_matmul_gflops_per_s{tag}": edge_matmul_rate,
            f"edge_mlp_fraction_of_matmul{tag}": mlp_rate / edge_matmul_rate,
        }
    )
    peak_rate = None if peak is None else peak["float32" if dtype == "float32" else "bfloat16"]
    if peak_rate:
        report.update(
            {
                f"train_step_ms_at_fma_peak{tag}": flops_train / peak_rate / 1e6,
                f"rollout_step_ms_at_fma_peak{tag}": flops_rollout / peak_rate / 1e6,
                f"rollout_fraction_of_fma_peak{tag}": flops_rollout / rollout_step / 1e9 / peak_rate,
            }
        )
        if tag != "_shipped":  # the 15 ms target is for the paper's network
            report[f"rollout_fraction_of_fma_peak_needed_for_target{tag}"] = flops_rollout / 15e-3 / 1e9 / peak_rate
    if tag == "":
        report.update(
            {
                "edges_per_example": [int(p) + n for p, n in zip(pairs, batch.mask.sum(axis=1))],
                "edge_slots_per_example": int(slots),
                "particles_per_example": [int(n) for n in batch.mask.sum(axis=1)],
                "parameters": count_parameters(params["network"]),
            }
        )
    print(
        f"[{dtype}] train step {1e3 * train_wall:.1f} ms (cpu {1e3 * train_cpu:.0f} ms), "
        f"{flops_train / 1e9:.1f} GFLOP -> {flops_train / train_wall / 1e9:.0f} GFLOP/s; rollout "
        f"{1e3 * rollout_step:.1f} ms/step ({rollout_step / (flops_rollout / matmul_rate_now):.2f}x the matmul "
        f"floor at {matmul_rate_now / 1e9:.0f} GFLOP/s); full 494-step rollout "
        f"{full if full is None else round(full, 2)} s",
        flush=True,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="float32 only, no full 494-step rollout")
    parser.add_argument("--repeats", type=int, default=20, help="timed training steps (median)")
    parser.add_argument("--rollout-steps", type=int, default=50, help="steps per timed rollout chunk")
    parser.add_argument(
        "--rollout-model",
        type=Path,
        default=PAPER_NETWORK,
        help="a trained paper-size model directory whose weights drive the rollouts "
        "(default: benchmarks/data/paper_network; 'none': untrained weights)",
    )
    parser.add_argument("--no-tuning", action="store_true", help="plain import dispgns: no opt-in speed settings")
    args = parser.parse_args()
    args.full = not args.quick
    report = {"machine": machine_info(), "tuned": TUNED}
    trajs = trajectories(220, 110)
    report["pairs_last_frame"] = [int(host_count_pairs(t.position[-1], connectivity_radius=0.2)) for t in trajs]
    report["matmul_gflops_per_s"] = matmul_rate(2048, 2048, 2048)
    report["matmul_4800x128x128_gflops_per_s"] = matmul_rate(4800, 128, 128)
    report["matmul_4800x128x128_bf16_gflops_per_s"] = matmul_rate(4800, 128, 128, jnp.bfloat16)
    print(
        f"matmul 2048^2 {report['matmul_gflops_per_s']:.0f} GFLOP/s, 4800x128x128 "
        f"{report['matmul_4800x128x128_gflops_per_s']:.0f} GFLOP/s (bf16 "
        f"{report['matmul_4800x128x128_bf16_gflops_per_s']:.0f})",
        flush=True,
    )
    # The CPU's own limit (no memory traffic, every FMA pipe busy): times below flops / peak are impossible.
    peak = fma_peak() if jax.default_backend() == "cpu" else None
    report["fma_peak_gflops_per_s"] = None if peak is None else peak["float32"]
    report["fma_peak_bf16_gflops_per_s"] = None if peak is None else peak["bfloat16"]
    if peak is not None:
        print(
            f"CPU peak (benchmarks/cpu_peak.py): float32 FMA {peak['float32']:.0f} GFLOP/s"
            + ("" if peak["bfloat16"] is None else f", bfloat16 dot {peak['bfloat16']:.0f} GFLOP/s"),
            flush=True,
        )
    trained_params, trained_config = paper_network(args.rollout_model)
    report["rollout_weights"] = "untrained" if trained_params is None else str(args.rollout_model)
    for dtype in ("float32",) if args.quick else ("float32", "bfloat16"):
        config = None if trained_config is None else dataclasses.replace(trained_config, matmul_dtype=dtype)
        run(dtype, trajs, args, report, model_config=config, rollout_params=trained_params, peak=peak)
    # The model that ships with dispgns (smaller than the paper's), for what users of the demo see.
    shipped_params, shipped, _ = dispgns.load_pretrained()
    # The network's own step, as the dated tables were measured (the default model ships with the mirror
    # average on, which doubles a step's network work).
    shipped = dataclasses.replace(shipped, symmetrize=False)
    run("float32", trajs, args, report, model_config=shipped, tag="_shipped", rollout_params=shipped_params, peak=peak)
    report["authors_pytorch"] = {"train_step_ms": AUTHORS_TRAIN_STEP_MS, "rollout_step_ms": AUTHORS_ROLLOUT_STEP_MS}
    report["speedup_vs_authors_train_step"] = AUTHORS_TRAIN_STEP_MS / report["train_step_ms"]
    report["speedup_vs_authors_rollout_step"] = AUTHORS_ROLLOUT_STEP_MS / report["rollout_step_ms"]
    report["edge_mlp_fraction_of_large_matmul"] = report["edge_mlp_gflops_per_s"] / report["matmul_gflops_per_s"]
    report["targets"] = {"train_step_ms": 200.0, "rollout_step_ms": 15.0, "edge_mlp_fraction_of_matmul": 0.6}
    report["machine"]["load_average_1min_end"] = os.getloadavg()[0]
    print(json.dumps(report, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


if __name__ == "__main__":
    main()
