"""Speed of the paper's network with the plain and the fused kernels, and of the code before the split.

The paper-size network (``ModelConfig()``: latent 128, 10 blocks) on random
but valid graphs (self-loops, random pairs, receivers sorted, unused slots
holding ``N`` at the end):

* ``forward``: one rollout step's graph, 220 nodes and 2,600 edge slots
  (2,400 real edges);
* ``train``: forward + backward (gradient of a squared-output loss with
  respect to the weights) on two such graphs merged, as the training step
  merges its 2 examples: 440 nodes, 5,000 edge slots (4,800 real).

Variants: ``old`` (``src/dispgns/model.py`` of git revision ``--old``, the
last one before the network and its CPU kernels were split, imported as a
separate module), ``fused`` and ``plain`` (``ModelConfig.kernels``). All are
float32, jitted with the XLA options the project uses for the float32
network on CPU (:func:`dispgns.tuning.network_compiler_options`), and fed the same
weights.

The machine's speed drifts by 15-30 % within minutes and other work runs on
it, so the variants are timed in interleaved rounds (the order rotating from
round to round) in one process; a round times ``--calls`` calls of each and
keeps their mean. Prints one JSON line: median milliseconds over the rounds,
and ``[median, 25th, 75th percentile]`` of the per-round ratios ``fused /
old`` (the split must not change the speed: the two compile to the same XLA
program) and ``plain / fused`` (what the plain kernels cost).

    python benchmarks/model_kernels.py [--rounds 15] [--calls 4] [--old d2b1a37]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _machine import cpu_model

import dispgns
from dispgns.model import ModelConfig, apply_network, init_params

REPO = Path(__file__).resolve().parent.parent
OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


def old_model(revision: str, directory: str):
    """``src/dispgns/model.py`` at ``revision``, imported as the module ``dispgns_model_old``."""
    source = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{revision}:src/dispgns/model.py"], check=True, capture_output=True, text=True
    ).stdout
    path = Path(directory) / "dispgns_model_old.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("dispgns_model_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def random_edges(rng, nodes: int, real: int, offset: int = 0):
    """``real`` edges on ``nodes`` nodes numbered from ``offset``: every self-loop plus random pairs."""
    pairs = real - nodes
    receivers = np.concatenate([np.arange(nodes), rng.integers(0, nodes, pairs)])
    senders = np.concatenate([np.arange(nodes), (receivers[nodes:] + rng.integers(1, nodes, pairs)) % nodes])
    order = np.argsort(receivers, kind="stable")
    return senders[order] + offset, receivers[order] + offset


def graph(rng, config: ModelConfig, examples: int, nodes: int = 220, real: int = 2400, slots: int = 2600):
    """Features and indices of ``examples`` merged graphs; unused slots (``examples * (slots - real)``) last."""
    parts = [random_edges(rng, nodes, real, k * nodes) for k in range(examples)]
    n, unused = examples * nodes, examples * (slots - real)
    senders = np.concatenate([s for s, _ in parts] + [np.full(unused, n)]).astype(np.int32)
    receivers = np.concatenate([r for _, r in parts] + [np.full(unused, n)]).astype(np.int32)
    node_features = rng.standard_normal((n, config.node_feature_size), np.float32)
    edge_features = rng.standard_normal((senders.size, config.edge_feature_size), np.float32)
    return tuple(jnp.asarray(a) for a in (node_features, edge_features, senders, receivers))


def compiled(apply, inputs, params):
    """Jitted forward on ``inputs["forward"]`` and forward + backward on ``inputs["train"]``, warmed up."""
    forward = jax.jit(apply, compiler_options=OPTIONS)
    train = jax.jit(jax.grad(lambda p, *g: jnp.sum(apply(p, *g) ** 2)), compiler_options=OPTIONS)
    fns = {"forward": lambda: forward(params, *inputs["forward"]), "train": lambda: train(params, *inputs["train"])}
    for fn in fns.values():
        jax.block_until_ready(fn())
    return fns


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--calls", type=int, default=4, help="calls per variant, size and round (their mean counts)")
    parser.add_argument("--old", default="d2b1a37", help="git revision of the code before the split")
    args = parser.parse_args(argv)
    dispgns.tune_host_allocator()  # as the command line and the other benchmarks do

    config = ModelConfig()
    params = init_params(jax.random.key(0), config)["network"]
    rng = np.random.default_rng(0)
    inputs = {"forward": graph(rng, config, 1), "train": graph(rng, config, 2)}
    with tempfile.TemporaryDirectory() as directory:
        old = old_model(args.old, directory)
        old_config = old.ModelConfig()
        variants = {"old": lambda p, *g: old.apply_network(p, *g, model_config=old_config)}
        for kernels in ("fused", "plain"):
            c = dataclasses.replace(config, kernels=kernels)
            variants[kernels] = lambda p, *g, c=c: apply_network(p, *g, model_config=c)
        fns = {name: compiled(apply, inputs, params) for name, apply in variants.items()}

    names = list(fns)
    times = {(name, size): [] for name in names for size in ("forward", "train")}
    for r in range(args.rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            for size, fn in fns[name].items():
                start = time.perf_counter()
                for _ in range(args.calls):
                    jax.block_until_ready(fn())
                times[name, size].append((time.perf_counter() - start) / args.calls)

    def ratio(a, b, size):
        """Median and quartiles of the per-round ratios (the quartiles show the noise)."""
        return [round(float(q), 3) for q in np.percentile(np.divide(times[a, size], times[b, size]), [50, 25, 75])]

    # The fused kernels are the old code moved: the same computation, so the same outputs to the bit.
    same = np.array_equal(fns["old"]["forward"](), fns["fused"]["forward"]())
    report = {
        "benchmark": "model_kernels",
        "cpu": cpu_model(),
        "jax": jax.__version__,
        "old_revision": args.old,
        "rounds": args.rounds,
        "calls_per_round": args.calls,
        "forward_graph": {"nodes": 220, "edge_slots": int(inputs["forward"][2].size)},
        "train_graph": {"nodes": 440, "edge_slots": int(inputs["train"][2].size)},
        "fused_output_equals_old": bool(same),
        **{f"{size}_ms_{name}": round(1e3 * float(np.median(t)), 2) for (name, size), t in times.items()},
        **{f"{size}_fused_over_old": ratio("fused", "old", size) for size in ("forward", "train")},
        **{f"{size}_plain_over_fused": ratio("plain", "fused", size) for size in ("forward", "train")},
    }
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
