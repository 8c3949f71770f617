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
With ``--windows``, the same for the mean MSE over windows of frames (1-10, 11-50, ..., 401-494), each with its
share of the baseline's full-rollout MSE: where along the rollout a gain holds and where it fades.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HORIZONS = ("mse_h1", "mse_h10", "mse_h100", "mse")
# Predicted frames, 1-based and inclusive; the last window ends at the rollout's last frame.
WINDOWS = ((1, 10), (11, 50), (51, 100), (101, 200), (201, 300), (301, 400), (401, None))


def pooled(paths: list[Path], windows: bool = False) -> dict[str, np.ndarray]:
    """Per-trajectory figures of every horizon, and the particle counts, pooled over ``paths`` in order.

    With ``windows``, also each trajectory's mean MSE over every window of :data:`WINDOWS` (``frames_A-B``).
    """
    columns: dict[str, list[float]] = {name: [] for name in (*HORIZONS, "n_particles")}
    for path in paths:
        for record in json.loads(path.read_text())["splits"].values():
            for trajectory in record["trajectories"]:
                for name in HORIZONS + ("n_particles",):
                    columns[name].append(trajectory[name])
                if windows:
                    per_frame = np.asarray(trajectory["per_frame_mse"], dtype=float)
                    for first, last in WINDOWS:
                        name = f"frames_{first}-{last or per_frame.size}"
                        columns.setdefault(name, []).append(float(per_frame[first - 1 : last].mean()))
    if len({len(values) for values in columns.values()}) != 1:
        raise ValueError(f"{', '.join(map(str, paths))}: the trajectories' rollouts differ in length")
    return {name: np.asarray(values, dtype=float) for name, values in columns.items()}


def compare(baseline: dict[str, np.ndarray], candidate: dict[str, np.ndarray], names: tuple[str, str]) -> dict:
    """Means, ratio, paired difference (candidate - baseline) and its standard error, per horizon."""
    if baseline["n_particles"].shape != candidate["n_particles"].shape or np.any(
        baseline["n_particles"] != candidate["n_particles"]
    ):
        raise ValueError(
            f"{names[0]} and {names[1]} were not evaluated on the same trajectories: "
            f"{baseline['n_particles'].size} against {candidate['n_particles'].size} trajectories, "
            "or different particle counts in the same position"
        )
    n = baseline["mse"].size
    rows = {}
    for horizon in [name for name in baseline if name != "n_particles"]:
        if horizon not in candidate:
            raise ValueError(f"{names[1]}'s rollouts end before {horizon}, {names[0]}'s do not")
        a, b = baseline[horizon], candidate[horizon]
        difference = b - a
        rows[horizon] = {
            names[0]: float(a.mean()),
            names[1]: float(b.mean()),
            "ratio": float(b.mean() / a.mean()),
            "paired_difference": float(difference.mean()),
            "paired_standard_error": float(difference.std(ddof=1) / np.sqrt(n)),
            f"{names[1]}_lower_on": int(np.sum(difference < 0)),
            "n": n,
        }
    windows = {name: [int(x) for x in name.removeprefix("frames_").split("-")] for name in rows if "frames_" in name}
    if windows:
        # A window's weight in the full-rollout MSE, the mean over all frames of every trajectory.
        frames = max(last for _, last in windows.values())
        for name, (first, last) in windows.items():
            share = rows[name][names[0]] * (last - first + 1) / (rows["mse"][names[0]] * frames)
            rows[name]["share_of_baseline_mse"] = float(share)
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
    except (OSError, KeyError, ValueError, json.JSONDecodeError) as error:
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
        temporary = args.out.with_name(args.out.name + ".tmp")
        temporary.write_text(text + "\n")
        temporary.replace(args.out)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
