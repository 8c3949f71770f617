"""``dispgns import FORMAT``: trajectories from other simulators (GSD, extended XYZ, LAMMPS dump) into a dataset."""

from __future__ import annotations

import argparse

from dispgns.cli import CLIError
from dispgns.cli._common import clean_leftovers, file_error

_HELP = {
    "gsd": "GSD files (HOOMD-blue): positions, diameters, the centred box and dimensions from the file",
    "extxyz": "extended XYZ files (OVITO, ASE) with a radius or diameter column",
    "lammps-dump": "LAMMPS text dumps (dump custom) with id, x y z (or xs ys zs) and radius or diameter",
}


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import",
        help="import trajectories from GSD, extended XYZ or LAMMPS dump files",
        description="Import trajectory files, one trajectory per file, as one split of a dispgns dataset "
        "(validated; no initial state, so the physics cannot be re-run). What a file does not say must be "
        "given: its length unit (--length-unit; LAMMPS dumps never say it), the box (--box, when the file has "
        "none), the dimension (--dim). A file's box may be rectangular (per-axis widths; tilted boxes are not "
        "supported); positions are re-centred on it and divided by the length scale L (--L, default the box's "
        "vertical half-size), so the dataset's box is bounds = +-h/L per axis, as 'dispgns generate --preset "
        "wide4' writes it. Import several splits into the same directory one after another.",
    )
    formats = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for fmt, text in _HELP.items():
        sub = formats.add_parser(fmt, help=text, description=f"Import {text}.")
        sub.add_argument("files", nargs="+", metavar="FILE", help="trajectory files, in trajectory order")
        sub.add_argument("--out", required=True, metavar="DIR", help="dataset directory (new, or an earlier import)")
        sub.add_argument(
            "--split", default="train", choices=("train", "valid", "test", "test_unseen"), help="default train"
        )
        sub.add_argument(
            "--length-unit",
            type=float,
            metavar="METRES",
            help="metres per length unit of the file (default: what the file states, e.g. dispgns's exports)",
        )
        sub.add_argument(
            "--box",
            type=_half_sizes,
            dest="box_half_size",
            metavar="METRES[,METRES...]",
            help="the box's half-size in m, one or one per axis (e.g. 0.4,0.1), for files without a box; "
            "checked against a file's box",
        )
        sub.add_argument(
            "--L",
            type=float,
            dest="length_scale",
            metavar="METRES",
            help="length scale L in m that positions and radii are divided by (default: the box's half-size "
            "along the last, vertical axis; without a box in the file and without --box, the box is [-L, L]^D)",
        )
        sub.add_argument("--dim", type=int, choices=(2, 3), help="dimension (default: the file's, else 2 if z = 0)")
        sub.add_argument("--save-every", type=int, default=15, metavar="STEPS", help="Euler steps per frame (15)")
        sub.add_argument("--dt", type=float, metavar="SECONDS", help="Euler step in s (default 1e-4)")
        sub.add_argument("--overwrite", action="store_true", help="replace the split if DIR already has it")
        sub.set_defaults(func=run)


def _half_sizes(text: str) -> float | tuple[float, ...]:
    """``"0.1"`` -> ``0.1``; ``"0.4,0.1"`` -> ``(0.4, 0.1)``."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not one or more comma-separated numbers (m)") from None
    return values[0] if len(values) == 1 else values


def run(args: argparse.Namespace) -> int:
    from dispgns.data import DatasetError
    from dispgns.data.formats import import_trajectory_files

    clean_leftovers(args.out)
    try:
        metadata = import_trajectory_files(
            args.files,
            args.format,
            args.out,
            split=args.split,
            length_unit=args.length_unit,
            box_half_size=args.box_half_size,
            length_scale=args.length_scale,
            dim=args.dim,
            save_every=args.save_every,
            dt=args.dt,
            overwrite=args.overwrite,
        )
    except (DatasetError, ValueError, ModuleNotFoundError) as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise file_error(error, args.out) from None
    counts = metadata.particle_counts[args.split]
    print(
        f"wrote {args.out} (split {args.split}): {len(counts)} trajectories, {metadata.sequence_length} frames, "
        f"{min(counts)}-{max(counts)} particles, box half-size {metadata.box_half_size} m, "
        f"L = {metadata.length_scale} m, {metadata.dim}-D"
    )
    return 0
