"""``dispgns export FORMAT``: write a dataset (or a rollout) in a format other tools read."""

from __future__ import annotations

import argparse

from dispgns.cli import CLIError
from dispgns.cli._common import clean_leftovers, file_error


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "export",
        help="write a dataset or rollout for other tools (LagrangeBench, OVITO, HOOMD, ParaView)",
        description="Write a dispgns dataset in a format other tools read. Refuses an existing non-empty "
        "output directory unless --overwrite; writes it whole or not at all.",
    )
    formats = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    lb = formats.add_parser(
        "lagrangebench",
        help="a directory LagrangeBench 0.2.0's H5Dataset and case_builder read",
        description="Write DATASET as a LagrangeBench dataset directory: train/valid/test .h5 files padded "
        "to one particle count (padding has particle_type -1, LagrangeBench's PAD_VALUE, and radius 0), "
        "metadata.json with every key LagrangeBench reads (statistics from the training split), "
        "and, when DATASET has test_unseen, a second dataset directory OUT/test_unseen (its test.h5 "
        "and valid.h5 hold the unseen trajectories, its train.h5 is OUT's). Each trajectory keeps "
        "its 'radius' dataset (radii / L) for LagrangeBench users to read. The export is also a "
        "valid dispgns dataset (dispgns drops the padding).",
    )
    lb.add_argument("dataset", metavar="DATASET", help="dispgns dataset directory (needs a train split)")
    lb.add_argument("--out", required=True, metavar="DIR", help="export directory to create")
    lb.add_argument("--overwrite", action="store_true", help="replace an earlier export in DIR")
    lb.set_defaults(func=run_lagrangebench)
    helps = {
        "extxyz": "extended XYZ, one multi-frame file per trajectory (OVITO, ASE): radius column, Lattice, Time",
        "gsd": "GSD, one file per trajectory (HOOMD-blue, OVITO): diameters, centred box, time in the log",
        "vtu": "a ParaView series per trajectory (NAME.vtu.series + one .vtu per frame, point data radius)",
    }
    for fmt, text in helps.items():
        sub = formats.add_parser(
            fmt,
            help=text,
            description=f"Write trajectories as {text}. Lengths in m, times in s. SOURCE is a dataset "
            "directory or one .h5 split file (e.g. a rollout from dispgns evaluate: OUT/predictions/test.h5, "
            "with --data DATASET for its L and frame spacing). OUT/export.json records what was written.",
        )
        sub.add_argument("source", metavar="SOURCE", help="dataset directory or .h5 split file")
        sub.add_argument("--out", required=True, metavar="DIR", help="export directory to create")
        sub.add_argument("--split", action="append", metavar="SPLIT", help="split(s) of a dataset (default all)")
        sub.add_argument("--index", action="append", type=int, metavar="I", help="trajectory index(es) (default all)")
        sub.add_argument("--data", metavar="DATASET", help="the dataset of a split file (L, frame spacing)")
        sub.add_argument("--L", type=float, dest="box_half_size", metavar="METRES", help="box half-size L in m")
        sub.add_argument("--frame-dt", type=float, metavar="SECONDS", help="time between frames in s")
        sub.add_argument("--overwrite", action="store_true", help="replace an earlier export in DIR")
        sub.set_defaults(func=run_format)


def run_lagrangebench(args: argparse.Namespace) -> int:
    from dispgns.data import DatasetError
    from dispgns.data.lagrangebench import UNSEEN_DIRECTORY, export_lagrangebench

    clean_leftovers(args.out)
    try:
        result = export_lagrangebench(args.dataset, args.out, overwrite=args.overwrite)
    except DatasetError as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise file_error(error, args.out) from None
    main = result[""]
    print(
        f"wrote {args.out}: LagrangeBench dataset, splits "
        + ", ".join(f"{s} {main.trajectory_counts[s]}" for s in main.splits)
        + f", {main.num_particles_max} particles per trajectory (padded), {main.sequence_length} frames"
    )
    if UNSEEN_DIRECTORY in result:
        unseen = result[UNSEEN_DIRECTORY]
        print(
            f"wrote {args.out}/{UNSEEN_DIRECTORY}: the {unseen.trajectory_counts['test']} test_unseen trajectories "
            f"as its test and valid splits (train.h5 shared with {args.out})"
        )
    return 0


def run_format(args: argparse.Namespace) -> int:
    from dispgns.data import DatasetError, read_metadata
    from dispgns.data.formats import export_trajectories

    clean_leftovers(args.out)
    try:
        metadata = read_metadata(args.data) if args.data else None
        written = export_trajectories(
            args.source,
            args.out,
            args.format,
            splits=args.split,
            indices=args.index,
            metadata=metadata,
            box_half_size=args.box_half_size,
            frame_dt=args.frame_dt,
            overwrite=args.overwrite,
        )
    except (DatasetError, ModuleNotFoundError) as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise file_error(error, args.out) from None
    print(f"wrote {args.out}: {len(written)} {args.format} file(s) (m, s), listed in {args.out}/export.json")
    return 0
