"""Accuracy per CPU-hour of the accuracy run: validation rollout MSE against cumulative wall and CPU time.

    python experiments/accuracy/curves.py [--run experiments/accuracy/run] [--out experiments/accuracy]

Reads ``run/log.jsonl``. ``elapsed_s`` and ``cpu_s`` restart from 0 in each resumed segment of the run (a
record whose time is below the previous one starts a segment), so the cumulative time adds the segments.
Writes ``accuracy_per_cpu_hour.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def cumulative(records: list[dict]) -> list[dict]:
    """The validation records with ``wall_h`` and ``cpu_h``: hours since the start of the run, all segments."""
    offset = {"elapsed_s": 0.0, "cpu_s": 0.0}
    last = {"elapsed_s": 0.0, "cpu_s": 0.0}
    out = []
    for record in records:
        if "elapsed_s" not in record:
            continue
        if record["elapsed_s"] < last["elapsed_s"]:  # a resumed segment starts
            offset = {k: offset[k] + last[k] for k in offset}
        last = {k: float(record.get(k, 0.0)) for k in offset}
        if record.get("kind") == "validation" and "valid_rollout_mse" in record:
            out.append(
                {
                    "step": record["step"],
                    "valid_rollout_mse": record["valid_rollout_mse"],
                    "wall_h": (offset["elapsed_s"] + last["elapsed_s"]) / 3600,
                    "cpu_h": (offset["cpu_s"] + last["cpu_s"]) / 3600,
                }
            )
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=str(HERE / "run"))
    parser.add_argument("--out", default=str(HERE))
    args = parser.parse_args(argv)

    from dispgns.files import write_atomic
    from dispgns.render import save_figure

    lines = (Path(args.run) / "log.jsonl").read_text().splitlines()
    points = cumulative([json.loads(line) for line in lines if line.strip()])
    out = Path(args.out)
    write_atomic(out / "accuracy_per_cpu_hour.json", json.dumps(points, indent=1) + "\n")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    for key, label in (("wall_h", "wall time (h)"), ("cpu_h", "CPU time (h, process)")):
        ax.plot([p[key] for p in points], [p["valid_rollout_mse"] for p in points], "o-", label=label)
    ax.axhline(9.45e-4, color="grey", linestyle="--", label="paper, test (2 M GPU steps)")
    ax.set_yscale("log")
    ax.set_xlabel("hours of training")
    ax.set_ylabel("valid rollout MSE (12 trajectories, 494 frames)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    save_figure(fig, out / "accuracy_per_cpu_hour.png")
    print(json.dumps(points[-1] if points else {}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
