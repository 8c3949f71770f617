"""Where a 3-D model's one-step error lives: the loss per frame of validation trajectories.

    python experiments/three_d/one_step_by_frame.py --run RUN --data datasets/paper3d --out by_frame.json

For every ``--every``-th frame ``t`` of the first ``--trajectories`` valid trajectories it predicts the
acceleration from the true frames ``t-5..t`` (no noise, no rollout) and prints, in the units of the
training loss per component (radius-normalised acceleration divided by the training std):

- ``model``: the mean squared error of the model;
- ``zero``: the same for predicting the mean acceleration (what a model that learned nothing scores);
- ``top5``: the share of the frame's error carried by its 5 worst particles.

Then, per phase (free settling, collisions, bed; ``PHASES``), the means of the three and the phase's
share of the summed error: the ratio model / zero says how much of the signal the network explains.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dispgns import load_dataset, predict_acceleration
from dispgns.training.checkpoint import load_params

# The phases of a paper3d trajectory (frames, inclusive): the spheres settle freely, collide and form the
# bed (frames ~90-150 in the 8 cm cube), then sit in it.
PHASES = {"free settling": (0, 89), "collisions": (90, 149), "bed": (150, 10**6)}


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
    phases = {}
    for name, (first, last) in PHASES.items():
        chosen = [r for r in rows if first <= r["frame"] <= last]
        if chosen:
            model, zero = (float(np.mean([r[key] for r in chosen])) for key in ("model", "zero"))
            top5 = float(np.mean([r["top5"] for r in chosen]))
            share = sum(r["model"] for r in chosen) / sum(r["model"] for r in rows)
            phases[name] = {"frames": [first, last], "model": model, "zero": zero, "top5": top5, "share": share}
            frames = f"{first}-{last}" if last < 10**6 else f"{first} on"
            print(
                f"{name} (frames {frames}): model {model:.3g}, zero {zero:.3g} (ratio {model / zero:.2f}), "
                f"top5 {top5:.2f}, share of the summed error {share:.0%}"
            )
    if args.out:
        record = {"run": str(args.run), "best": args.best, "phases": phases, "rows": rows}
        args.out.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
