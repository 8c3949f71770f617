"""What the optimiser update costs, per parameter leaf (dispgns' training) against one flat vector.

dispgns trains with ``optax.adam`` over the network's parameter tree (182 leaves in the shipped network), so each
update runs Adam's elementwise operations leaf by leaf. ``optax.flatten`` runs them on one concatenated vector.
For the shipped 2-D network this script times one jitted update (Adam's moments and ``apply_updates``) both ways,
median of several rounds of back-to-back updates, and checks whether the two give the same parameters after
``--steps`` updates with the same gradients (they agree to a few float32 ulps, not bit for bit: XLA fuses and
vectorises the two programs differently, so switching would change every trained model's digits).

    python benchmarks/optimizer_update.py            # --rounds 7 --updates 200
    python benchmarks/optimizer_update.py --in-step  # and the whole training step with each

A standalone update overstates what flattening buys a run: ``--in-step`` also times the compiled training step
(track J's fine-tuning recipe, batch 2, the densest windows of 220-particle trajectories, as ``batch_size.py``),
where XLA fuses the update with the rest of the step, with each optimiser, in interleaved rounds.
"""

import argparse
import dataclasses
import functools
import json
import statistics
import sys
import time
from unittest import mock

from dispgns import tuning  # nothing of JAX has started yet

# The whole training step as a training run has it (the command line tunes the allocator first).
if "--in-step" in sys.argv[1:] and __name__ == "__main__":
    tuning.tune_host_allocator()

import jax
import jax.numpy as jnp
import optax
from _machine import machine_info

from dispgns.pretrained import load_pretrained
from dispgns.training import TrainConfig
from dispgns.training import step as step_module
from dispgns.training.step import learning_rate_schedule


def _updater(optimizer):
    @jax.jit
    def update(grads, state, params):
        updates, state = optimizer.update(grads, state, params)
        return optax.apply_updates(params, updates), state

    return update


def _gradients(params, step: int):
    leaves, treedef = jax.tree_util.tree_flatten(params)
    keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), step), len(leaves))
    scale = 10.0 ** (step % 5 - 3)  # gradients of several sizes, as training sees
    return jax.tree_util.tree_unflatten(treedef, [scale * jax.random.normal(k, x.shape) for k, x in zip(keys, leaves)])


def _in_step_ms(rounds: int, hidden_size: int) -> dict:
    """Median ms of one compiled training step with the per-leaf and with the flat Adam, interleaved rounds."""
    import numpy as np
    from gnn import timed, trajectories  # benchmarks/gnn.py, beside this script

    from dispgns.training import compute_normalization, create_train_state
    from dispgns.training.batches import BatchStream

    _, shipped, _ = load_pretrained()
    model_config = tuning.tuned_model_config(
        dataclasses.replace(shipped, symmetrize=False, keep_inside_box=False, hidden_size=hidden_size)
    )
    recipe = TrainConfig(noise_std=1e-4, pushforward_steps=2, mirror_augmentation=True, ema_decay=0.9998)
    trajs = trajectories(220, 300, seeds=(0, 1))
    norm = compute_normalization(trajs, noise_std=recipe.noise_std)
    stream = BatchStream.for_training(trajs, model_config, recipe)
    batch = stream.make_batch(np.argsort(-stream.pairs, kind="stable")[: recipe.batch_size])
    key = jax.random.key(0)
    optimizers = {
        "per_leaf": step_module.make_optimizer,
        "flat": lambda tc: optax.flatten(optax.adam(learning_rate_schedule(tc))),
    }
    compiled = {}
    for name, make in optimizers.items():
        # train_step builds its optimiser with make_optimizer: a benchmark-only swap, undone on leaving the block.
        with mock.patch.object(step_module, "make_optimizer", make):
            state = create_train_state(jax.random.key(0), model_config, recipe, norm)
            step = tuning.jitted(step_module.train_step, tuning.network_compiler_options(model_config))
            compiled[name] = functools.partial(step.lower(state, batch, key).compile(), state, batch, key)
    times = {name: [] for name in compiled}
    for _ in range(rounds):
        for name, run in compiled.items():
            times[name].append(timed(run, 5)[0])
    result = {f"step_ms_{name}": 1e3 * float(np.median(t)) for name, t in times.items()}
    result["ratio_per_leaf_over_flat"] = result["step_ms_per_leaf"] / result["step_ms_flat"]
    result["hidden_size"] = hidden_size
    result["host_allocator_tuned"] = tuning.host_allocator_tuned()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--updates", type=int, default=200, help="back-to-back updates per round")
    parser.add_argument("--steps", type=int, default=30, help="updates compared for equality")
    parser.add_argument("--in-step", action="store_true", help="also time the whole training step with each")
    parser.add_argument(
        "--hidden-size", type=int, nargs="+", default=[64], help="hidden widths of the networks timed --in-step"
    )
    args = parser.parse_args()

    params = load_pretrained()[0]["network"]
    schedule = learning_rate_schedule(TrainConfig())
    variants = {"per_leaf": optax.adam(schedule), "flat": optax.flatten(optax.adam(schedule))}
    report = {
        "benchmark": "optimizer_update",
        "network": "sedimentation-2d (latent 64, 5 blocks)",
        "leaves": len(jax.tree_util.tree_leaves(params)),
        "parameters": sum(x.size for x in jax.tree_util.tree_leaves(params)),
    }
    finals = {}
    for name, optimizer in variants.items():
        update = _updater(optimizer)
        state, current = optimizer.init(params), params
        for step in range(args.steps):  # the equality check; also compiles
            current, state = update(_gradients(params, step), state, current)
        finals[name] = jax.block_until_ready(current)
        grads = _gradients(params, 0)
        times = []
        for _ in range(args.rounds):
            start = time.perf_counter()
            for _ in range(args.updates):
                current, state = update(grads, state, current)
            jax.block_until_ready(current)
            times.append((time.perf_counter() - start) / args.updates)
        report[f"update_ms_{name}"] = 1e3 * statistics.median(times)
    pairs = list(zip(jax.tree_util.tree_leaves(finals["per_leaf"]), jax.tree_util.tree_leaves(finals["flat"])))
    report["ratio_per_leaf_over_flat"] = report["update_ms_per_leaf"] / report["update_ms_flat"]
    report["bitwise_equal_after_steps"] = all(bool(jnp.array_equal(a, b)) for a, b in pairs)
    report["max_abs_difference_after_steps"] = max(float(jnp.max(jnp.abs(a - b))) for a, b in pairs)
    report["steps_compared"] = args.steps
    if args.in_step:
        report["in_step"] = [_in_step_ms(args.rounds, width) for width in args.hidden_size]
    report["machine"] = machine_info(jax=jax.__version__, optax=optax.__version__)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
