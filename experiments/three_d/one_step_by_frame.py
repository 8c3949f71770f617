"""Where a 3-D model's one-step error lives: the loss per frame of validation trajectories.

    python experiments/three_d/one_step_by_frame.py --run RUN --data datasets/paper3d --out by_frame.json

For every ``--every``-th frame ``t`` of the first ``--trajectories`` valid trajectories it predicts the
acceleration from the true frames ``t-5..t`` (no noise, no rollout) and prints, in the units of the
training loss per component (radius-normalised acceleration divided by the training std):

- ``model``: the mean squared error of the model;
- ``zero``: the same for predicting the mean acceleration (what a model that learned nothing scores);
- ``top5``: the share of the frame's error carried by its 5 worst particles.

The ratio model / zero per phase says how much of the signal the network explains while the spheres
settle freely and while they collide and form the bed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dispgns import load_dataset, predict_acceleration
from dispgns.training.checkpoint import load_params


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, type=Path, help="a run directory or an exported model")
    parser.add_argument("--best", action="store_true", help="the run's best checkpoint by validation")
    parser.add_argument("--data", required=True, type=Path, help="the paper3d dataset")
    parser.add_argument("--trajectories", type=int, default=2, help="the first K valid trajectories")
    parser.add_argument("--every", type=int, default=6, help="score every N-th frame")
    parser.add_argument("--out", type=Path, help="write the rows as JSON")
    args = parser.parse_args()

    params, config, _ = load_params(args.run, best=args.best)
    std = np.asarray(params["normalization"]["acceleration_std"])
    mean = np.asarray(params["normalization"]["acceleration_mean"])
    c = config.input_sequence_length
    _, splits = load_dataset(args.data, ["valid"])
    rows = []
    for k, trajectory in enumerate(splits["valid"][: args.trajectories]):
        x = np.asarray(trajectory.position, np.float32)
        radius = np.asarray(trajectory.radius, np.float32)
        for t in range(c - 1, x.shape[0] - 1, args.every):
            predicted = np.asarray(predict_acceleration(params, x[t - c + 1 : t + 1], radius, model_config=config))
            true = x[t + 1] - 2 * x[t] + x[t - 1]
            error = ((predicted - true) / radius[:, None] / std) ** 2
            zero = ((true / radius[:, None] - mean) / std) ** 2
            per_particle = error.mean(axis=1)
            top5 = float(np.sort(per_particle)[-5:].sum() / per_particle.sum())
            rows.append(
                {"trajectory": k, "frame": t, "model": float(error.mean()), "zero": float(zero.mean()), "top5": top5}
            )
            print(f"trajectory {k} frame {t:3d}: model {error.mean():.3g}, zero {zero.mean():.3g}, top5 {top5:.2f}")
    if args.out:
        args.out.write_text(json.dumps({"run": str(args.run), "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
