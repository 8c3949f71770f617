"""How precisely a test split measures a model: its rollout MSE on many fresh trajectories (issue 19).

    python experiments/accuracy/fresh_seeds.py --out experiments/accuracy/results/fresh_seed8.json \
        sedimentation-2d=runs/seed8-shipped/metrics.json paper=runs/seed8-paper/metrics.json \
        sedimentation-2d=runs/seed8u-shipped/metrics.json

Each argument is NAME=PATH[,PATH...], PATH the ``metrics.json`` of ``dispgns evaluate`` on a dataset drawn with a
seed the models never saw (``dispgns generate --preset paper --seed 8 --train-count 0 --valid-count 0 --test-count 48
--unseen-count 0``, and the same with ``--test-count 0 --unseen-count 48`` for unseen radii). The files of one
argument are pooled split by split, e.g. the same split of two seeds:

    track-S10b=runs/seed8-S10b/metrics.json,runs/seed10-S10b/metrics.json

Every model's files must come in the same order (checked by their datasets' names and seeds) so that pairs stay
paired. A documented test split holds 6 trajectories whose full-rollout MSEs spread by ~25 %, so one split says
little about what a model scores on the next fresh draw. For every split and model this writes the mean over
trajectories, its standard error and a 95 % bootstrap interval, the spread of the means of consecutive groups of 6
trajectories (what 6-trajectory splits would have reported), and, for two models on the same trajectories, the
paired difference.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

SPLIT_SIZE = 6  # the paper's test split
BOOTSTRAP_SAMPLES = 10_000
BOOTSTRAP_SEED = 0


def per_trajectory_mse(path: Path) -> tuple[dict[str, np.ndarray], str]:
    """Full-rollout MSE of every trajectory, by split, from a ``metrics.json`` of ``dispgns evaluate``, and the
    dataset it was scored on (its name and seed: what pairs two models' files)."""
    try:
        metrics = json.loads(path.read_text())
        values = {
            split: np.array([trajectory["mse"] for trajectory in record["trajectories"]])
            for split, record in metrics["splits"].items()
        }
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(
            f"{path}: not a metrics.json of dispgns evaluate with per-trajectory mse ({error!r})"
        ) from None
    dataset = metrics.get("dataset", {})
    return values, f"{Path(str(dataset.get('path', '?'))).name} (seed {dataset.get('seed', '?')})"


def describe(values: np.ndarray, rng: np.random.Generator) -> dict:
    """Mean, spread, standard error and 95 % bootstrap interval of the mean; 6-trajectory group means."""
    count = len(values)
    resampled = rng.choice(values, size=(BOOTSTRAP_SAMPLES, count)).mean(axis=1)
    groups = [float(values[i : i + SPLIT_SIZE].mean()) for i in range(0, count - SPLIT_SIZE + 1, SPLIT_SIZE)]
    return {
        "n": count,
        "mean": float(values.mean()),
        "std": float(values.std(ddof=1)),
        "standard_error": float(values.std(ddof=1) / np.sqrt(count)),
        "bootstrap_95": [float(q) for q in np.quantile(resampled, [0.025, 0.975])],
        f"means_of_groups_of_{SPLIT_SIZE}": groups,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("evaluations", nargs="+", metavar="NAME=PATH[,PATH...]")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--target", type=float, default=8e-4, help="issue 19's full-rollout MSE target")
    args = parser.parse_args(argv)

    # split -> model -> per-trajectory MSE (a model may come from several arguments, one per split; the files of one
    # argument, comma-separated, are pooled split by split in the order given, e.g. the same split of two seeds)
    by_split: dict[str, dict[str, np.ndarray]] = {}
    sources: dict[str, dict[str, list[str]]] = {}  # split -> model -> the datasets pooled, in order
    for argument in args.evaluations:
        name, separator, paths = argument.partition("=")
        if not separator or not all(paths.split(",")):
            parser.error(f"expected NAME=PATH[,PATH...], got {argument!r}")
        pooled: dict[str, list[np.ndarray]] = {}
        pooled_sources: dict[str, list[str]] = {}
        for path in paths.split(","):
            try:
                values_by_split, dataset = per_trajectory_mse(Path(path))
            except ValueError as error:
                parser.error(str(error))
            for split, values in values_by_split.items():
                pooled.setdefault(split, []).append(values)
                pooled_sources.setdefault(split, []).append(dataset)
        for split, parts in pooled.items():
            if name in by_split.setdefault(split, {}):
                parser.error(f"{name} has two evaluations of split {split}")
            by_split[split][name] = np.concatenate(parts)
            sources.setdefault(split, {})[name] = pooled_sources[split]

    rng = np.random.default_rng(BOOTSTRAP_SEED)
    result = {"target": args.target, "splits": {}}
    for split, models in by_split.items():
        entry = {"models": {name: describe(values, rng) for name, values in models.items()}}
        for record, values in zip(entry["models"].values(), models.values()):
            record["trajectories_over_target"] = int((values > args.target).sum())
        names = list(models)
        for i, first in enumerate(names):
            for second in names[i + 1 :]:
                if len(models[first]) == len(models[second]):
                    if sources[split][first] != sources[split][second]:
                        parser.error(
                            f"split {split}: {first} pools {sources[split][first]}, {second} "
                            f"{sources[split][second]}: give every model's files in the same order"
                        )
                    difference = models[second] - models[first]
                    entry[f"{second} - {first}"] = describe(difference, rng) | {
                        f"{first}_lower_on": int((difference > 0).sum())
                    }
        result["splits"][split] = entry

    from dispgns.files import write_atomic

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(result, indent=1) + "\n")
    for split, entry in result["splits"].items():
        for name, record in entry["models"].items():
            low, high = record["bootstrap_95"]
            groups = record[f"means_of_groups_of_{SPLIT_SIZE}"]
            print(
                f"{split:12s} {name:18s} n={record['n']}  MSE {record['mean']:.3e} ± {record['standard_error']:.1e} "
                f"(95 %: {low:.2e}-{high:.2e}); groups of {SPLIT_SIZE}: {min(groups):.2e}-{max(groups):.2e}; "
                f"{record['trajectories_over_target']} over {args.target:g}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
