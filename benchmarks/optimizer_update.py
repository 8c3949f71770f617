"""What the optimiser update costs, per parameter leaf (dispgns' training) against one flat vector.

dispgns trains with ``optax.adam`` over the network's parameter tree (182 leaves in the shipped network), so each
update runs Adam's elementwise operations leaf by leaf. ``optax.flatten`` runs them on one concatenated vector.
For the shipped 2-D network this script times one jitted update (Adam's moments and ``apply_updates``) both ways,
median of several rounds of back-to-back updates, and checks whether the two give the same parameters after
``--steps`` updates with the same gradients (they agree to a few float32 ulps, not bit for bit: XLA fuses and
vectorises the two programs differently, so switching would change every trained model's digits).

    python benchmarks/optimizer_update.py            # --rounds 7 --updates 200
"""

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import optax
from _machine import machine_info

from dispgns.pretrained import load_pretrained
from dispgns.training import TrainConfig
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--updates", type=int, default=200, help="back-to-back updates per round")
    parser.add_argument("--steps", type=int, default=30, help="updates compared for equality")
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
    report["machine"] = machine_info(jax=jax.__version__, optax=optax.__version__)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
