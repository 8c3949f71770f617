"""Data-scaling curve: validation error against the number of training trajectories, at fixed step counts.

    python experiments/accuracy/data_scaling.py [--out experiments/accuracy/results]

Every run has the same network, training configuration (``experiments/accuracy/config.yaml``), seed and
validation set (the 12 valid trajectories of ``datasets/acc400``, in the files the run used at that step);
only the number of training trajectories differs. The 400-trajectory run is track A
(``experiments/accuracy/run``); the 16- and 64-trajectory runs trained on the first 16 / 64 training
trajectories of the same files (``subset.py``) and their logs and configs are in
``experiments/accuracy/scaling/<K>/``. The dataset was regenerated in session 6 and is not bit-identical to
the first one (float32 rounding differs between machines, and the trajectories are chaotic): track A's first
25,056 steps used the first files, the 16- and 64-trajectory runs to 50,000 steps (``scaling/16``,
``scaling/64``) and track A from step 25,056 on the regenerated ones; ``scaling/16-session4`` and
``scaling/64-session4`` are the first runs of those sizes (20,000 steps, first files). Every record is
tagged with the files it was validated on, and the data-scaling panel only joins points of the same files. Reads
the validation records (one-step loss without noise and the full 494-frame rollout MSE, mean over the 12
trajectories) and writes ``data_scaling.json`` and ``data_scaling.png``: the learning curve of each run, and the
rollout MSE against the number of training trajectories at every step where more than one size was validated.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
# (label, training trajectories, run directory, the last step on the first files: None = all of them, 0 = none)
RUNS = (
    ("16 trajectories (regenerated files)", 16, HERE / "scaling" / "16", 0),
    ("16 trajectories (first files, session 4)", 16, HERE / "scaling" / "16-session4", None),
    ("64 trajectories (regenerated files)", 64, HERE / "scaling" / "64", 0),
    ("64 trajectories (first files, session 4)", 64, HERE / "scaling" / "64-session4", None),
    ("400 trajectories (track A; regenerated files after 25,056)", 400, HERE / "run", 25056),
)
COUNTS = sorted({count for _, count, _, _ in RUNS})


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
    for label, count, run, last_step_on_first_files in RUNS:
        for step, record in sorted(validations(run).items()):
            table.append(
                {
                    "run": label,
                    "train_trajectories": count,
                    "files": "first"
                    if last_step_on_first_files is None or step <= last_step_on_first_files
                    else "regenerated",
                    "step": step,
                    "valid_one_step_loss": record["valid_one_step_loss"],
                    "valid_rollout_mse": record["valid_rollout_mse"],
                }
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "data_scaling.json", json.dumps(table, indent=1) + "\n")

    from matplotlib.figure import Figure
    from matplotlib.ticker import NullLocator

    fig = Figure(figsize=(15, 6), layout="constrained")
    axes = fig.subplots(1, 3)
    # Left and middle: the learning curves of each training-set size (not every run validated at every step).
    for ax, key, label in (
        (axes[0], "valid_one_step_loss", "valid one-step loss (no noise, std units)"),
        (axes[1], "valid_rollout_mse", "valid rollout MSE (12 trajectories, 494 frames)"),
    ):
        for run_label, *_ in RUNS:
            points = sorted((p["step"], p[key]) for p in table if p["run"] == run_label)
            if points:
                ax.plot(*zip(*points), "o-", label=run_label)
        ax.set_yscale("log")
        ax.set_xlabel("training step (batch 2)")
        ax.set_ylabel(label)
    # Right: the data-scaling curve, at every step where at least two sizes were validated on the same files.
    for files, style in (("first", "s--"), ("regenerated", "D-")):
        for step in sorted({p["step"] for p in table}):
            points = sorted(
                (p["train_trajectories"], p["valid_rollout_mse"])
                for p in table
                if p["step"] == step and p["files"] == files
            )
            if len(points) > 1:
                axes[2].plot(*zip(*points), style, label=f"step {step:,}, {files} files")
    axes[2].set_xscale("log")
    axes[2].set_yscale("log")
    axes[2].xaxis.set_minor_locator(NullLocator())  # only the training-set sizes are labelled
    axes[2].set_xticks(COUNTS, [str(k) for k in COUNTS])
    axes[2].set_xlabel("training trajectories")
    axes[2].set_ylabel("valid rollout MSE (12 trajectories, 494 frames)")
    for ax in axes[1:]:
        ax.axhline(9.5e-4, color="grey", linestyle=":", label="for scale: the paper on test (2 M GPU steps)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small", loc="upper center", bbox_to_anchor=(0.5, -0.17))  # below: keeps the points clear
    save_figure(fig, out / "data_scaling.png")
    for row in table:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
