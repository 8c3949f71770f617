"""The suspension statistics of a model next to the chaos floor, constant velocity and a second model (issue 19).

    python experiments/accuracy/statistics_table.py --eval runs/data-rich/eval-box-on/metrics.json \
        --other experiments/paper/results/statistics/summary.json --other-name paper \
        --out experiments/accuracy/results/statistics.md

``--eval`` is the ``metrics.json`` of ``dispgns evaluate`` (with statistics); ``--other`` is the
``summary.json`` of the same evaluation for another model (``experiments/paper/results/statistics``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

# (label, summary key, format, signed): a signed error's mean over trajectories can cancel, so no ratio for it.
ROWS = (
    ("full-rollout MSE", "mse", "{:.3g}", False),
    ("mean height, mean abs error (mm)", "mean_height_mean_abs_error_mm", "{:.2f}", False),
    ("front settling velocity error (mm/s), mean", "front_settling_velocity_error_mm_s", "{:+.2f}", True),
    ("final bed area fraction error, mean", "bed_area_fraction_error", "{:+.4f}", True),
    ("final g(r), L1 distance to the truth's", "rdf_l1", "{:.3f}", False),
    ("final positions, Sinkhorn divergence (L^2)", "sinkhorn_position_final", "{:.3g}", False),
    ("final positions, MMD^2", "mmd_position_final", "{:.3g}", False),
    ("final velocities, Sinkhorn divergence", "sinkhorn_velocity_final", "{:.3g}", False),
)


def mean(value):
    return value.get("mean") if isinstance(value, dict) else value


def cell(summary, key, fmt):
    value = mean(summary.get(key))
    return "-" if value is None else fmt.format(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eval", required=True)
    parser.add_argument("--name", default="sedimentation-2d")
    parser.add_argument("--other", required=True)
    parser.add_argument("--other-name", default="paper")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    splits = json.loads(Path(args.eval).read_text())["splits"]
    ours = {split: data["summary"] for split, data in splits.items()}
    other = json.loads(Path(args.other).read_text())["summary"]
    text = []
    for split, summary in ours.items():
        text += [
            f"### {split} ({len(splits[split]['trajectories'])} trajectories)\n",
            f"| | {args.name} | {args.other_name} | chaos floor | constant velocity | {args.name} / chaos floor |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for label, key, fmt, signed in ROWS:
            model, floor = mean(summary.get(key)), mean(summary.get(f"chaos_floor_{key}"))
            ratio = "-" if signed or model is None or not floor else f"{model / floor:.2f}"
            cells = [
                cell(summary, key, fmt),
                cell(other.get(split, {}), key, fmt),
                cell(summary, f"chaos_floor_{key}", fmt),
                cell(summary, f"constant_velocity_{key}", fmt),
                ratio,
            ]
            text.append(f"| {label} | " + " | ".join(cells) + " |")
        text.append("")
    Path(args.out).write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
