"""Score a prediction ensemble: every step's acceleration is the mean of several models' (issue 19, track G).

The mirror average (track E) is a two-member ensemble of one network and cut the validation rollout MSE by 13 %;
this checks whether members with other weights add to it. Each member runs with the first member's settings
(as shipped: mirror average, box guard; `--symmetrize`/`--keep-inside-box` change it as for one model), on one
normalisation (checked: the members must come from one fine-tuning lineage), and the mean of their outputs replaces
the network's. Members may differ in their network's shape (``SHAPE_FIELDS``, e.g. track L's hidden width 128
beside track O3's 64; session 20): each then runs with its own shape. `dispgns evaluate` does the rest; its
arguments follow the members:

    python experiments/accuracy/ensemble.py sedimentation-2d,experiments/accuracy/pushforward3_run:best \\
        --data datasets/acc400 --splits valid --no-chaos --no-statistics --out runs/ensemble-valid

A member is read as ``dispgns evaluate --model`` reads it (``RUN:best`` = ``--model RUN --best``); the outputs name
the ensemble as their model. An experiment, not a feature: the mean is put in place of
`dispgns.simulator.apply_network`, and `dispgns.cli._common._load` returns the ensemble, while `main_ensemble`
runs; both are put back after.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

import dispgns.cli._common as cli_common
import dispgns.simulator as simulator
from dispgns.cli import CLIError, main


def _soup():
    """The weight average's module (its member reader and lineage check), loaded from beside this file."""
    spec = importlib.util.spec_from_file_location("soup", Path(__file__).with_name("soup.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# The fields in which members may differ: they change the parameters' shapes, not the features or the graph.
SHAPE_FIELDS = ("latent_size", "hidden_layers", "hidden_size", "message_passing_steps")


def _shape(config) -> dict:
    return {field: getattr(config, field) for field in SHAPE_FIELDS}


def ensemble(members: list[str]):
    """``(params, model_config, info, shapes)``: ``params["network"]`` stacks the members' networks on axis 0.

    When the members' networks differ in shape, ``params["network"]`` is instead the tuple of them and ``shapes``
    the tuple of each member's :data:`SHAPE_FIELDS` (``None`` when stacked).
    """
    soup = _soup()
    loaded = [soup.load(member) for member in members]
    first, config, info = loaded[0]
    # One lineage in all but the shape fields: compared as if every member had the first's.
    soup.check_lineage(members, [(p, dataclasses.replace(c, **_shape(config)), i) for p, c, i in loaded])
    shapes = tuple(_shape(c) for _, c, _ in loaded)
    networks = [p["network"] for p, _, _ in loaded]
    if all(shape == shapes[0] for shape in shapes):
        network, shapes = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *networks), None
    else:
        network = tuple(networks)
    sources = [member_info.get("source", member) for member, (_, _, member_info) in zip(members, loaded, strict=True)]
    # `evaluate` writes the model's source, configuration (the first member's) and record to metrics.json: the record
    # names every member, with its network's shape and its own training record.
    members_record = [
        {"source": source, "shape": _shape(c), "record": member_info.get("record", {})}
        for source, (_, c, member_info) in zip(sources, loaded, strict=True)
    ]
    source = "ensemble of " + " + ".join(sources)
    info = dict(info, source=source, ensemble=sources, record={"ensemble": members_record})
    if shapes is not None:  # for callers (the configuration returned is the first member's); metrics.json: `record`
        info["ensemble_shapes"] = list(shapes)
    return {"network": network, "normalization": first["normalization"]}, config, info, shapes


def mean_of_members(single, shapes=None):
    """``single`` (:func:`dispgns.model.apply_network`) turned into the mean over the members' networks.

    ``shapes`` ``None``: the networks are stacked on axis 0 (one vmapped network); else a tuple of networks, each run
    with the caller's configuration and its own :data:`SHAPE_FIELDS`.
    """

    def network(networks, *args, model_config):
        if shapes is None:
            return jax.vmap(lambda one: single(one, *args, model_config=model_config))(networks).mean(axis=0)
        outputs = [
            single(one, *args, model_config=dataclasses.replace(model_config, **shape))
            for one, shape in zip(networks, shapes, strict=True)
        ]
        return sum(outputs) / len(outputs)

    return network


def main_ensemble(argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    try:
        params, config, info, shapes = ensemble(argv[0].split(","))
    except CLIError as error:
        print(f"ensemble.py: {error}", file=sys.stderr)
        return 2
    # Replaced for this evaluation only: the next ensemble in this process reads its members with the real reader.
    saved = simulator.apply_network, cli_common._load
    simulator.apply_network = mean_of_members(saved[0], shapes)
    # The model reader only: `evaluate`'s --symmetrize, --keep-inside-box and speed settings still apply.
    cli_common._load = lambda args, dim=2: (params, config, info)
    try:
        return main(["evaluate", *argv[1:]])
    finally:
        simulator.apply_network, cli_common._load = saved


if __name__ == "__main__":
    from dispgns.tuning import tune_host_allocator

    # As the dispgns program does (dispgns.cli.main leaves the allocator as it is); after the imports above, so
    # possibly in part (threads that have allocated keep their arenas): speed only.
    tune_host_allocator(warn_if_late=False)
    raise SystemExit(main_ensemble(sys.argv[1:]))
