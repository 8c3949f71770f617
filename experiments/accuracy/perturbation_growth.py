"""How the exact physics grows a perturbation of the initial state, by its size (issue 19).

    python experiments/accuracy/perturbation_growth.py --data datasets/acc400-valid --splits valid \
        --eval runs/stats-valid-S10b/metrics.json --out experiments/accuracy/results/perturbation_growth_valid12.json

The chaos floor of ``dispgns evaluate`` re-runs the ground truth from its initial state shifted by 1e-6 L. This
re-runs it with shifts of several sizes (``--perturbations``, std in units of L, each trajectory's shift drawn as
the floor draws it) and writes, per size, the mean over the trajectories of the per-frame position MSE at
``--frames`` (predicted frames) and over the full rollout. The pairs (MSE at frame A, MSE at frame B) of the sizes
trace how the physics maps an error at A to an error at B; where a model's pair (``--eval``, its metrics.json)
falls on that curve, the local slope ``d log MSE_B / d log MSE_A`` says how much a model more accurate at A would
gain at B, if its dynamics after A are the physics'. A shift of the first size, 1e-6 L with the floor's seed,
reproduces the floor of ``dispgns evaluate`` (checked in the output: ``floor_check``).

A shifted start can blow the paper's explicit Euler step up, as the hand-over's states can (``handover.py``): a
re-run with a coordinate moving more than the smallest radius in one frame is left out of its size's mean and
counted under ``unstable``. A shift that makes two particles overlap at the start is refused by the physics'
input check (at 1e-2 L on ``acc400-valid``); the script then stops with that error.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from paired import trajectory_records  # the sibling script, on sys.path as this one's folder

from dispgns import tuning
from dispgns.data import load_dataset
from dispgns.evaluation import CHAOS_PERTURBATION, chaos_floor_trajectories
from dispgns.files import write_atomic
from dispgns.metrics import per_frame_mse


def growth(data: str, splits: list[str], perturbations: list[float], input_frames: int, seed: int) -> dict:
    """Per size of shift: every trajectory's per-frame MSE curve (``None`` where the re-run blew up)."""
    metadata, loaded = load_dataset(data, splits)
    trajectories = [t for split in splits for t in loaded[split]]
    truth = [np.asarray(t.position) for t in trajectories]
    frames = truth[0].shape[0]
    curves = {}
    for size in perturbations:
        start = time.perf_counter()
        rerun = chaos_floor_trajectories(
            trajectories,
            metadata.physics_config,
            n_frames=frames,
            save_every=metadata.save_every,
            seed=seed,
            perturbation=size,
            x64=metadata.precision == "float64",
            compiler_options=tuning.physics_compiler_options(),
            length_scale=metadata.length_scale,
        )
        rows = []
        for x, t, trajectory in zip(rerun, truth, trajectories, strict=True):
            stable = np.abs(np.diff(x, axis=0)).max() <= np.min(trajectory.radius)
            rows.append(np.asarray(per_frame_mse(x, t, input_frames=input_frames)) if stable else None)
        curves[size] = rows
        print(f"shift {size:g} L: {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    return curves


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--splits", nargs="+", default=["valid"])
    parser.add_argument("--perturbations", type=float, nargs="+", default=[CHAOS_PERTURBATION, 1e-5, 1e-4, 1e-3, 3e-3])
    parser.add_argument("--frames", type=int, nargs=2, default=[300, 494], metavar=("A", "B"))
    parser.add_argument("--input-frames", type=int, default=6, help="C: the curves start at frame C")
    parser.add_argument("--seed", type=int, default=0, help="the floor's seed (dispgns evaluate uses 0)")
    parser.add_argument("--eval", type=Path, help="a metrics.json of dispgns evaluate with the chaos floor")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    a, b = args.frames
    model = None
    if args.eval:
        try:
            records = trajectory_records(args.eval, ("per_frame_mse", "chaos_floor_per_frame_mse"))
        except ValueError as error:
            print(f"perturbation_growth.py: {error}", file=sys.stderr)
            return 1
        model = np.mean([r["per_frame_mse"] for r in records], axis=0)
        floor = np.mean([r["chaos_floor_per_frame_mse"] for r in records], axis=0)
    curves = growth(args.data, args.splits, sorted(args.perturbations), args.input_frames, args.seed)
    sizes = {}
    for size, rows in curves.items():
        kept = np.array([row for row in rows if row is not None])
        if not 1 <= a < b <= kept.shape[1]:
            parser.error(f"--frames must satisfy 1 <= A < B <= {kept.shape[1]}")
        mean = kept.mean(axis=0)
        sizes[f"{size:g}"] = {
            "mse_at": {str(a): float(mean[a - 1]), str(b): float(mean[b - 1])},
            "full_rollout_mse": float(mean.mean()),
            "n": len(kept),
            "unstable": len(rows) - len(kept),
        }
    # Local slopes between consecutive sizes: of the MSE at B, and of the full-rollout MSE, in the MSE at A.
    names = list(sizes)
    slopes: dict[str, dict[str, float]] = {f"mse_{b}": {}, "full_rollout_mse": {}}
    for first, second in zip(names[:-1], names[1:], strict=True):
        x1, x2 = sizes[first]["mse_at"][str(a)], sizes[second]["mse_at"][str(a)]
        for key, y1, y2 in (
            (f"mse_{b}", sizes[first]["mse_at"][str(b)], sizes[second]["mse_at"][str(b)]),
            ("full_rollout_mse", sizes[first]["full_rollout_mse"], sizes[second]["full_rollout_mse"]),
        ):
            slopes[key][f"{first}->{second}"] = float(np.log(y2 / y1) / np.log(x2 / x1))
    report = {
        "what": f"the exact physics re-run from each trajectory's initial state shifted by each size (std, units of "
        f"L); the mean per-frame position MSE at predicted frames {a} and {b} and over the full rollout, and the "
        f"local slopes of log MSE_{b} and of log full-rollout MSE in log MSE_{a} between consecutive sizes",
        "data": args.data,
        "splits": args.splits,
        "seed": args.seed,
        "sizes": sizes,
        "slopes": slopes,
    }
    if model is not None:
        report["model"] = {
            "eval": str(args.eval),
            "mse_at": {str(a): float(model[a - 1]), str(b): float(model[b - 1])},
            "full_rollout_mse": float(model.mean()),
        }
        floor_size = f"{CHAOS_PERTURBATION:g}"
        if floor_size in sizes and args.seed == 0:
            mine = sizes[floor_size]["mse_at"]
            report["floor_check"] = {
                "evaluate": {str(a): float(floor[a - 1]), str(b): float(floor[b - 1])},
                "here": mine,
            }
    text = json.dumps(report, indent=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
