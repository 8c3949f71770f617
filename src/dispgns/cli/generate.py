"""``dispgns generate``: simulate a ground-truth dataset (HDF5 splits + metadata.json)."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import warnings

from dispgns.cli import CLIError
from dispgns.cli._common import (
    check_writable_place,
    clean_leftovers,
    file_error,
    physics_options,
    sigterm_as_interrupt,
)

_COUNT_OPTIONS = (("train", "train"), ("valid", "valid"), ("test", "test"), ("unseen", "test_unseen"))


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "generate",
        help="simulate a ground-truth dataset",
        description="Simulate sedimentation trajectories with the ground-truth physics and write a dataset "
        "directory (train/valid/test/test_unseen .h5 files and metadata.json). Deterministic "
        "for a seed; written atomically.",
    )
    parser.add_argument(
        "--preset",
        choices=("paper", "paper3d", "tiny", "wide4", "wide16"),
        default="paper",
        help="paper: the paper's 40 trajectories of 500 frames (default); paper3d: spheres in an 8 cm "
        "cube with the paper's radii (54 trajectories of 200 frames, 180-360 spheres, Euler step 2.5e-5 s); "
        "tiny: 5 small trajectories for tests and demos; wide4, wide16: containers 4x and 16x wider than the paper's "
        "box (same height, its radii lists, 14 trajectories of ~600-900 and ~2,400-3,600 disks)",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset directory to create")
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed in [0, 2^32) (default 0); every trajectory's key derives from it",
    )
    parser.add_argument("--x64", action="store_true", help="simulate in float64 (slower; default float32)")
    parser.add_argument("--frames", type=int, metavar="T", help="frames per trajectory (default: the preset's)")
    for option, split in _COUNT_OPTIONS:
        parser.add_argument(
            f"--{option}-count",
            type=int,
            metavar="K",
            dest=f"count_{split}",
            help=f"number of {split} trajectories (0 drops the split)",
        )
    parser.add_argument(
        "--radii", metavar="MM[,MM...]", help="radii in mm drawn for train, valid and test, e.g. 2,2.5,3,3.5,4,4.5,5"
    )
    parser.add_argument(
        "--unseen-radii",
        action="append",
        metavar="MM[,MM...]",
        help="radii in mm of one group of test_unseen trajectories; repeat for several "
        "groups (the count is spread evenly over them)",
    )
    parser.add_argument(
        "--batch-size",
        type=int,
        metavar="B",
        help="at most B trajectories simulated together, to save memory (default: no limit; "
        "groups of similar particle count are chosen automatically). In float32 the "
        "grouping changes the rounding of the chaotic dynamics: the same files need the "
        "same seed, spec and batch size (recorded in metadata.json)",
    )
    parser.add_argument(
        "--max-frame-move",
        type=float,
        default=None,
        metavar="R",
        help="refuse the dataset (exit 2, nothing written) when a particle moves more than R of its trajectory's "
        "smallest radius between two frames: the explicit Euler step blew up (default 2; healthy runs stay "
        "under ~0.9, and moves past 1 are reported as warnings; with 'inf' only positions that are not finite "
        "refuse it)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset in DIR")
    parser.set_defaults(func=run)


def _parse_mm(text: str, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        raise CLIError(f"{option} {text!r}: expected comma-separated radii in mm, e.g. 2,2.5,3") from None
    if not values or any(not (v > 0) for v in values):
        raise CLIError(f"{option} {text!r}: expected radii > 0 mm")
    return tuple(round(v * 1e-3, 12) for v in values)


def build_spec(args: argparse.Namespace):
    """The :class:`DatasetSpec` the arguments describe."""
    from dispgns.data.generate import preset

    spec = preset(args.preset)
    counts = {}
    for option, split in _COUNT_OPTIONS:
        value = getattr(args, f"count_{split}")
        if value is not None:
            if value < 0:
                raise CLIError(f"--{option}-count {value}: expected a count >= 0")
            counts[split] = value
    if args.frames is not None and args.frames < 2:
        raise CLIError(f"--frames {args.frames}: expected at least 2 frames")
    radii = _parse_mm(args.radii, "--radii") if args.radii else None
    unseen = [_parse_mm(text, "--unseen-radii") for text in args.unseen_radii] if args.unseen_radii else None
    unseen_count = counts.get("test_unseen", spec.counts.get("test_unseen", 0))
    if unseen is not None and 0 < unseen_count < len(unseen):
        raise CLIError(
            f"--unseen-radii gives {len(unseen)} groups but only {unseen_count} test_unseen "
            f"trajectories are asked for (--unseen-count): every group needs at least one"
        )
    try:
        return spec.replace(
            n_frames=args.frames,
            counts=counts,
            radii_m=radii,
            unseen_radii_m=unseen,
            precision="float64" if args.x64 else "float32",
        )
    except ValueError as error:
        raise CLIError(str(error)) from None


class _Bars:
    """One tqdm bar per generation stage."""

    labels = {"place": "placing particles", "simulate": "simulating frames"}

    def __init__(self):
        self.stage = None
        self.bar = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = tqdm(
                total=total,
                desc=self.labels.get(stage, stage),
                unit=" traj" if stage == "place" else " frames",
                dynamic_ncols=True,
                leave=False,
            )
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run(args: argparse.Namespace) -> int:
    import jax

    from dispgns.data import DatasetError, generate_dataset
    from dispgns.data.generate import MAX_FRAME_MOVE, FrameMoveWarning, UnstableSimulationError
    from dispgns.physics import PlacementError

    spec = build_spec(args)
    if args.batch_size is not None and args.batch_size < 1:
        raise CLIError(f"--batch-size {args.batch_size}: expected at least 1")
    max_frame_move = MAX_FRAME_MOVE if args.max_frame_move is None else args.max_frame_move
    if not max_frame_move > 0:
        raise CLIError(f"--max-frame-move {args.max_frame_move}: expected a number of radii > 0")
    start = time.perf_counter()
    bars = _Bars()
    # float64 must be on before the first array of the run is made; the
    # context keeps it local to this command (main() may be called in-process).
    precision = jax.enable_x64(True) if args.x64 else contextlib.nullcontext()
    check_writable_place(args.out)  # before minutes of simulation
    clean_leftovers(args.out)
    caught = []
    try:
        with precision, sigterm_as_interrupt(), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", FrameMoveWarning)
            metadata = generate_dataset(
                spec,
                args.out,
                args.seed,
                overwrite=args.overwrite,
                batch_size=args.batch_size,
                progress=bars,
                compiler_options=physics_options(args),
                max_frame_move=max_frame_move,
            )
    except (PlacementError, DatasetError, UnstableSimulationError, ValueError) as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise file_error(error, args.out) from None
    finally:
        bars.close()
        # Also on an error or Ctrl-C: the trajectories checked before it were at their stability limit.
        for warning in caught:
            if issubclass(warning.category, FrameMoveWarning):
                print(f"warning: {warning.message}", file=sys.stderr)
            else:  # recorded only because record=True takes them all: shown as Python would have
                warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
    elapsed = time.perf_counter() - start
    counts = metadata.trajectory_counts
    particles = [n for split in metadata.splits for n in metadata.particle_counts[split]]
    per_split = ", ".join(f"{split} {counts[split]}" for split in metadata.splits)
    print(f"wrote {args.out}")
    print(
        f"{sum(counts.values())} trajectories ({per_split}), {metadata.sequence_length} frames each, "
        f"{min(particles)}-{max(particles)} particles per trajectory, {metadata.precision}, "
        f"seed {metadata.seed}, {elapsed:.1f} s"
    )
    return 0
