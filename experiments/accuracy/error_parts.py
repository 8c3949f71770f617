"""How much of a rollout's position error the particles share: the whole suspension, or a size class (issue 19).

A model whose suspension settles too fast or too slow, as a whole or one size class of it, makes the same position
error for many particles at once; a model that errs particle by particle does not. For every trajectory and horizon
this splits the mean squared position error over the particles, ``mean_i |e_i|^2`` with ``e_i`` predicted minus
true centre (normalised units), into

- ``collective``: ``|mean_i e_i|^2``, the error of the suspension's centre of mass (``vertical``: its vertical
  component alone);
- ``per_size_class``: ``sum_c (n_c / n) |mean_{i in c} e_i|^2``, the error of each size class's centre of mass,
  weighted by its share of the particles (it includes the collective part);

and writes their fractions of the total, averaged over trajectories, with the totals' mean.

    python experiments/accuracy/error_parts.py --predictions runs/seed10-S10b/predictions/test.h5 \\
        --truth datasets/paper-seed10/test.h5 --out experiments/accuracy/results/error_parts_seed10_trackS10b.json

``--predictions`` is a file that ``dispgns evaluate`` writes (``predictions/SPLIT.h5``), ``--truth`` the dataset
split it was scored on. A horizon ``h`` is the frame ``h`` steps after the last input frame.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np

INPUT_FRAMES = 6  # the shipped models' input sequence length: predictions start at frame 6
HORIZONS = (10, 50, 100, 200, 300, 493)


def parts(predicted: np.ndarray, true: np.ndarray, radius: np.ndarray) -> dict[str, float]:
    """Total squared error per particle and its shared parts, for one frame: arrays ``(n, dim)`` and ``(n,)``."""
    error = predicted - true
    classes = np.unique(radius)
    return {
        "total": float((error**2).sum(axis=1).mean()),
        "collective": float((error.mean(axis=0) ** 2).sum()),
        "vertical": float(error[:, -1].mean() ** 2),
        "per_size_class": float(
            sum((radius == c).mean() * (error[radius == c].mean(axis=0) ** 2).sum() for c in classes)
        ),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predictions", type=Path, required=True)
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    rows: dict[int, list[dict[str, float]]] = {h: [] for h in HORIZONS}
    with h5py.File(args.predictions, "r") as predictions, h5py.File(args.truth, "r") as truth:
        for key in predictions:
            if key not in truth:
                parser.error(f"{args.truth}: no trajectory {key!r}, which {args.predictions} holds")
            predicted, true = predictions[key]["position"][:], truth[key]["position"][:]
            if predicted.shape != true.shape:
                parser.error(f"trajectory {key}: predicted positions {predicted.shape}, true {true.shape}")
            radius = truth[key]["radius"][:]
            for h in HORIZONS:
                rows[h].append(parts(predicted[INPUT_FRAMES + h], true[INPUT_FRAMES + h], radius))

    # the run's and the dataset's names, not this machine's paths
    names = {"predictions": "/".join(args.predictions.parts[-3:]), "truth": "/".join(args.truth.parts[-2:])}
    result = names | {"horizons": {}}
    for h, records in rows.items():
        fractions = {
            name: float(np.mean([r[name] / r["total"] for r in records]))
            for name in ("collective", "vertical", "per_size_class")
        }
        result["horizons"][str(h)] = (
            {"trajectories": len(records)}
            | {"mean_total": float(np.mean([r["total"] for r in records]))}
            | {f"{name}_fraction": value for name, value in fractions.items()}
        )
        print(
            f"h={h:3d}: mean |e|^2 {result['horizons'][str(h)]['mean_total']:.2e}, collective "
            f"{fractions['collective']:.3f} (vertical {fractions['vertical']:.3f}), per size class "
            f"{fractions['per_size_class']:.3f}"
        )

    from dispgns.files import write_atomic

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
