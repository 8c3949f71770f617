"""Reproduce the paper's experiment end to end: dataset, training, evaluation, results table.

    python experiments/paper/run.py                       # everything, resumable
    python experiments/paper/run.py --steps 20000         # a shorter training budget
    python experiments/paper/run.py --config experiments/paper/paper_exact.yaml --out runs/paper-exact
    python experiments/paper/run.py --evaluate-only       # re-score the trained run
    python experiments/paper/run.py --ship                # also copy the model into dispgns/pretrained/paper
    python experiments/paper/run.py --evaluate-only --out runs/data-rich --best --ship --name sedimentation-2d \
        --record experiments/accuracy/sedimentation-2d_record.json

Stages (each skipped when its output exists, so an interrupted run continues):

1. ``dispgns generate --preset paper --seed 0`` into ``--data`` (40 trajectories, 500 frames);
2. ``dispgns train`` with ``--config`` into ``OUT/run`` (``--resume`` when a run is there);
3. ``dispgns evaluate`` on ``test`` (training radii) and ``test_unseen`` (unseen radii), once with the
   network alone (``OUT/eval-box-off``) and once with predicted centres kept inside the box
   (``OUT/eval-box-on``);
4. ``OUT/results.md`` and ``OUT/results.json``: per split the rollout MSE (mean ± std), the RMSE in mm
   and in particle diameters, horizons, the constant-velocity baseline and the chaos floor, next to the
   paper's numbers, for both evaluations.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
from pathlib import Path

from dispgns.cli import main as dispgns

HERE = Path(__file__).parent
REPO = HERE.parent.parent

# Hashemi & Izadkhah (2025), Table/Fig. of the rollout MSE (normalised units), mean ± std.
PAPER = {
    "test": {"mse": 9.5e-4, "std": 2.2e-4, "example": 6.6e-4, "label": "6 test trajectories, training radii"},
    "test_unseen": {"mse": 9.4e-4, "std": 2.0e-4, "example": 6.5e-4, "label": "12 test trajectories, unseen radii"},
}
TARGET_MSE = 2e-3


def run_stage(argv: list[str]) -> None:
    print("$ dispgns " + " ".join(argv), flush=True)
    code = dispgns(argv)
    if code != 0:
        sys.exit(code)


def results(evaluation: dict, run_dir: Path) -> tuple[str, dict]:
    """The results table (Markdown) and its JSON twin."""
    record = evaluation["model"].get("record", {})
    rows, table = {}, []
    table.append("| | test (training radii) | test_unseen (unseen radii) |")
    table.append("| --- | --- | --- |")

    def cell(split, key, scale=1.0, digits=2):
        entry = evaluation["splits"][split]["summary"].get(key)
        if not entry:
            return "-", None
        mean, std = entry["mean"] * scale, entry["std"] * scale
        rows.setdefault(split, {})[key] = {"mean": mean, "std": std}
        if abs(mean) < 1e-2 or abs(mean) >= 1e3:
            return f"{mean:.{digits}e} ± {std:.{digits - 1}e}", mean
        return f"{mean:.{digits + 1}g} ± {std:.{digits}g}", mean

    lines = [
        ("rollout MSE, dispgns", "mse"),
        ("RMSE (mm), dispgns", "rmse_mm"),
        ("RMSE (mean diameters), dispgns", "rmse_diameters"),
        ("MSE at 10 steps", "mse_h10"),
        ("MSE at 50 steps", "mse_h50"),
        ("MSE at 100 steps", "mse_h100"),
        ("constant-velocity baseline MSE", "constant_velocity_mse"),
        ("constant-velocity baseline RMSE (mm)", "constant_velocity_rmse_mm"),
        ("chaos floor MSE (physics re-run, 1e-6 L perturbation)", "chaos_floor_mse"),
        ("model MSE / constant-velocity MSE", "mse_over_constant_velocity"),
        ("wall crossings per trajectory (particle-frames)", "wall_violations_total"),
    ]
    for label, key in lines:
        cells = [cell(split, key)[0] for split in ("test", "test_unseen")]
        table.append(f"| {label} | {cells[0]} | {cells[1]} |")
    paper = [f"{PAPER[s]['mse']:.1e} ± {PAPER[s]['std']:.1e}" for s in ("test", "test_unseen")]
    table.append(f"| rollout MSE, paper (2M steps on a GPU) | {paper[0]} | {paper[1]} |")
    paper_rmse = [f"{(PAPER[s]['mse'] ** 0.5) * 100:.2f}" for s in ("test", "test_unseen")]
    table.append(f"| RMSE (mm) implied by the paper's MSE, sqrt(MSE) L | {paper_rmse[0]} | {paper_rmse[1]} |")
    text = "\n".join(table)
    summary = {
        "model": {
            "source": evaluation["model"]["source"],
            "steps": record.get("steps"),
            "config": evaluation["model"]["config"],
            "train": record.get("train"),
        },
        "dataset": evaluation["dataset"],
        "splits": rows,
        "paper": PAPER,
        "target_mse": TARGET_MSE,
        "meets_target": all(
            rows.get(s, {}).get("mse", {}).get("mean", 1.0) <= TARGET_MSE
            and rows.get(s, {}).get("mse_over_constant_velocity", {}).get("mean", 1.0) <= 0.1
            and rows.get(s, {}).get("wall_violations_total", {}).get("mean", 1.0) == 0
            for s in PAPER
        ),
        "run": str(run_dir),
    }
    return text, summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=str(HERE / "config.yaml"), help="training config (YAML)")
    parser.add_argument("--data", default=str(REPO / "datasets" / "paper"), help="dataset directory")
    parser.add_argument("--out", default=str(REPO / "runs" / "paper"), help="output directory")
    parser.add_argument("--seed", type=int, default=0, help="dataset seed (the documented results use 0)")
    parser.add_argument("--steps", type=int, help="training steps (default: the config's num_steps)")
    parser.add_argument("--evaluate-only", action="store_true", help="skip generation and training")
    parser.add_argument(
        "--ship", action="store_true", help="copy the trained model and its record into src/dispgns/pretrained/NAME"
    )
    parser.add_argument("--name", default="paper", help="the shipped model's name with --ship (default paper)")
    parser.add_argument(
        "--record",
        type=Path,
        help="with --ship: a JSON object merged into the shipped model's record (e.g. how it was selected)",
    )
    parser.add_argument(
        "--best",
        action="store_true",
        help="evaluate and ship the run's best checkpoint by validation instead of its last step",
    )
    parser.add_argument(
        "--keep-inside-box",
        choices=("on", "off"),
        default="on",
        help="the shipped model's keep_inside_box setting (default on)",
    )
    parser.add_argument(
        "--symmetrize",
        choices=("on", "off"),
        default="off",
        help="evaluate (both keep_inside_box modes) and ship with every prediction averaged over the mirror "
        "image (ModelConfig.symmetrize: 2 network evaluations per step; default off)",
    )
    args = parser.parse_args()
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", args.name):
        parser.error(f"--name {args.name!r}: a plain name of letters, digits, '.', '_' and '-'")
    if (args.name != "paper" or args.record) and not args.ship:
        parser.error("--name and --record only apply with --ship")
    extra = json.loads(args.record.read_text()) if args.record else {}
    if not isinstance(extra, dict):
        parser.error(f"--record {args.record}: expected a JSON object")

    data, out = Path(args.data), Path(args.out)
    run_dir = out / "run"
    if args.ship and args.evaluate_only and not (run_dir / "training_curve.png").is_file():
        parser.error(f"--ship: {run_dir / 'training_curve.png'} is missing (dispgns train writes it)")
    if not args.evaluate_only:
        if not (data / "metadata.json").is_file():
            run_stage(["generate", "--preset", "paper", "--seed", str(args.seed), "--out", str(data)])
        train = ["train", "--data", str(data), "--out", str(run_dir), "--config", args.config]
        if args.steps is not None:
            train += ["--steps", str(args.steps)]
        if (run_dir / "config.json").is_file():
            train.append("--resume")
        run_stage(train)
    texts, summaries = [], {}
    for mode, title in (
        ("off", "the network alone (the paper's method)" if args.symmetrize == "off" else "no box guard"),
        ("on", "with predicted centres kept inside the box (keep_inside_box)"),
    ):
        eval_dir = out / f"eval-box-{mode}"
        run_stage(
            [
                "evaluate",
                "--model",
                str(run_dir),
                "--data",
                str(data),
                "--splits",
                "test",
                "test_unseen",
                "--out",
                str(eval_dir),
                "--keep-inside-box",
                mode,
                "--overwrite",
                "--symmetrize" if args.symmetrize == "on" else "--no-symmetrize",
            ]
            + (["--best"] if args.best else [])
        )
        evaluation = json.loads((eval_dir / "metrics.json").read_text())
        text, summary = results(evaluation, run_dir)
        texts.append(f"### {title}\n\n{text}")
        summaries[f"keep_inside_box_{mode}"] = summary
    (out / "results.md").write_text("\n\n".join(texts) + "\n")
    (out / "results.json").write_text(json.dumps(summaries, indent=2) + "\n")
    print("\n\n".join(texts))
    print(f"wrote {out / 'results.md'} and {out / 'results.json'}")
    if args.ship:
        ship(
            run_dir,
            summaries,
            keep_inside_box=args.keep_inside_box == "on",
            symmetrize=args.symmetrize == "on",
            best=args.best,
            name=args.name,
            extra=extra,
        )
    return 0


def training_time(log: list[dict]) -> float:
    """Wall time of training over all resumed segments (each segment's clock restarts at 0)."""
    total, last = 0.0, 0.0
    for record in log:
        elapsed = float(record.get("elapsed_s", 0.0))
        if elapsed < last:
            total += last
        last = elapsed
    return total + last


def ship(
    run_dir: Path,
    summaries: dict,
    keep_inside_box: bool,
    best: bool,
    name: str = "paper",
    extra: dict | None = None,
    symmetrize: bool = False,
) -> None:
    """Copy the run's model (its last step, or its best checkpoint) into the package, with the
    evaluation summaries in its record."""
    import dataclasses

    from dispgns.training.checkpoint import export_model, load_params, read_json

    curve = run_dir / "training_curve.png"
    if not curve.is_file():  # checked first: nothing is exported without it
        sys.exit(f"{curve}: missing (dispgns train writes it); the model was not shipped")
    params, model_config, info = load_params(run_dir, best=best)
    model_config = dataclasses.replace(model_config, keep_inside_box=keep_inside_box, symmetrize=symmetrize)
    config = read_json(run_dir / "config.json", "configuration of the run")
    record = dict(info.get("record", {}))
    # One vocabulary whatever was loaded: an exported model's record names its last validation "last_validation",
    # a checkpoint's "validation" (what the package's record and its test read).
    if "last_validation" in record:
        record["validation"] = record.pop("last_validation")
    dataset = record.get("dataset")
    if isinstance(dataset, dict) and "path" in dataset:  # this machine's path says nothing elsewhere
        record["dataset"] = {**dataset, "path": Path(dataset["path"]).name}
    log = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines() if line.strip()]
    # The training that made the shipped parameters: nothing logged after its step (a best checkpoint's).
    log = [r for r in log if r.get("step", 0) <= record.get("steps", float("inf"))]
    record["evaluation"] = {mode: summary["splits"] for mode, summary in summaries.items()}
    record["paper"] = PAPER
    record["training_log"] = {
        "train": [[r["step"], r["loss"]] for r in log if r.get("kind") == "train"][::10],
        "validation": [
            [r["step"], r.get("valid_rollout_mse"), r.get("valid_one_step_loss")]
            for r in log
            if r.get("kind") == "validation"
        ],
        "training_time_s": training_time(log),
    }
    record["normalization"] = config["normalization"]
    record.update(extra or {})
    target = REPO / "src" / "dispgns" / "pretrained" / name
    export_model(target, params, model_config, record)
    shutil.copyfile(curve, target / "training_curve.png")
    print(f"shipped {info['source']} as {target} (keep_inside_box={keep_inside_box}, symmetrize={symmetrize})")


if __name__ == "__main__":
    from dispgns.tuning import tune_host_allocator

    # As the dispgns program does (dispgns.cli.main leaves the allocator as it is); after the imports above, so
    # possibly in part (threads that have allocated keep their arenas): speed only.
    tune_host_allocator(warn_if_late=False)
    sys.exit(main())
