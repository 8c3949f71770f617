"""Score a prediction ensemble: every step's acceleration is the mean of several models' (issue 19, track G).

The mirror average (track E) is a two-member ensemble of one network and cut the validation rollout MSE by 13 %;
this checks whether members with other weights add to it. Each member runs with the first member's configuration
(as shipped: mirror average, box guard), on one normalisation (checked: the members must come from one
fine-tuning lineage), and the mean of their outputs replaces the network's. `dispgns evaluate` does the rest; its
arguments follow the members:

    python experiments/accuracy/ensemble.py sedimentation-2d,experiments/accuracy/pushforward3_run:best \\
        --data datasets/acc400 --splits valid --no-chaos --no-statistics --out runs/ensemble-valid

A member is read as ``dispgns evaluate --model`` reads it (``RUN:best`` = ``--model RUN --best``). An experiment,
not a feature: the mean is put in place of `dispgns.simulator.apply_network` for this process only.
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np

import dispgns.cli.evaluate as evaluate_cli
import dispgns.simulator as simulator
from dispgns.cli import CLIError, main

sys.path.insert(0, __file__.rsplit("/", 1)[0])
import soup  # noqa: E402  (the same member reader and configuration check as the weight average)


def ensemble(members: list[str]):
    """``(params, model_config, info)`` whose ``params["network"]`` stacks the members' networks on axis 0."""
    loaded = [soup.load(member) for member in members]
    first, config, info = loaded[0]
    for member, (params, member_config, _) in zip(members[1:], loaded[1:], strict=True):
        if soup._network_fields(member_config) != soup._network_fields(config):
            raise CLIError(f"{member}: its model configuration differs from {members[0]}'s")
        gaps = jax.tree_util.tree_map(
            lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))),
            params["normalization"],
            first["normalization"],
        )
        if max(jax.tree_util.tree_leaves(gaps)) > 1e-6:
            raise CLIError(f"{member}: its normalisation differs from {members[0]}'s (another dataset)")
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *[p["network"] for p, _, _ in loaded])
    return {"network": stacked, "normalization": first["normalization"]}, config, dict(info, ensemble=members)


def mean_of_members(single):
    """``single`` (:func:`dispgns.model.apply_network`) turned into the mean over networks stacked on axis 0."""

    def network(networks, *args, model_config):
        return jax.vmap(lambda one: single(one, *args, model_config=model_config))(networks).mean(axis=0)

    return network


def main_ensemble(argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    try:
        params, config, info = ensemble(argv[0].split(","))
    except CLIError as error:
        print(f"ensemble.py: {error}", file=sys.stderr)
        return 2
    simulator.apply_network = mean_of_members(simulator.apply_network)
    evaluate_cli.load_model_argument = lambda args, dim=2: (params, config, info)
    return main(["evaluate", *argv[1:]])


if __name__ == "__main__":
    raise SystemExit(main_ensemble(sys.argv[1:]))
