"""Paired comparison of two models on the same trajectories, pooled over several evaluations (issue 19).

    python experiments/accuracy/paired.py --out runs/JM.json \
        shipped=runs/sel-valid-J/metrics.json,runs/seed9-emaJ/metrics.json \
        M=runs/sel-valid-M/metrics.json,runs/sel-s9-M/metrics.json

Each argument is NAME=PATH[,PATH...], the ``metrics.json`` files of ``dispgns evaluate`` of one model; the first
argument is the baseline. The trajectories of all files (every split of each, in file order) are pooled, and the
models must have been evaluated on the same trajectories in the same order (checked: equal counts and particle
numbers). Session 13's selection set is the 12 trajectories of ``acc400-valid`` and the 48 of ``paper-seed9``'s
``test`` split: 60 chaotic rollouts, enough to resolve a few percent paired where 12 cannot. For each horizon
(1, 10, 100 frames and the full rollout) this writes each model's mean, their ratio, the mean paired difference
(candidate minus baseline) with its standard error, and on how many trajectories the candidate is lower.
With ``--windows``, the same for the mean MSE over windows of frames (1-10, 11-50, ..., 401 to the last; the first
repeats ``mse_h10``), each with its share of the baseline's full-rollout MSE: where along the rollout a gain holds
and where it fades.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dispgns.files import write_atomic

HORIZONS = ("mse_h1", "mse_h10", "mse_h100", "mse")
# Predicted frames, 1-based and inclusive; a window is cut at the rollout's last frame (the last one ends there).
WINDOWS = ((1, 10), (11, 50), (51, 100), (101, 200), (201, 300), (301, 400), (401, None))


def trajectory_records(path: Path, keys: tuple[str, ...]) -> list[dict]:
    """Every trajectory's record of every split of a ``metrics.json`` of ``dispgns evaluate``, in file order.

    Raises ValueError naming the file when it cannot be read or a record lacks one of ``keys``.
    """
    try:
        records = [t for split in json.loads(path.read_text())["splits"].values() for t in split["trajectories"]]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise ValueError(f"{path}: not a metrics.json of dispgns evaluate ({error!r})") from None
    if not records:
        raise ValueError(f"{path}: no trajectories")
    for index, record in enumerate(records):
        missing = [key for key in keys if key not in record]
        if missing:
            raise ValueError(f"{path}: trajectory {index} has no {', '.join(missing)}")
    return records


def pooled(paths: list[Path], windows: bool = False) -> dict[str, np.ndarray]:
    """Per-trajectory figures of every horizon, and the particle counts, pooled over ``paths`` in order.

    With ``windows``, also every trajectory's per-frame MSE (``per_frame_mse``, trajectories x frames), which
    must have one length.
    """
    keys = (*HORIZONS, "n_particles") + (("per_frame_mse",) if windows else ())
    records = [record for path in paths for record in trajectory_records(path, keys)]
    columns = {name: np.asarray([r[name] for r in records], dtype=float) for name in (*HORIZONS, "n_particles")}
    if windows:
        lengths = sorted({len(r["per_frame_mse"]) for r in records})
        if len(lengths) != 1:
            raise ValueError(f"{', '.join(map(str, paths))}: rollouts of {lengths} frames; windows need one length")
        columns["per_frame_mse"] = np.asarray([r["per_frame_mse"] for r in records], dtype=float)
    return columns


def _row(a: np.ndarray, b: np.ndarray, names: tuple[str, str]) -> dict:
    """Means, ratio, paired difference (b - a), its standard error, and on how many b is lower."""
    difference = b - a
    return {
        names[0]: float(a.mean()),
        names[1]: float(b.mean()),
        "ratio": float(b.mean() / a.mean()),
        "paired_difference": float(difference.mean()),
        "paired_standard_error": float(difference.std(ddof=1) / np.sqrt(a.size)),
        f"{names[1]}_lower_on": int(np.sum(difference < 0)),
        "n": int(a.size),
    }


def compare(baseline: dict[str, np.ndarray], candidate: dict[str, np.ndarray], names: tuple[str, str]) -> dict:
    """Means, ratio, paired difference (candidate - baseline) and its standard error, per horizon.

    When both carry ``per_frame_mse`` (:func:`pooled` with ``windows``), also per window of :data:`WINDOWS`
    (``frames_A-B``: the mean over those frames of each trajectory), with the window's share of the baseline's
    summed per-frame MSE (its weight in the full-rollout MSE, the mean over all frames).
    """
    if baseline["n_particles"].shape != candidate["n_particles"].shape or np.any(
        baseline["n_particles"] != candidate["n_particles"]
    ):
        raise ValueError(
            f"{names[0]} and {names[1]} were not evaluated on the same trajectories: "
            f"{baseline['n_particles'].size} against {candidate['n_particles'].size} trajectories, "
            "or different particle counts in the same position"
        )
    rows = {horizon: _row(baseline[horizon], candidate[horizon], names) for horizon in HORIZONS}
    if "per_frame_mse" in baseline:
        a, b = baseline["per_frame_mse"], candidate["per_frame_mse"]
        if a.shape != b.shape:
            raise ValueError(f"{names[0]}'s rollouts have {a.shape[1]} frames, {names[1]}'s {b.shape[1]}")
        frames = a.shape[1]
        for first, last in WINDOWS:
            if first > frames:
                break
            last = min(last or frames, frames)
            window = slice(first - 1, last)
            rows[f"frames_{first}-{last}"] = _row(a[:, window].mean(axis=1), b[:, window].mean(axis=1), names)
            rows[f"frames_{first}-{last}"]["share_of_baseline_mse"] = float(a[:, window].sum() / a.sum())
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", nargs=2, metavar="NAME=PATH[,PATH...]", help="baseline first, then candidate")
    parser.add_argument("--out", type=Path, help="write the comparison here as JSON (also printed)")
    parser.add_argument("--windows", action="store_true", help="also compare the MSE over windows of frames")
    args = parser.parse_args(argv)
    named = []
    for argument in args.models:
        name, _, paths = argument.partition("=")
        if not name or not paths:
            parser.error(f"{argument!r}: expected NAME=PATH[,PATH...]")
        named.append((name, [Path(p) for p in paths.split(",")]))
    (base_name, base_paths), (cand_name, cand_paths) = named
    try:
        rows = compare(pooled(base_paths, args.windows), pooled(cand_paths, args.windows), (base_name, cand_name))
    except ValueError as error:
        print(f"paired.py: {error}", file=sys.stderr)
        return 1
    report = {
        "what": f"per horizon, the mean over the pooled trajectories of each model and the paired difference "
        f"({cand_name} - {base_name})",
        "files": {base_name: [str(p) for p in base_paths], cand_name: [str(p) for p in cand_paths]},
        "horizons": rows,
    }
    text = json.dumps(report, indent=1)
    if args.out:
        write_atomic(args.out, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
