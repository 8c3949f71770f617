"""Data-scaling curve: validation error against the number of training trajectories, at fixed step counts.

    python experiments/accuracy/data_scaling.py [--out experiments/accuracy/results]

Every run has the same network, training configuration (``experiments/accuracy/config.yaml``), seed and
validation set (the 12 valid trajectories of ``datasets/acc400``); only the number of training trajectories
differs. The 400-trajectory run is track A (``experiments/accuracy/run``); the 16- and 64-trajectory runs
trained on the first 16 / 64 training trajectories of the same files (``subset.py``) and their logs and
configs are in ``experiments/accuracy/scaling/<K>/``. Reads the validation records (one-step loss without
noise and the full 494-frame rollout MSE, mean over the 12 trajectories) and writes ``data_scaling.json``
and ``data_scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = {16: HERE / "scaling" / "16", 64: HERE / "scaling" / "64", 400: HERE / "run"}
STEPS = (5000, 10000, 15000, 20000)


def validations(run: Path) -> dict[int, dict]:
    """The validation records of a run's ``log.jsonl``, by step (a resumed run's repeat keeps the last)."""
    records = {}
    for line in (run / "log.jsonl").read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            if record.get("kind") == "validation":
                records[int(record["step"])] = record
    return records


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(HERE / "results"))
    args = parser.parse_args(argv)

    from dispgns.files import write_atomic
    from dispgns.render import save_figure

    table = []
    for count, run in RUNS.items():
        found = validations(run)
        for step in STEPS:
            if step in found:
                record = found[step]
                table.append(
                    {
                        "train_trajectories": count,
                        "step": step,
                        "valid_one_step_loss": record["valid_one_step_loss"],
                        "valid_rollout_mse": record["valid_rollout_mse"],
                    }
                )
    out = Path(args.out)
    write_atomic(out / "data_scaling.json", json.dumps(table, indent=1) + "\n")

    from matplotlib.figure import Figure
    from matplotlib.ticker import NullLocator

    fig = Figure(figsize=(10, 4), layout="constrained")
    axes = fig.subplots(1, 2)
    for ax, key, label in (
        (axes[0], "valid_one_step_loss", "valid one-step loss (no noise, std units)"),
        (axes[1], "valid_rollout_mse", "valid rollout MSE (12 trajectories, 494 frames)"),
    ):
        for step in STEPS:
            points = sorted((p["train_trajectories"], p[key]) for p in table if p["step"] == step)
            if points:
                ax.plot(*zip(*points), "o-", label=f"step {step:,}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_locator(NullLocator())  # only the three counts are labelled
        ax.set_xticks(list(RUNS), [str(k) for k in RUNS])
        ax.set_xlabel("training trajectories")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[1].axhline(9.5e-4, color="grey", linestyle="--", label="for scale: the paper on test (2 M GPU steps)")
    axes[1].legend()
    save_figure(fig, out / "data_scaling.png")
    for row in table:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
