"""Summarise a `dispgns evaluate` of a wide container next to the same model in the paper's box; prints JSON + a table.

Reads OUT/metrics.json and OUT/predictions/*.h5 of `dispgns evaluate` and the
dataset it evaluated, and writes one results JSON (``--results``): every scalar
of the evaluation's summary and per trajectory (curves left out), plus what
the summary does not hold, computed here from the predictions and the truth:

- ``mean_height_max_abs_error_mm``: the largest error of the mean height of
  all disks over the whole rollout (the issue's target: within 2 mm);
- ``bed_columns``: the final frame cut into columns one ``L`` wide (32 in
  wide16): per column the mean height error (mm) and the count of disks,
  model against truth (where a local error of the bed would show, which the
  box-wide mean height averages away);
- ``rdf_l1_final``: the final frame's g(r) of the model against the truth's
  (mean absolute difference over the 30 shells of 1 mm up to 0.3 L, over the
  box's area: the evaluation's ``rdf_l1``), for an evaluation run with
  ``--no-statistics`` (at ~3,000 disks the statistics' pairwise matrices,
  vectorised over frames and trajectories, need more memory than 24 GB).

``--paper`` is the same model's evaluation in the paper's box
(`experiments/paper/results/statistics/summary.json`), for the table's
comparison column. Usage:

    python experiments/scale/summarize.py --eval eval/wide16 --data datasets/wide16 \
        --paper experiments/paper/results/statistics/summary.json \
        --results experiments/scale/results/wide16_metrics.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dispgns.data import load_dataset, read_split
from dispgns.metrics import STATISTICS_DEFAULTS, radial_distribution

ROWS = (
    ("rollout MSE (normalised)", "mse", "{:.3g}"),
    ("RMSE (mm)", "rmse_mm", "{:.2f}"),
    ("MSE at 10 / 100 steps", ("mse_h10", "mse_h100"), "{:.2g}"),
    ("constant-velocity MSE", "constant_velocity_mse", "{:.3g}"),
    ("chaos floor MSE (physics re-run, 1e-6 L)", "chaos_floor_mse", "{:.2g}"),
    ("wall crossings (particle-frames)", "wall_violations_total", "{:.0f}"),
    ("finite (fraction of trajectories)", "finite", "{:.0f}"),
    ("mean height, mean abs error (mm)", "mean_height_mean_abs_error_mm", "{:.2f}"),
    ("  chaos floor", "chaos_floor_mean_height_mean_abs_error_mm", "{:.2f}"),
    ("front settling velocity, truth (mm/s)", "front_settling_velocity_truth_mm_s", "{:.1f}"),
    ("front settling velocity error (mm/s)", "front_settling_velocity_error_mm_s", "{:.2f}"),
    ("  chaos floor", "chaos_floor_front_settling_velocity_error_mm_s", "{:.2f}"),
    ("final bed area fraction error", "bed_area_fraction_error", "{:.2g}"),
    ("  chaos floor", "chaos_floor_bed_area_fraction_error", "{:.2g}"),
    ("final g(r) L1", "rdf_l1", "{:.3f}"),
    ("  chaos floor", "chaos_floor_rdf_l1", "{:.3f}"),
    ("final Sinkhorn, positions (L^2)", "sinkhorn_position_final", "{:.2g}"),
    ("  chaos floor", "chaos_floor_sinkhorn_position_final", "{:.2g}"),
)


def scalars(entry: dict) -> dict:
    """The entries that are numbers (or ``{"mean", "std", "n"}`` of numbers), curves left out."""
    out = {}
    for key, value in entry.items():
        if isinstance(value, (int, float, bool)) or value is None:
            out[key] = value
        elif isinstance(value, dict) and isinstance(value.get("mean"), (int, float)):
            out[key] = value
    return out


def mean_of(summary: dict, key: str):
    value = summary.get(key)
    if isinstance(value, dict):
        value = value.get("mean")
    if key.endswith("_total") and isinstance(summary.get(key), dict):
        value = summary[key]["mean"] * summary[key]["n"]
    return value


def cell(summary: dict | None, key, fmt: str) -> str:
    if summary is None:
        return "-"
    keys = key if isinstance(key, tuple) else (key,)
    values = [mean_of(summary, k) for k in keys]
    return " / ".join("-" if v is None else fmt.format(v) for v in values)


def local_errors(truth: np.ndarray, predicted: np.ndarray, bounds, length_scale: float) -> dict:
    """Mean-height max error over the rollout and the final bed per column one L wide (mm, counts)."""
    frames = predicted.shape[0]
    truth = truth[:frames]
    mm = 1e3 * length_scale
    height_error = (predicted[..., -1].mean(axis=1) - truth[..., -1].mean(axis=1)) * mm
    (x0, x1) = bounds[0]
    edges = np.arange(x0, x1 + 0.5, 1.0)
    columns = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        t = truth[-1][(truth[-1, :, 0] >= lo) & (truth[-1, :, 0] < hi)]
        p = predicted[-1][(predicted[-1, :, 0] >= lo) & (predicted[-1, :, 0] < hi)]
        columns.append(
            {
                "x": [float(lo), float(hi)],
                "count_truth": int(len(t)),
                "count_model": int(len(p)),
                "mean_height_error_mm": float((p[:, -1].mean() - t[:, -1].mean()) * mm) if len(t) and len(p) else None,
            }
        )
    area = float(np.prod([hi - lo for lo, hi in bounds]))
    rdf = dict(r_max=STATISTICS_DEFAULTS["rdf_max"], bins=STATISTICS_DEFAULTS["rdf_bins"], volume=area)
    g_truth = np.asarray(radial_distribution(truth[-1], **rdf)[1])
    g_model = np.asarray(radial_distribution(predicted[-1], **rdf)[1])
    errors = [abs(c["mean_height_error_mm"]) for c in columns if c["mean_height_error_mm"] is not None]
    return {
        "mean_height_max_abs_error_mm": float(np.abs(height_error).max()),
        "mean_height_mean_abs_error_mm": float(np.abs(height_error).mean()),
        "bed_column_max_abs_mean_height_error_mm": max(errors),
        "bed_column_max_abs_count_difference": max(abs(c["count_model"] - c["count_truth"]) for c in columns),
        "rdf_l1_final": float(np.mean(np.abs(g_model - g_truth))),
        "bed_columns": columns,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eval", required=True, type=Path, help="the output directory of dispgns evaluate")
    parser.add_argument("--data", required=True, type=Path, help="the dataset it evaluated")
    parser.add_argument("--paper", type=Path, help="the same model's evaluation in the paper's box (summary.json)")
    parser.add_argument("--results", type=Path, help="results JSON to write")
    args = parser.parse_args()

    report = json.loads((args.eval / "metrics.json").read_text())
    splits = list(report["splits"])
    metadata, data = load_dataset(args.data, splits)
    paper = json.loads(args.paper.read_text())["summary"] if args.paper else {}
    results = {
        "dataset": report["dataset"],
        "bounds": [list(b) for b in metadata.bounds],
        "length_scale_m": metadata.length_scale,
        "frames": report["frames"],
        "model": report["model"]["source"],
        "splits": {},
    }
    for split in splits:
        predicted = read_split(args.eval / "predictions" / f"{split}.h5")
        trajectories = [
            {
                **scalars(metrics),
                **local_errors(
                    np.asarray(truth.position), np.asarray(p.position), metadata.bounds, metadata.length_scale
                ),
            }
            for metrics, truth, p in zip(report["splits"][split]["trajectories"], data[split], predicted)
        ]
        results["splits"][split] = {
            "summary": scalars(report["splits"][split]["summary"]),
            "trajectories": trajectories,
            "paper_box_summary": scalars(paper[split]) if split in paper else None,
        }
    if args.results:
        args.results.write_text(json.dumps(results, indent=1) + "\n")
    columns = []
    for split in splits:
        entry = results["splits"][split]
        columns += [(f"wide {split} ({entry['summary']['n_trajectories']})", entry["summary"])]
        if entry["paper_box_summary"] is not None:
            columns += [
                (f"paper box {split} ({entry['paper_box_summary']['n_trajectories']})", entry["paper_box_summary"])
            ]
    lines = ["| | " + " | ".join(name for name, _ in columns) + " |", "| --- |" + " --- |" * len(columns)]
    for label, key, fmt in ROWS:
        lines.append(f"| {label} | " + " | ".join(cell(s, key, fmt) for _, s in columns) + " |")
    for label, key, fmt in (
        ("mean height, max abs error over the rollout (mm)", "mean_height_max_abs_error_mm", "{:.2f}"),
        (
            "final bed per 1 L column: max abs mean-height error (mm)",
            "bed_column_max_abs_mean_height_error_mm",
            "{:.1f}",
        ),
        ("final bed per 1 L column: max count difference", "bed_column_max_abs_count_difference", "{:.0f}"),
        ("final g(r) L1, model (computed here)", "rdf_l1_final", "{:.3f}"),
    ):
        cells = []
        for name, _ in columns:
            split = name.split(" ")[-2] if name.startswith("wide") else None
            if split is None:
                cells.append("-")
            else:
                values = [t[key] for t in results["splits"][split]["trajectories"]]
                cells.append(", ".join(fmt.format(v) for v in values))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
