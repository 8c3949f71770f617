"""``dispgns render``: side-by-side animation (ground truth | prediction) and a still frame grid."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from dispgns.cli import CLIError
from dispgns.cli._common import add_model_argument, check_output, load_model_argument, network_options, output_directory


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "render",
        help="animate ground truth next to a model's rollout",
        description="Draw one trajectory of a dataset split next to a prediction: either rolled out here by "
        "the model (--model, default the shipped one) or read from a predictions file written by "
        "dispgns evaluate (--predictions). Writes DIR/rollout.gif (and DIR/rollout.mp4 when ffmpeg is "
        "available), DIR/rollout_grid.png, a still grid of a few frames, and DIR/render.json (what was drawn).",
    )
    parser.add_argument("--data", required=True, metavar="DIR", help="dataset directory")
    parser.add_argument("--split", default="test_unseen", help="split (default test_unseen)")
    parser.add_argument("--index", type=int, default=0, help="trajectory index in the split (default 0)")
    add_model_argument(parser)
    parser.add_argument(
        "--predictions",
        metavar="FILE.h5",
        help="a predictions file from dispgns evaluate (instead of rolling out a model)",
    )
    parser.add_argument(
        "--out",
        default="dispgns-render",
        metavar="DIR",
        help="output directory, new or empty (default ./dispgns-render): DIR/rollout.gif, DIR/rollout.mp4, "
        "DIR/rollout_grid.png, DIR/render.json",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an earlier render in DIR (a directory with render.json)"
    )
    parser.add_argument("--start", type=int, default=0, help="first frame of the animation")
    parser.add_argument("--stop", type=int, help="frame after the last one of the animation (default: the end)")
    parser.add_argument("--stride", type=int, default=2, help="draw every STRIDE-th frame (default 2)")
    parser.add_argument("--fps", type=float, default=25.0, help="frames per second of the animation")
    parser.add_argument(
        "--grid-frames",
        metavar="F,F,...",
        help="frames of the still grid (negative: from the end; default: 5 evenly spaced)",
    )
    parser.add_argument("--no-mp4", action="store_true", help="GIF only")
    parser.set_defaults(func=run)


RENDER_FILE = "render.json"


def _frames(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values:
        raise CLIError(f"--grid-frames {text!r}: expected comma-separated frame numbers, at least one")
    return values


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from dispgns.data import DatasetError, load_dataset, read_split
    from dispgns.evaluation import predict_trajectories
    from dispgns.render import frame_grid, save_rollout_animation
    from dispgns.training.checkpoint import write_json

    check_output(args.out, overwrite=args.overwrite, marker=RENDER_FILE, kind="render")
    try:
        metadata, splits = load_dataset(args.data, [args.split])
    except DatasetError as error:
        raise CLIError(str(error)) from None
    trajectories = splits[args.split]
    if not 0 <= args.index < len(trajectories):
        raise CLIError(f"--index {args.index}: {args.split} has trajectories 0..{len(trajectories) - 1}")
    if args.stride < 1 or not 0 < args.fps < float("inf"):
        raise CLIError(f"--stride must be >= 1 and --fps a finite number > 0, got {args.stride} and {args.fps}")
    truth = trajectories[args.index]
    grid_text = _frames(args.grid_frames) if args.grid_frames is not None else None
    input_frames = None
    if args.predictions:
        if args.model or args.best:
            raise CLIError("give either --predictions or --model, not both")
        try:
            predicted = read_split(args.predictions)
        except DatasetError as error:
            raise CLIError(str(error)) from None
        if args.index >= len(predicted):
            raise CLIError(f"{args.predictions}: holds {len(predicted)} trajectories, no index {args.index}")
        prediction = np.asarray(predicted[args.index].position)
        shape = truth.position.shape
        # `dispgns evaluate --frames T` writes the first T frames of each trajectory, inputs included.
        if (
            prediction.shape[1:] != shape[1:]
            or not 1 <= prediction.shape[0] <= shape[0]
            or not np.allclose(prediction[0], truth.position[0], rtol=0, atol=1e-6)
        ):
            raise CLIError(
                f"{args.predictions}: trajectory {args.index} (shape {prediction.shape}) is not a "
                f"prediction of {args.split} trajectory {args.index} (shape {shape}): it must start "
                f"from the same frame 0{_split_note(predicted[args.index], args.split)}"
            )
    else:
        params, model_config, model_info = load_model_argument(args, dim=metadata.dim)
        if metadata.dim != model_config.dim:
            raise CLIError(
                f"{Path(args.data) / 'metadata.json'}: 'dim' is {metadata.dim}, the model has dim {model_config.dim}"
            )
        # As in evaluate: the network is local, so the same parameters roll out in the dataset's
        # box once the wall features are given its walls (with the model's own [-1, 1]^2, every
        # disk of a wider container would be pinned to a wall).
        model_config = dataclasses.replace(model_config, bounds=tuple(map(tuple, metadata.bounds)))
        input_frames = model_config.input_sequence_length
        try:
            prediction = np.asarray(
                predict_trajectories(
                    params, [truth], model_config=model_config, compiler_options=network_options(args, model_config)
                )[0]
            )
        except ValueError as error:  # the input checks: a trajectory the model cannot take
            raise CLIError(f"{args.split} trajectory {args.index}: {error}") from None
    frames = prediction.shape[0]
    truth_frames = np.asarray(truth.position)[:frames]
    grid_frames = grid_text if grid_text is not None else np.linspace(0, frames - 1, 5).round().astype(int).tolist()
    for f in grid_frames:
        if not -frames <= f < frames:
            raise CLIError(f"--grid-frames: frame {f} is outside 0..{frames - 1}")
    if not 0 <= args.start < frames or (args.stop is not None and not args.start < args.stop <= frames):
        raise CLIError(f"--start/--stop: expected 0 <= start < stop <= {frames}")
    out = Path(args.out)
    # The dataset's box (per axis, in units of L): a wide container is drawn to its aspect.
    common = dict(frame_dt=metadata.frame_dt, box_half_size=metadata.length_scale, bounds=metadata.bounds)
    with output_directory(out, overwrite=args.overwrite, marker=RENDER_FILE, kind="render") as staging:
        files = save_rollout_animation(
            str(staging / "rollout"),
            truth_frames,
            prediction,
            np.asarray(truth.radius),
            mp4=not args.no_mp4,
            input_frames=input_frames or 6,
            start=args.start,
            stop=args.stop,
            stride=args.stride,
            fps=args.fps,
            **common,
        )
        frame_grid(
            truth_frames, prediction, np.asarray(truth.radius), grid_frames, path=staging / "rollout_grid.png", **common
        )
        source = (
            {"predictions": str(args.predictions)}
            if args.predictions
            else {"model": args.model or model_info.get("source", "shipped")}
        )
        write_json(
            staging / RENDER_FILE,
            {
                "data": str(args.data),
                "split": args.split,
                "index": args.index,
                **source,
                "frames": frames,
                "bounds": [list(map(float, axis)) for axis in metadata.bounds],
            },
        )
    written = ["rollout.gif"] + (["rollout.mp4"] if files["mp4"] else []) + ["rollout_grid.png", RENDER_FILE]
    print(
        "wrote "
        + ", ".join(str(out / name) for name in written)
        + (f" (mp4 skipped: {files['mp4_skipped']})" if files["mp4_skipped"] and not args.no_mp4 else "")
    )
    return 0


def _split_note(trajectory, split: str) -> str:
    """``"; it was predicted for split X"`` when the trajectory's ``split`` attribute names another split."""
    written = trajectory.attrs.get("split")
    return f"; it was predicted for split {written!r}" if written is not None and str(written) != split else ""
