"""How a rollout's error grows, beside the chaos floor's, frame by frame (issue 19).

    python experiments/accuracy/late_growth.py --eval runs/stats-valid-S10b/metrics.json \
        --out experiments/accuracy/results/late_growth_valid12_trackS10b.json

``--eval`` is the ``metrics.json`` of a ``dispgns evaluate`` run with the chaos floor (the default). At each of
``--frames`` this writes the model's per-frame position MSE, the chaos floor's (the exact physics run from the true
initial frames shifted by 1e-6 L, ``dispgns.evaluation.CHAOS_PERTURBATION``) and constant velocity's, each the mean
over the trajectories. Between two frames A < B (``--between``) it writes the exponent
``log(model_B / floor_B) / log(model_A / floor_A)``: how the MSE at B scales with the MSE at A across two rollouts
of the same trajectories, the model's and the floor's, whose errors at A differ by orders of magnitude. It is a
secant over that range, not a local slope. A small exponent reads as: the error at B barely depends on the error
at A, so a model more accurate up to A gains little at B (provided its dynamics after A are as sensitive as the
physics').
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from paired import trajectory_records  # the sibling script, on sys.path as this one's folder

from dispgns.files import write_atomic

CURVES = {"model": "per_frame_mse", "chaos_floor": "chaos_floor_per_frame_mse"}
CONSTANT_VELOCITY = "constant_velocity_per_frame_mse"


def curves(path: Path) -> dict[str, np.ndarray]:
    """The mean over every trajectory of every split of the per-frame MSE curves (predicted frames, 1-based)."""
    names = {**CURVES, "constant_velocity": CONSTANT_VELOCITY}
    try:
        records = trajectory_records(path, tuple(names.values()))
    except ValueError as error:
        raise ValueError(f"{error} (evaluate with the chaos floor, without --no-chaos)") from None
    lengths = sorted({len(r[key]) for r in records for key in names.values()})
    if len(lengths) != 1:
        raise ValueError(f"{path}: per-frame curves of {lengths} frames; expected one length")
    return {name: np.mean([r[key] for r in records], axis=0) for name, key in names.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--eval", type=Path, required=True, help="metrics.json of dispgns evaluate (with the floor)")
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 10, 50, 100, 200, 250, 300, 350, 400, 450, 494])
    parser.add_argument("--between", type=int, nargs=2, default=[300, 494], metavar=("A", "B"))
    parser.add_argument("--out", type=Path, help="write the table here as JSON (also printed)")
    args = parser.parse_args(argv)
    try:
        mean = curves(args.eval)
    except ValueError as error:
        print(f"late_growth.py: {error}", file=sys.stderr)
        return 1
    frames = mean["model"].size
    bad = [f for f in (*args.frames, *args.between) if not 1 <= f <= frames]
    if bad or args.between[0] >= args.between[1]:
        parser.error(f"frames must lie in 1..{frames} and A < B; got {bad or args.between}")
    at = {name: {f: float(curve[f - 1]) for f in args.frames} for name, curve in mean.items()}
    a, b = args.between
    ratio_a = mean["model"][a - 1] / mean["chaos_floor"][a - 1]
    ratio_b = mean["model"][b - 1] / mean["chaos_floor"][b - 1]
    if not ratio_a > 1:
        print(f"late_growth.py: at frame {a} the model's MSE is not above the floor's: no exponent", file=sys.stderr)
        return 1
    report = {
        "what": "mean per-frame position MSE (box units squared) of the model, the chaos floor and constant "
        "velocity, at predicted frames; the exponent of the later MSE in the earlier one across the model and "
        "the floor",
        "eval": str(args.eval),
        "predicted_frames": frames,
        "per_frame": at,
        "full_rollout_mse": {name: float(curve.mean()) for name, curve in mean.items()},
        "between": {
            "frames": [a, b],
            "model_over_floor": [float(ratio_a), float(ratio_b)],
            "exponent": float(np.log(ratio_b) / np.log(ratio_a)),
        },
    }
    text = json.dumps(report, indent=1)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
