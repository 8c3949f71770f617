"""How the exact physics grows a shift of the initial state, by its size (issue 19).

    python experiments/accuracy/perturbation_growth.py --data datasets/acc400-valid --splits valid \
        --eval runs/stats-valid-S10b/metrics.json \
        --out experiments/accuracy/results/perturbation_growth_valid12_trackS10b.json

The chaos floor of ``dispgns evaluate`` re-runs the ground truth from its initial state shifted by 1e-6 L. This
re-runs it with shifts of several sizes (``--perturbations``, std in units of L; every size scales the same
normal draws, the floor's, of each trajectory) and writes, per size, the mean over the trajectories of the
per-frame position MSE at two predicted frames A and B (``--frames``) and over the full rollout, every
trajectory's figures, and the local slopes between consecutive sizes of the MSE at B and of the full-rollout MSE
in the MSE at A. Where a model's figures (``--eval``, its metrics.json with the chaos floor) fall beside that
curve says whether its later error is about what the physics makes of the error it has at A. A shift at frame 0
and a model's error of the same size need not grow alike: this compares sizes, not mechanisms. With ``--eval``
and the floor's seed, the output also holds the 1e-6 L shift's figures beside the floor's from ``--eval``
(``floor_check``; recorded, not compared).

A shifted start can blow the paper's explicit Euler step up, as the hand-over's states can (``handover.py``): a
re-run with a coordinate moving more than the smallest radius in one frame counts under ``unstable``, and the
means and slopes are over the trajectories stable at every size. A shift that makes two particles overlap at the
start is refused by the physics' input check (1e-2 L on ``acc400-valid``); the largest size runs first, so the
script stops early with an error naming it.
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


def growth(metadata, trajectories, truth, sizes: list[float], input_frames: int, seed: int) -> dict:
    """Per size of shift (largest first): every trajectory's per-frame MSE curve, ``None`` where it blew up."""
    curves = {}
    for size in sorted(sizes, reverse=True):
        start = time.perf_counter()
        try:
            rerun = chaos_floor_trajectories(
                trajectories,
                metadata.physics_config,
                n_frames=truth[0].shape[0],
                save_every=metadata.save_every,
                seed=seed,
                perturbation=size,
                x64=metadata.precision == "float64",
                compiler_options=tuning.physics_compiler_options(),
                length_scale=metadata.length_scale,
            )
        except ValueError as error:
            raise ValueError(f"shift {size:g} L: {error}") from None
        rows = []
        for x, t, trajectory in zip(rerun, truth, trajectories, strict=True):
            stable = np.abs(np.diff(x, axis=0)).max() <= np.min(trajectory.radius)
            rows.append(np.asarray(per_frame_mse(x, t, input_frames=input_frames)) if stable else None)
        curves[size] = rows
        print(f"shift {size:g} L: {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    return dict(sorted(curves.items()))


def model_curves(path: Path, trajectories, predicted_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean per-frame MSE of a model and of its chaos floor from ``path``, checked against the data."""
    records = trajectory_records(path, ("per_frame_mse", "chaos_floor_per_frame_mse", "n_particles"))
    counts = [int(r["n_particles"]) for r in records]
    if counts != [t.position.shape[1] for t in trajectories]:
        raise ValueError(f"{path}: not evaluated on these trajectories (counts or particle numbers differ)")
    lengths = {len(r[key]) for r in records for key in ("per_frame_mse", "chaos_floor_per_frame_mse")}
    if lengths != {predicted_frames}:
        raise ValueError(f"{path}: per-frame curves of {sorted(lengths)} frames, expected {predicted_frames}")
    model = np.mean([r["per_frame_mse"] for r in records], axis=0)
    return model, np.mean([r["chaos_floor_per_frame_mse"] for r in records], axis=0)


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
    sizes = sorted(set(args.perturbations))
    if len(sizes) < 2 or sizes[0] <= 0:
        parser.error("--perturbations: two or more distinct sizes, all > 0")
    metadata, loaded = load_dataset(args.data, args.splits)
    trajectories = [t for split in args.splits for t in loaded[split]]
    truth = [np.asarray(t.position) for t in trajectories]
    predicted_frames = min(t.shape[0] for t in truth) - args.input_frames
    truth = [t[: predicted_frames + args.input_frames] for t in truth]
    a, b = args.frames
    if not 1 <= a < b <= predicted_frames:
        parser.error(f"--frames must satisfy 1 <= A < B <= {predicted_frames}")
    model = None
    try:
        if args.eval:
            model, floor = model_curves(args.eval, trajectories, predicted_frames)
        curves = growth(metadata, trajectories, truth, sizes, args.input_frames, args.seed)
    except ValueError as error:
        print(f"perturbation_growth.py: {error}", file=sys.stderr)
        return 1
    stable = [k for k in range(len(trajectories)) if all(rows[k] is not None for rows in curves.values())]
    if not stable:
        print("perturbation_growth.py: no trajectory is stable at every size", file=sys.stderr)
        return 1
    report_sizes = {}
    for size, rows in curves.items():
        kept = np.array([rows[k] for k in stable])
        report_sizes[f"{size:g}"] = {
            "mse_at": {str(a): float(kept[:, a - 1].mean()), str(b): float(kept[:, b - 1].mean())},
            "full_rollout_mse": float(kept.mean()),
            "unstable": sum(row is None for row in rows),
            "per_trajectory": {
                str(a): kept[:, a - 1].tolist(),
                str(b): kept[:, b - 1].tolist(),
                "full_rollout": kept.mean(axis=1).tolist(),
            },
        }
    # Local slopes between consecutive sizes: of the MSE at B, and of the full-rollout MSE, in the MSE at A.
    names = list(report_sizes)
    slopes: dict[str, dict[str, float]] = {f"mse_{b}": {}, "full_rollout_mse": {}}
    for first, second in zip(names[:-1], names[1:], strict=True):
        x1, x2 = report_sizes[first]["mse_at"][str(a)], report_sizes[second]["mse_at"][str(a)]
        for key, y1, y2 in (
            (f"mse_{b}", report_sizes[first]["mse_at"][str(b)], report_sizes[second]["mse_at"][str(b)]),
            ("full_rollout_mse", report_sizes[first]["full_rollout_mse"], report_sizes[second]["full_rollout_mse"]),
        ):
            slopes[key][f"{first}->{second}"] = float(np.log(y2 / y1) / np.log(x2 / x1))
    report = {
        "what": f"the exact physics re-run from each trajectory's initial state shifted by each size (std, units of "
        f"L); the mean per-frame position MSE at predicted frames {a} and {b} and over the full rollout, and the "
        f"local slopes of log MSE_{b} and of log full-rollout MSE in log MSE_{a} between consecutive sizes",
        "data": str(Path(args.data).resolve()),
        "splits": args.splits,
        "seed": args.seed,
        "input_frames": args.input_frames,
        "predicted_frames": predicted_frames,
        "trajectories": len(trajectories),
        "stable_at_every_size": len(stable),
        "sizes": report_sizes,
        "slopes": slopes,
    }
    if model is not None:
        report["model"] = {
            "eval": str(args.eval),
            "mse_at": {str(a): float(model[a - 1]), str(b): float(model[b - 1])},
            "full_rollout_mse": float(model.mean()),
        }
        floor_size = f"{CHAOS_PERTURBATION:g}"
        if floor_size in report_sizes and args.seed == 0:
            report["floor_check"] = {
                "evaluate": {str(a): float(floor[a - 1]), str(b): float(floor[b - 1])},
                "here": report_sizes[floor_size]["mse_at"],
            }
    text = json.dumps(report, indent=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, text + "\n")
    print(json.dumps({k: v for k, v in report.items() if k != "sizes"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
