"""``dispgns evaluate``: full rollouts of a model on dataset splits, metrics and references."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from dispgns.cli import CLIError
from dispgns.cli._common import (
    add_distributed_arguments,
    add_model_argument,
    check_output,
    clean_leftovers,
    file_error,
    fmt,
    load_model_argument,
    local_mesh,
    mean_std,
    network_options,
    physics_options,
    sigterm_as_interrupt,
    start_distributed,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="roll out a model on test splits and score it",
        description="Roll the model out over every trajectory of the chosen splits (all frames after the "
        "first C), score each rollout (rollout MSE, RMSE in mm and diameters, horizons, wall "
        "crossings, overlaps, kinetic energy, mean height) next to the constant-velocity baseline "
        "and the chaos floor, and write OUT/metrics.json, OUT/predictions/<split>.h5 and "
        "OUT/error_curves_<split>.png.",
    )
    add_model_argument(parser)
    parser.add_argument("--data", required=True, metavar="DIR", help="dataset directory")
    parser.add_argument(
        "--splits",
        nargs="+",
        default=["test", "test_unseen"],
        metavar="SPLIT",
        help="splits to evaluate (default: test test_unseen)",
    )
    parser.add_argument(
        "--out", default="dispgns-eval", metavar="DIR", help="output directory (default ./dispgns-eval)"
    )
    parser.add_argument("--frames", type=int, metavar="T", help="evaluate the first T frames only (default: all)")
    parser.add_argument("--max-trajectories", type=int, metavar="K", help="only the first K trajectories per split")
    parser.add_argument("--batch-size", type=int, default=6, metavar="B", help="trajectories rolled out together")
    parser.add_argument("--no-chaos", action="store_true", help="skip the chaos-floor reference")
    parser.add_argument(
        "--no-statistics",
        action="store_true",
        help="skip the suspension statistics (front and settling velocity, final bed, g(r), Sinkhorn divergence, "
        "MMD) and their pictures",
    )
    add_distributed_arguments(
        parser,
        "Each group of trajectories is spread over this process's devices; with --distributed the trajectories "
        "are shared out over the processes too, and process 0 writes the results.",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an earlier evaluation in DIR (a directory with metrics.json)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    start_distributed(args)  # first: jax-md starts JAX's backend at import
    import tempfile

    import jax

    from dispgns.data import DatasetError, load_dataset
    from dispgns.files import staged_directory

    try:
        metadata, splits = load_dataset(args.data, args.splits)
    except DatasetError as error:
        raise CLIError(str(error)) from None
    params, model_config, info = load_model_argument(args, dim=metadata.dim)
    if metadata.dim != model_config.dim:
        raise CLIError(
            f"{Path(args.data) / 'metadata.json'}: 'dim' is {metadata.dim}, the model has dim {model_config.dim}"
        )
    if tuple(map(tuple, metadata.bounds)) != model_config.bounds:
        # The network is local (wall distances are clipped): the same parameters roll out in
        # any box; the box is the dataset's, so that the wall features see its walls.
        try:
            model_config = dataclasses.replace(model_config, bounds=tuple(map(tuple, metadata.bounds)))
        except ValueError as error:  # --symmetrize in a box without the floor's symmetries
            raise CLIError(f"{Path(args.data) / 'metadata.json'}: the box {metadata.bounds}: {error}") from None
    c = model_config.input_sequence_length
    if args.frames is not None and not c < args.frames <= metadata.sequence_length:
        raise CLIError(f"--frames {args.frames}: expected C = {c} < T <= {metadata.sequence_length}")
    if args.batch_size < 1 or (args.max_trajectories is not None and args.max_trajectories < 1):
        raise CLIError("--batch-size and --max-trajectories must be >= 1")
    out = Path(args.out)
    if jax.process_index() != 0:  # it computes its share of the rollouts; process 0 writes the results
        with tempfile.TemporaryDirectory() as scratch:
            _evaluate(args, params, model_config, info, metadata, splits, Path(scratch))
        return 0
    check_output(out, overwrite=args.overwrite, marker=METRICS_FILE, kind="evaluation")
    clean_leftovers(out)
    # Everything is written into a staging directory renamed to --out at the
    # end: an interrupted or failed evaluation leaves nothing half-written.
    try:
        with (
            sigterm_as_interrupt(),
            staged_directory(out, overwrite=args.overwrite, marker=METRICS_FILE, kind="evaluation") as staging,
        ):
            report = _evaluate(args, params, model_config, info, metadata, splits, staging)
    except OSError as error:
        raise file_error(error, out) from None
    print(table(report))
    pictures = "error_curves_*.png" + ("" if args.no_statistics else ", statistics_*.png")
    print(f"wrote {out / METRICS_FILE}, {out / 'predictions'}/*.h5 and {out}/{pictures}")
    return 0


METRICS_FILE = "metrics.json"


def _evaluate(args, params, model_config, info, metadata, splits, out: Path) -> dict:
    """Roll out, score and write predictions, plots and metrics into ``out``; returns the report."""
    from tqdm import tqdm

    from dispgns.data import Trajectory, write_split
    from dispgns.data.format import split_filename
    from dispgns.evaluation import evaluate_trajectories
    from dispgns.render import plot_rollout_errors, plot_statistics
    from dispgns.training.checkpoint import write_json

    c = model_config.input_sequence_length
    (out / "predictions").mkdir()
    frames = args.frames or metadata.sequence_length
    report = {
        "model": {"source": info.get("source"), "config": model_config.to_dict(), "record": info.get("record", {})},
        "dataset": {"path": str(Path(args.data).absolute()), "preset": metadata.preset, "seed": metadata.seed},
        "frames": frames,
        "splits": {},
    }
    for split, trajectories in splits.items():
        trajectories = trajectories[: args.max_trajectories] if args.max_trajectories else trajectories
        total = len(trajectories) * (frames - c)
        bar = tqdm(
            total=total,
            desc=f"{split} rollouts",
            unit=" steps",
            file=sys.stderr,
            dynamic_ncols=True,
            disable=args.no_progress,
            leave=False,
        )

        def progress(stage, amount, bar=bar, split=split):
            if stage == "rollout":
                bar.update(amount)
            else:
                bar.set_description(f"{split} chaos floor done")

        chaos = not args.no_chaos and metadata.has_initial_state
        try:
            result = evaluate_trajectories(
                params,
                trajectories,
                model_config=model_config,
                box_half_size=metadata.length_scale,
                frame_dt=metadata.frame_dt,
                bounds=metadata.bounds,
                physics_config=metadata.physics_config,
                save_every=metadata.save_every,
                chaos_floor=chaos,
                chaos_x64=metadata.precision == "float64",
                n_frames=frames,
                batch_size=args.batch_size,
                progress=progress,
                mesh=local_mesh(),
                compiler_options=network_options(args, model_config),
                physics_compiler_options=physics_options(args),
                statistics=not args.no_statistics,
            )
        except ValueError as error:  # the host conveniences' input checks: a dataset the model cannot take
            raise CLIError(f"{Path(args.data) / (split + '.h5')}: {error}") from None
        finally:
            bar.close()
        predicted = [
            Trajectory(
                position=p, radius=t.radius, attrs={"source_index": k, "split": split, "model": str(info.get("source"))}
            )
            for k, (p, t) in enumerate(zip(result["predictions"], trajectories))
        ]
        write_split(out / "predictions" / split_filename(split), predicted, predicted=True, bounds=metadata.bounds)
        plot_rollout_errors(
            result["summary"],
            frame_dt=metadata.frame_dt,
            title=f"{split}: rollout error",
            path=out / f"error_curves_{split}.png",
        )
        if not args.no_statistics:
            plot_statistics(
                result["summary"],
                frame_dt=metadata.frame_dt,
                box_half_size=metadata.length_scale,
                title=f"{split}: suspension statistics (mean over {len(trajectories)} trajectories)",
                path=out / f"statistics_{split}.png",
            )
        report["splits"][split] = {
            "summary": result["summary"],
            "trajectories": result["metrics"],
            "chaos_floor": result["chaos_floor"],
        }
    write_json(out / METRICS_FILE, report)
    return report


ROWS = (
    ("rollout MSE", "mse"),
    ("RMSE (mm)", "rmse_mm"),
    ("RMSE (diameters)", "rmse_diameters"),
    ("MSE h10", "mse_h10"),
    ("MSE h100", "mse_h100"),
    ("constant velocity MSE", "constant_velocity_mse"),
    ("chaos floor MSE", "chaos_floor_mse"),
    ("model / constant velocity", "mse_over_constant_velocity"),
    ("wall crossings (particle-frames)", "wall_violations_total"),
    ("overlapping pairs (sum)", "overlaps_total"),
    ("overlapping pairs, truth", "overlaps_truth_total"),
)

# The suspension statistics (shown when they were computed): each for the model, then the same distance
# for the constant-velocity baseline and for the chaos floor, all against the ground truth.
STATISTICS_ROWS = (
    ("mean height error (mm, mean abs)", "mean_height_mean_abs_error_mm"),
    ("  constant velocity", "constant_velocity_mean_height_mean_abs_error_mm"),
    ("  chaos floor", "chaos_floor_mean_height_mean_abs_error_mm"),
    ("front settling velocity, truth (mm/s)", "front_settling_velocity_truth_mm_s"),
    ("front settling velocity error (mm/s)", "front_settling_velocity_error_mm_s"),
    ("  constant velocity", "constant_velocity_front_settling_velocity_error_mm_s"),
    ("  chaos floor", "chaos_floor_front_settling_velocity_error_mm_s"),
    ("final bed: particles in another slab", "height_profile_distance"),
    ("  constant velocity", "constant_velocity_height_profile_distance"),
    ("  chaos floor", "chaos_floor_height_profile_distance"),
    ("final bed area fraction, truth", "bed_area_fraction_truth"),
    ("final bed area fraction error", "bed_area_fraction_error"),
    ("  constant velocity", "constant_velocity_bed_area_fraction_error"),
    ("  chaos floor", "chaos_floor_bed_area_fraction_error"),
    ("final g(r) L1", "rdf_l1"),
    ("  constant velocity", "constant_velocity_rdf_l1"),
    ("  chaos floor", "chaos_floor_rdf_l1"),
    ("final Sinkhorn, positions (L^2)", "sinkhorn_position_final"),
    ("  chaos floor", "chaos_floor_sinkhorn_position_final"),
    ("final Sinkhorn, velocities ((m/s)^2)", "sinkhorn_velocity_final"),
    ("  chaos floor", "chaos_floor_sinkhorn_velocity_final"),
    ("final MMD^2, positions", "mmd_position_final"),
    ("  constant velocity", "constant_velocity_mmd_position_final"),
    ("  chaos floor", "chaos_floor_mmd_position_final"),
    ("final MMD^2, velocities", "mmd_velocity_final"),
    ("  constant velocity", "constant_velocity_mmd_velocity_final"),
    ("  chaos floor", "chaos_floor_mmd_velocity_final"),
)


def table(report) -> str:
    """A Markdown table: one column per split, mean ± std over its trajectories."""
    splits = list(report["splits"])
    lines = [
        "| metric | " + " | ".join(f"{s} ({report['splits'][s]['summary']['n_trajectories']})" for s in splits) + " |",
        "| --- |" + " --- |" * len(splits),
    ]
    with_statistics = any("rdf_l1" in report["splits"][s]["summary"] for s in splits)
    for label, key in ROWS + (STATISTICS_ROWS if with_statistics else ()):
        cells = []
        for s in splits:
            summary = report["splits"][s]["summary"]
            if key.endswith("_total"):
                entry = summary.get(key)
                cells.append("-" if entry is None else fmt(int(round(entry["mean"] * entry["n"]))))
            else:
                cells.append(mean_std(summary, key))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
