"""``dispgns export FORMAT``: write a dataset (or a rollout) in a format other tools read."""

from __future__ import annotations

import argparse

from dispgns.cli import CLIError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "export",
        help="write a dataset for other tools (LagrangeBench, ...)",
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


def run_lagrangebench(args: argparse.Namespace) -> int:
    from dispgns.data import DatasetError
    from dispgns.data.lagrangebench import UNSEEN_DIRECTORY, export_lagrangebench

    try:
        result = export_lagrangebench(args.dataset, args.out, overwrite=args.overwrite)
    except (FileExistsError, DatasetError) as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise CLIError(f"cannot export {args.dataset} to {args.out}: {error}") from None
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
