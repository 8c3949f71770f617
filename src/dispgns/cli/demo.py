"""``dispgns demo``: the main job. A fresh ground-truth trajectory, the shipped model's rollout, metrics, pictures."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from types import SimpleNamespace

from dispgns.cli import CLIError
from dispgns.cli._common import (
    add_model_argument,
    check_output,
    fmt,
    load_model_argument,
    network_options,
    output_directory,
    physics_options,
)

DEFAULT_SEED = 2025
METRICS_FILE = "metrics.json"
DEFAULT_RADII_MM = "2.25,3.25,3.75,4.75"  # one of the paper's unseen-radii groups
# Frames by default: the paper's 500 in its box; in the wide containers fewer, so that the demo stays
# within minutes on a 2-core CPU (wide16 holds ~15x the paper's disks, and the learned simulator's
# cost grows linearly with them).
DEFAULT_FRAMES = {"paper": 500, "wide4": 300, "wide16": 150}


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="simulate a fresh trajectory and compare the shipped model's rollout with it (the main job)",
        description="Simulate a fresh sedimentation trajectory with the ground-truth physics (radii never "
        "seen in training by default), roll the shipped learned simulator out from its first C "
        "frames, print the errors next to the constant-velocity baseline and the chaos floor, and "
        "write a side-by-side animation, a frame grid, an error-curve plot and metrics.json.",
    )
    parser.add_argument(
        "--seed", type=int, default=DEFAULT_SEED, help=f"seed of the initial state (default {DEFAULT_SEED})"
    )
    parser.add_argument(
        "--radii",
        default=DEFAULT_RADII_MM,
        metavar="MM[,MM...]",
        help=f"radii in mm drawn for the particles (default {DEFAULT_RADII_MM}: unseen in training)",
    )
    parser.add_argument(
        "--dim",
        type=int,
        choices=(2, 3),
        default=2,
        help="2: disks in the paper's 0.2 m square (default); 3: spheres in the 8 cm cube of "
        "'dispgns generate --preset paper3d' with the shipped 3-D model (sedimentation-3d) or --model PATH",
    )
    parser.add_argument(
        "--preset",
        choices=tuple(DEFAULT_FRAMES),
        default="paper",
        help="the 2-D container: paper, the paper's 0.2 m square (default); wide4, wide16: the containers "
        "of 'dispgns generate --preset wide4/wide16', 4x and 16x wider, same height (~700 and ~2,800 "
        "disks; the shipped model was trained in the paper's box only)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        metavar="T",
        help="frames to simulate (default 500 in the paper's box, 300 in wide4, 150 in wide16, 200 in 3-D as paper3d)",
    )
    parser.add_argument(
        "--out",
        default="dispgns-demo",
        metavar="DIR",
        help="output directory, new or empty (default ./dispgns-demo): rollout.gif, rollout.mp4, "
        "rollout_grid.png, error_curve.png, metrics.json",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an earlier demo in DIR (a directory with metrics.json)"
    )
    add_model_argument(parser)
    parser.add_argument("--stride", type=int, default=2, help="animation draws every STRIDE-th frame (default 2)")
    parser.add_argument("--no-mp4", action="store_true", help="GIF only")
    parser.add_argument("--no-chaos", action="store_true", help="skip the chaos-floor reference")
    parser.set_defaults(func=run)


def _radii(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise CLIError(f"--radii {text!r}: expected comma-separated radii in mm, e.g. 2.25,3.25") from None
    if not values or any(not 0 < v < 50 for v in values):
        raise CLIError(f"--radii {text!r}: expected radii between 0 and 50 mm (half the box half-size)")
    return [round(v * 1e-3, 12) for v in values]


def run(args: argparse.Namespace) -> int:
    import jax
    import numpy as np

    from dispgns.data.generate import preset
    from dispgns.evaluation import chaos_floor_trajectories, predict_trajectories
    from dispgns.metrics import rollout_metrics
    from dispgns.physics import PhysicsConfig, PlacementError, sample_initial_state, simulate
    from dispgns.render import frame_grid, plot_rollout_errors, save_rollout_animation
    from dispgns.training.checkpoint import write_json

    radii = _radii(args.radii)
    if args.dim == 3 and args.preset != "paper":
        raise CLIError(f"--preset {args.preset}: a 2-D container; --dim 3 uses the paper3d cube")
    out = Path(args.out)
    # Refused before minutes of computing: an existing output needs --overwrite.
    check_output(out, overwrite=args.overwrite, marker=METRICS_FILE, kind="demo")
    params, model_config, info = load_model_argument(args, dim=args.dim)
    if model_config.dim != args.dim:
        raise CLIError(f"--dim {args.dim}: the model is {model_config.dim}-D ({info.get('source')})")
    if args.frames is None:
        args.frames = DEFAULT_FRAMES[args.preset] if args.dim == 2 else 200
    c = model_config.input_sequence_length
    if args.frames <= c:
        raise CLIError(f"--frames {args.frames}: expected more than C = {c} input frames")
    if args.stride < 1:
        raise CLIError(f"--stride {args.stride}: expected >= 1")
    bounds = None
    save_every = 15
    if args.dim == 3:
        # The paper3d physics: its shorter Euler step (stable in a bed of spheres), 1.5 ms frames.
        spec = preset("paper3d")
        config, save_every = spec.physics, spec.save_every
        half = config.box_half_size
    elif args.preset == "paper":
        config = PhysicsConfig()
        half = config.box_half_size
    else:
        spec = preset(args.preset)
        config, half, bounds = spec.physics, spec.length_scale, spec.bounds
        # The network is local: the shipped parameters roll out in the wide box once its wall
        # features see that box's walls (as dispgns evaluate does with a dataset's bounds).
        model_config = dataclasses.replace(model_config, bounds=bounds)
    frame_dt = save_every * config.dt
    box = "x".join(f"{2 * h:g}" for h in config.half_sizes(args.dim))
    print(
        f"dispgns demo: seed {args.seed}, radii {', '.join(f'{r * 1e3:g}' for r in radii)} mm, "
        f"{args.frames} frames ({args.frames * frame_dt:.2f} s), {args.dim}-D, box {box} m"
        f"{'' if bounds is None else f' ({args.preset})'}; model: {info.get('source')}",
        flush=True,
    )

    timings = {}
    start = time.perf_counter()
    try:
        state = sample_initial_state(jax.random.PRNGKey(args.seed), radii, config, dim=args.dim)
    except (PlacementError, ValueError) as error:
        raise CLIError(f"--radii {args.radii}: {error}") from None
    truth = (
        np.asarray(
            simulate(
                state.position,
                state.velocity,
                state.radius,
                config,
                n_frames=args.frames,
                save_every=save_every,
                compiler_options=physics_options(args),
            )
        )
        / half
    )
    truth = truth.astype(np.float32)
    timings["physics_s"] = time.perf_counter() - start
    n = truth.shape[1]
    radius = (np.asarray(state.radius, np.float64) / half).astype(np.float32)
    print(
        f"ground truth: {n} particles, {(args.frames - 1) * save_every} Euler steps in {timings['physics_s']:.1f} s",
        flush=True,
    )

    start = time.perf_counter()

    prediction = predict_trajectories(
        params,
        [SimpleNamespace(position=truth, radius=radius)],
        model_config=model_config,
        compiler_options=network_options(args, model_config),
    )[0]
    timings["gnn_rollout_s"] = time.perf_counter() - start
    steps = args.frames - c
    print(
        f"learned simulator: {steps} steps in {timings['gnn_rollout_s']:.1f} s "
        f"({1e3 * timings['gnn_rollout_s'] / steps:.1f} ms/step, compilation included)",
        flush=True,
    )

    chaos = None
    if not args.no_chaos:
        start = time.perf_counter()

        initial = SimpleNamespace(
            initial_position=np.asarray(state.position, np.float64),
            initial_velocity=np.asarray(state.velocity, np.float64),
            initial_radius=np.asarray(state.radius, np.float64),
        )
        chaos = chaos_floor_trajectories(
            [initial], config, n_frames=args.frames, save_every=save_every, compiler_options=physics_options(args)
        )[0]
        timings["chaos_floor_s"] = time.perf_counter() - start

    metrics = rollout_metrics(
        prediction,
        truth,
        radius,
        box_half_size=half,
        input_frames=c,
        frame_dt=frame_dt,
        chaos_floor=None if chaos is None else chaos.astype(np.float32),
        physics_config=config,
        bounds=bounds,
    )
    print("writing pictures ...", flush=True)
    start = time.perf_counter()
    with output_directory(out, overwrite=args.overwrite, marker=METRICS_FILE, kind="demo") as staging:
        files = save_rollout_animation(
            str(staging / "rollout"),
            truth,
            prediction,
            radius,
            mp4=not args.no_mp4,
            input_frames=c,
            stride=args.stride,
            frame_dt=frame_dt,
            box_half_size=half,
            bounds=bounds,
        )
        grid_frames = np.linspace(0, args.frames - 1, 5).round().astype(int).tolist()
        frame_grid(
            truth,
            prediction,
            radius,
            grid_frames,
            frame_dt=frame_dt,
            box_half_size=half,
            bounds=bounds,
            path=staging / "rollout_grid.png",
        )
        plot_rollout_errors(
            metrics,
            frame_dt=frame_dt,
            title=f"demo rollout (seed {args.seed}, N = {n})",
            path=staging / "error_curve.png",
        )
        timings["pictures_s"] = time.perf_counter() - start
        report = {
            "seed": args.seed,
            "preset": args.preset if args.dim == 2 else "paper3d",
            "box_half_sizes_m": list(config.half_sizes(args.dim)),
            "radii_mm": [r * 1e3 for r in radii],
            "n_particles": n,
            "frames": args.frames,
            "model": {"source": info.get("source"), "config": model_config.to_dict()},
            "timings": timings,
            "metrics": metrics,
        }
        write_json(staging / METRICS_FILE, report)
    print()
    print(summary_table(metrics, timings, steps, (args.frames - 1) * save_every))
    print()
    written = (
        [out / "rollout.gif"]
        + ([out / "rollout.mp4"] if files["mp4"] else [])
        + [out / "rollout_grid.png", out / "error_curve.png", out / METRICS_FILE]
    )
    print("wrote:")
    for path in written:
        print(f"  {path}")
    return 0


def _ratio(metrics) -> str:
    ratio = metrics["mse_over_constant_velocity"]
    if not ratio > 0:
        return "model MSE not finite" if not metrics["finite"] else "baseline MSE is 0"
    if ratio >= 1:
        return f"model is {ratio:.1f}x higher"
    return f"model is {1 / ratio:.0f}x lower" if ratio <= 0.1 else f"model is {1 / ratio:.1f}x lower"


def summary_table(metrics, timings, steps: int, euler_steps: int) -> str:
    """The demo's results as a Markdown table."""
    rows = [
        ("rollout MSE (normalised units²)", fmt(metrics["mse"])),
        ("RMSE", f"{metrics['rmse_mm']:.2f} mm = {metrics['rmse_diameters']:.2f} mean diameters"),
        ("MSE at 10 / 100 steps", f"{fmt(metrics['mse_h10'])} / {fmt(metrics['mse_h100'])}"),
        ("constant-velocity baseline MSE", f"{fmt(metrics['constant_velocity_mse'])} ({_ratio(metrics)})"),
    ]
    if "chaos_floor_mse" in metrics:
        rows.append(("chaos floor MSE (physics, 1e-6 L perturbation)", fmt(metrics["chaos_floor_mse"])))
    rows += [
        ("wall crossings (particle-frames beyond 0.1 a)", str(metrics["wall_violations_total"])),
        ("overlapping pairs, max per frame (truth)", f"{metrics['overlaps_max']} ({metrics['overlaps_truth_max']})"),
        ("time: ground-truth physics", f"{timings['physics_s']:.1f} s ({euler_steps} Euler steps, with compilation)"),
        ("time: learned simulator", f"{timings['gnn_rollout_s']:.1f} s ({steps} steps, with compilation)"),
    ]
    if "chaos_floor_s" in timings:
        rows.append(("time: chaos floor (physics again)", f"{timings['chaos_floor_s']:.1f} s"))
    if "pictures_s" in timings:
        rows.append(("time: writing pictures and metrics", f"{timings['pictures_s']:.1f} s"))
    width = max(len(r[0]) for r in rows)
    lines = [f"| {'metric'.ljust(width)} | value |", f"| {'-' * width} | --- |"]
    lines += [f"| {label.ljust(width)} | {value} |" for label, value in rows]
    return "\n".join(lines)
