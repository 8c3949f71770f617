"""Where a model's errors sit: by frame, by wall contact, by the nearest neighbour's gap (issue 19).

Two views of the same question, does the error live in a few particles a fix could target (wall contacts, touching
pairs) or in the bulk:

- one step from true frames (``--model``, every ``--every``-th frame): each particle's squared next-position
  error (normalised units, summed over the axes), its share of the total and its mean, by window of frames, by the
  gap to the nearest wall (in the particle's radii, at the input's last frame) and by the nearest neighbour's
  centre distance over the two radii' sum (1 is touching; the pair force's zero lies at 2^(1/6) = 1.12);
- along a rollout (``--predictions``, a file ``dispgns evaluate`` writes): at frames 10-400 after the inputs, the
  share of the squared position error carried by particles in contact with the floor, the lid and a side wall
  (gap under half a radius at the true frame), and by the worst 1 % and 10 % of particles.

    python experiments/accuracy/error_places.py --data datasets/acc400-valid --split valid --model sedimentation-2d \\
        --every 2 --predictions runs/stats-valid-S10b/predictions/valid.h5 \\
        --out experiments/accuracy/results/error_places_valid12_trackS10b.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from far_field import one_step_errors  # sibling scripts, on sys.path as this one's folder
from handover import load

from dispgns.data import load_dataset
from dispgns.data.format import read_split
from dispgns.files import write_atomic

FRAME_WINDOWS = ((0, 60), (60, 200), (200, 300), (300, 400), (400, None))
"""Windows of the input's last frame (absolute frame indices)."""
WALL_GAPS = (0.05, 0.5, 2.0)
"""Edges of the wall-gap classes, in the particle's radii."""
NEIGHBOUR_GAPS = (1.0, 1.1, 1.2, 1.5)
"""Edges of the nearest-neighbour classes, centre distance over the radii's sum."""
ROLLOUT_HORIZONS = (10, 50, 100, 200, 300, 400)
"""Predicted frames of the rollout view."""


def wall_gap(x, radius):
    """``(..., N, D)`` centres -> ``(..., N, D)`` gap to the nearer wall on each axis, in radii (box ``[-1, 1]^D``)."""
    a = radius[..., None]
    return np.minimum(1.0 - x - a, x + 1.0 - a) / a


def nearest_neighbour(x, radius):
    """``(F, N, D)`` -> ``(F, N)``: the smallest centre distance over the radii's sum."""
    d = np.sqrt(((x[:, :, None, :] - x[:, None, :, :]) ** 2).sum(-1))
    q = d / (radius[:, None] + radius[None, :])
    q[:, np.arange(x.shape[1]), np.arange(x.shape[1])] = np.inf
    return q.min(-1)


def classes(values, edges, name):
    """``{label: bool mask}`` for ``values`` cut at ``edges``."""
    bounds = (-np.inf, *edges, np.inf)
    return {f"{name} {lo:g}-{hi:g}": (values >= lo) & (values < hi) for lo, hi in zip(bounds, bounds[1:])}


def one_step(params, config, trajectories, every):
    """Squared one-step errors and the particles' situations, flattened over frames and particles."""
    parts = {"error2": [], "frame": [], "wall_gap": [], "neighbour": []}
    for traj in trajectories:
        x, a = np.asarray(traj.position), np.asarray(traj.radius)
        frames, error, _ = one_step_errors(params, config, traj, every, x.shape[0])
        parts["error2"].append((error**2).sum(-1).ravel())
        parts["frame"].append(np.repeat(frames, x.shape[1]))
        parts["wall_gap"].append(wall_gap(x[frames], a).min(-1).ravel())
        parts["neighbour"].append(nearest_neighbour(x[frames], a).ravel())
    return {k: np.concatenate(v) for k, v in parts.items()}


def worst(ranked, fraction):
    """The share of the error held by the worst ``fraction`` of entries, from their descending cumulative shares."""
    return float(ranked[max(round(fraction * len(ranked)) - 1, 0)])


def shares(error2, masks):
    """Per class: its share of the particles, of the squared error, and its mean squared error."""
    total = error2.sum()
    return {
        name: {
            "particles": float(m.mean()),
            "error": float(error2[m].sum() / total),
            "mean": float(error2[m].mean()) if m.any() else None,
        }
        for name, m in masks.items()
    }


def one_step_report(data):
    """Shares by window of frames (those holding a checked frame), and within each by wall gap and neighbour gap."""
    report = {"all frames": shares(data["error2"], {"all": np.ones_like(data["frame"], bool)})}
    windows = {}
    for first, last in FRAME_WINDOWS:
        sel = (data["frame"] >= first) & (data["frame"] < (last or np.inf))
        if not sel.any():
            continue
        masks = {
            **classes(data["wall_gap"][sel], WALL_GAPS, "wall gap"),
            **classes(data["neighbour"][sel], NEIGHBOUR_GAPS, "neighbour"),
        }
        e = data["error2"][sel]
        ranked = np.sort(e)[::-1].cumsum() / e.sum()
        windows[f"frames {first}-{last or 'end'}"] = {
            "share_of_all": float(e.sum() / data["error2"].sum()),
            "mean": float(e.mean()),
            "classes": shares(e, masks),
            "worst_1_percent": worst(ranked, 0.01),
            "worst_10_percent": worst(ranked, 0.1),
        }
    report["windows"] = windows
    return report


def rollout_report(predictions, trajectories, c):
    """At each horizon: the shares of the particles touching the floor, the lid or a side wall, and of the worst.

    ``mse`` is pooled over every particle of every trajectory at that frame (not a mean of per-trajectory MSEs).
    """
    out = {}
    for h in ROLLOUT_HORIZONS:
        e2, floor, lid, side = [], [], [], []
        for p, t in zip(predictions, trajectories, strict=True):
            frame, a = c - 1 + h, np.asarray(t.radius)
            if frame >= t.position.shape[0]:
                continue
            x = np.asarray(t.position[frame])
            e2.append(((np.asarray(p.position[frame]) - x) ** 2).sum(-1))
            # The last axis is the vertical: its lower wall is the floor, its upper one the lid (touched at the
            # start, where the suspension fills the box to the top).
            floor.append((x[:, -1] + 1.0 - a) / a < 0.5)
            lid.append((1.0 - x[:, -1] - a) / a < 0.5)
            side.append(wall_gap(x, a)[:, :-1].min(-1) < 0.5)
        e2, floor, lid, side = (np.concatenate(v) for v in (e2, floor, lid, side))
        ranked = np.sort(e2)[::-1].cumsum() / e2.sum()
        out[str(h)] = {
            "mse": float(e2.mean() / trajectories[0].position.shape[-1]),
            **{
                f"{name}_contact": {"particles": float(m.mean()), "error": float(e2[m].sum() / e2.sum())}
                for name, m in (("floor", floor), ("lid", lid), ("side_wall", side))
            },
            "worst_1_percent": worst(ranked, 0.01),
            "worst_10_percent": worst(ranked, 0.1),
        }
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="valid")
    parser.add_argument("--model", help="a shipped name, run or export (the one-step view)")
    parser.add_argument("--every", type=int, default=1, help="true frames between one-step checks")
    parser.add_argument("--predictions", type=Path, help="the model's rollouts from dispgns evaluate")
    parser.add_argument("--input-frames", type=int, default=6, help="C, the frames the rollouts were given")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    if not args.model and not args.predictions:
        parser.error("give --model, --predictions or both")
    _, splits = load_dataset(args.data, [args.split])
    trajectories = splits[args.split]
    result = {"data": args.data, "split": args.split}
    if args.model:
        params, config = load(args.model)
        result["model"] = args.model
        result["one_step"] = one_step_report(one_step(params, config, trajectories, args.every))
        print(json.dumps(result["one_step"]["windows"], indent=1), flush=True)
    if args.predictions:
        predictions = read_split(args.predictions)
        if len(predictions) != len(trajectories):
            parser.error(f"{args.predictions} holds {len(predictions)} trajectories, the split {len(trajectories)}")
        for k, (p, t) in enumerate(zip(predictions, trajectories, strict=True)):
            if p.position.shape != t.position.shape:
                parser.error(
                    f"{args.predictions}: trajectory {k:05d} is {p.position.shape}, the truth {t.position.shape}"
                )
        result["predictions"] = "/".join(args.predictions.parts[-3:])
        result["rollout"] = rollout_report(predictions, trajectories, args.input_frames)
        print(json.dumps(result["rollout"], indent=1), flush=True)
    write_atomic(Path(args.out), json.dumps(result, indent=1) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    main()
