"""Average the parameters of several models of one fine-tuning lineage into one exported model (a "model soup").

Track G (RESUME.md) checked whether averaging the weights of checkpoints whose validation rollouts swing by +-15 %
smooths them out; it did not. Every source must be trained on the same dataset (same normalisation statistics,
checked) and share one model configuration, whose settings (symmetrize, keep_inside_box) the soup keeps from the
first source.

    python experiments/accuracy/soup.py OUT SOURCE [SOURCE ...]

A SOURCE is an exported model directory, a training run directory (followed by ``:best``: its best checkpoint by
validation) or a shipped model's name; an existing path wins over a name, as in ``dispgns --model``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import jax
import numpy as np

from dispgns.cli import CLIError
from dispgns.cli._common import _load
from dispgns.cli.train import _FINE_TUNE_MODEL_FIELDS as UNCOMPARED  # what a fine-tune may change
from dispgns.training.checkpoint import export_model


def load(source: str):
    """``source`` read as ``dispgns evaluate --model`` reads it (``:best`` = ``--best``)."""
    return _load(argparse.Namespace(model=source.removesuffix(":best"), best=source.endswith(":best")))


def _network_fields(config) -> dict:
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in UNCOMPARED}


def load_lineage(sources: list[str]) -> list:
    """``[(params, model_config, info)]`` of ``sources``; :class:`CLIError` unless one network on one dataset."""
    loaded = [load(source) for source in sources]
    check_lineage(sources, loaded)
    return loaded


def check_lineage(sources: list[str], loaded: list) -> None:
    """:class:`CLIError` unless ``loaded`` (as :func:`load_lineage` returns) is one network on one dataset."""
    first_params, first_config, _ = loaded[0]
    for source, (params, config, _) in zip(sources[1:], loaded[1:], strict=True):
        if _network_fields(config) != _network_fields(first_config):
            raise CLIError(f"{source}: its model configuration differs from {sources[0]}'s")
        gaps = jax.tree_util.tree_map(
            lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))),
            params["normalization"],
            first_params["normalization"],
        )
        if max(jax.tree_util.tree_leaves(gaps)) > 1e-6:
            raise CLIError(f"{source}: its normalisation differs from {sources[0]}'s (another dataset)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", help="the model directory to write")
    parser.add_argument("sources", nargs="+", help="models to average (see the module docstring)")
    args = parser.parse_args(argv)
    try:
        loaded = load_lineage(args.sources)
    except CLIError as error:
        print(f"soup.py: {error}", file=sys.stderr)
        return 2
    first_config = loaded[0][1]
    soup = jax.tree_util.tree_map(lambda *leaves: sum(leaves) / len(leaves), *[params for params, _, _ in loaded])
    sources = [info.get("source", source) for source, (_, _, info) in zip(args.sources, loaded, strict=True)]
    export_model(args.out, soup, first_config, {"soup_of": sources})
    print(f"wrote {args.out}: the mean of {len(loaded)} models")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
