"""``dispgns import-npz``: convert one of the authors' ``.npz`` files into a dataset split."""

from __future__ import annotations

import argparse

from dispgns.cli import CLIError
from dispgns.cli._common import clean_leftovers, file_error


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-npz",
        help="import one of the authors' .npz trajectory files",
        description="Convert one of the authors' .npz files (object arrays (positions, radii), normalised by "
        "L) into one split of a dispgns dataset. Import several files into the same directory "
        "to build a whole dataset. The files are pickles: reading them can run arbitrary code, "
        "so --trust-pickle is required.",
    )
    parser.add_argument("file", metavar="FILE", help="the authors' .npz file")
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset directory (new, or an earlier import)")
    parser.add_argument(
        "--split",
        default="train",
        choices=("train", "valid", "test", "test_unseen"),
        help="split to write (default train)",
    )
    parser.add_argument(
        "--L",
        type=float,
        default=0.1,
        dest="box_half_size",
        metavar="METRES",
        help="box half-size L in m the data was normalised by (default 0.1)",
    )
    parser.add_argument(
        "--save-every",
        type=int,
        default=15,
        metavar="STEPS",
        help="Euler steps between stored frames (default 15: 1.5 ms)",
    )
    parser.add_argument(
        "--trust-pickle", action="store_true", help="allow unpickling FILE (required: only for files you trust)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace the split if DIR already has it")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dispgns.data import DatasetError, import_authors_npz

    if not args.trust_pickle:
        raise CLIError(
            f"{args.file}: the authors' .npz files hold pickled object arrays, and unpickling a file "
            f"can run arbitrary code; pass --trust-pickle if you trust this file"
        )
    if args.save_every < 1:
        raise CLIError(f"--save-every {args.save_every}: expected at least 1")
    clean_leftovers(args.out)
    try:
        metadata = import_authors_npz(
            args.file,
            args.out,
            trust_pickle=True,
            split=args.split,
            L=args.box_half_size,
            save_every=args.save_every,
            overwrite=args.overwrite,
        )
    except (DatasetError, ValueError) as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise file_error(error, args.out) from None
    counts = metadata.particle_counts[args.split]
    print(f"wrote {args.out} (split {args.split})")
    print(
        f"{len(counts)} trajectories, {metadata.sequence_length} frames each, {min(counts)}-{max(counts)} "
        f"particles per trajectory; no initial state (the physics cannot be re-run); dataset splits: "
        + ", ".join(f"{s} {metadata.trajectory_counts[s]}" for s in metadata.splits)
    )
    return 0
