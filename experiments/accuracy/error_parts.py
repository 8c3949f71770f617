"""How much of a rollout's position error the particles share: the whole suspension, or a size class (issue 19).

A model whose suspension settles too fast or too slow, as a whole or one size class of it, makes the same position
error for many particles at once; a model that errs particle by particle does not. For every trajectory and horizon
this splits the mean squared position error over the particles, ``mean_i |e_i|^2`` with ``e_i`` predicted minus
true centre (normalised units), into

- ``collective``: ``|mean_i e_i|^2``, the error of the suspension's centre of mass (``vertical``: its vertical
  component alone);
- ``per_size_class``: ``sum_c (n_c / n) |mean_{i in c} e_i|^2``, the error of each size class's centre of mass,
  weighted by its share of the particles (it includes the collective part);

and writes their fractions of the total, averaged over trajectories, with the totals' mean (summed over the axes:
``dim`` times the per-axis MSE of ``rollout_metrics``). Particles that erred independently of one another would
already give a collective fraction of about ``1 / n`` and a size-class fraction of about ``K / n`` (``K`` size
classes, ``n`` particles): the JSON gives both floors beside the measured fractions.

    python experiments/accuracy/error_parts.py --predictions runs/seed10-S10b/predictions/test.h5 \\
        --truth datasets/paper-seed10/test.h5 --out experiments/accuracy/results/error_parts_seed10_trackS10b.json

``--predictions`` is a file that ``dispgns evaluate`` writes (``predictions/SPLIT.h5``), ``--truth`` the dataset
split it was scored on; both are read (and checked) as dataset splits. A horizon ``h`` is the ``h``-th predicted
frame, ``h`` steps after the last input frame (``mse_h1`` of ``rollout_metrics`` is ``h = 1``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dispgns.data.format import read_split

INPUT_FRAMES = 6  # the shipped models' input sequence length: frame 6 is the first predicted one (h = 1)
HORIZONS = (10, 50, 100, 200, 300, 494)


def parts(predicted: np.ndarray, true: np.ndarray, radius: np.ndarray) -> dict[str, float]:
    """Mean squared error per particle (summed over the axes), and the fractions of it the particles share, for one
    frame; beside them, the fractions independent errors would give.

    ``predicted`` and ``true`` are ``(n, dim)`` centres, ``radius`` ``(n,)`` radii, all normalised by L; ``total``
    is in L^2.
    """
    error = predicted - true
    classes = np.unique(radius)
    total = float((error**2).sum(axis=1).mean())
    per_size_class = sum((radius == c).mean() * (error[radius == c].mean(axis=0) ** 2).sum() for c in classes)
    return {
        "total": total,
        "collective_fraction": float((error.mean(axis=0) ** 2).sum()) / total,
        "vertical_fraction": float(error[:, -1].mean() ** 2) / total,
        "per_size_class_fraction": float(per_size_class) / total,
        "independent_collective_fraction": 1.0 / len(radius),
        "independent_per_size_class_fraction": len(classes) / len(radius),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--predictions", type=Path, required=True)
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    rows: dict[int, list[dict[str, float]]] = {h: [] for h in HORIZONS}
    predictions, truth = read_split(args.predictions), read_split(args.truth)
    if len(predictions) != len(truth):
        parser.error(f"{args.predictions} holds {len(predictions)} trajectories, {args.truth} {len(truth)}")
    for index, (predicted, true) in enumerate(zip(predictions, truth)):
        if predicted.position.shape != true.position.shape:
            parser.error(
                f"trajectory {index:05d}: position {predicted.position.shape} in {args.predictions}, "
                f"{true.position.shape} in {args.truth}"
            )
        if len(true.position) < INPUT_FRAMES - 1 + max(HORIZONS) + 1:
            parser.error(
                f"{args.truth}: trajectory {index:05d} has {len(true.position)} frames, fewer than "
                f"{INPUT_FRAMES} inputs and {max(HORIZONS)} predicted"
            )
        for h in HORIZONS:
            frame = INPUT_FRAMES - 1 + h
            rows[h].append(parts(predicted.position[frame], true.position[frame], true.radius))

    # the run's and the dataset's names, not this machine's paths
    result = {"predictions": "/".join(args.predictions.parts[-3:]), "truth": "/".join(args.truth.parts[-2:])}
    result["horizons"] = {}
    for h, records in rows.items():
        means = {name: float(np.mean([r[name] for r in records])) for name in records[0]}
        result["horizons"][str(h)] = {"trajectories": len(records), "mean_total": means.pop("total")} | means
        print(
            f"h={h:3d}: mean |e|^2 {result['horizons'][str(h)]['mean_total']:.2e} L^2, collective "
            f"{means['collective_fraction']:.3f} (vertical {means['vertical_fraction']:.3f}; independent errors "
            f"{means['independent_collective_fraction']:.3f}), per size class {means['per_size_class_fraction']:.3f} "
            f"(independent errors {means['independent_per_size_class_fraction']:.3f})"
        )

    from dispgns.files import write_atomic

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
