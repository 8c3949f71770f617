"""Where in a rollout does a model's full-rollout MSE come from? Model first, exact physics after (issue 19).

Gains at 1, 10 and 100 steps have moved the 494-frame mean far less than themselves; this measures why.
For a hand-over step ``h``, the model rolls out (as shipped) for its first ``h`` predicted frames; then the exact
physics takes the model's state at that frame (its centres, and velocities from a second-order backward difference
of its last three frames) and runs the rest of the trajectory, in float64. The hybrid's full-rollout MSE against the
truth (frames ``C ..``, normalised units, the average of ``rollout_metrics``) is what the model would score if it
were perfect from step ``h`` on:

- if the hybrid at ``h = 100`` scores about what the model scores on its own, the model's error after step 100 is
  no worse than the physics' own sensitivity to the state it was handed, and only the first ~100 steps can be
  improved;
- the hybrid at small ``h`` says how much of the full-rollout MSE the first few steps alone decide;
- with ``--scales``, the model's error up to the hand-over is scaled by ``s`` first (its frames replaced by
  ``truth + s (model - truth)``): what a model ``1/s`` times more accurate over the first ``h`` steps, and exact
  after them, would score (rows ``h@s``). Only up to step ``--scale-until`` (100): once the model's paths have
  parted from the truth's, a point between two unrelated configurations puts particles on top of one another.

The paper's explicit Euler step (1e-4 s) is only just stable in a settled bed: from a rare handed-over state the
exact physics itself blows up hundreds of frames later (particles crossing the box in one frame). Such a hybrid is
reported as ``null`` and counted under ``unstable``; a row's mean is over the others. The rule: a coordinate
that moves more than the smallest radius in one frame (a blow-up moves particles across the box; the stored
truth of the selection files moves at most 0.85 of one, and of all files generated so far 1.14).

The same hand-over from the true frames (``truth`` row: the same velocity estimate, no model) measures what the
hand-over itself costs: 0.5-2.5e-4 in session 18, a few times the chaos floor (the velocity estimate was ~0.5 % off
on two trajectories checked against the physics' own velocities).

    python experiments/accuracy/handover.py --data datasets/acc400-valid --splits valid \\
        --models shipped=sedimentation-2d O2=experiments/accuracy/unrolled5_run --out runs/handover-valid.json

writes, per model and hand-over step, every trajectory's full-rollout MSE and the mean (``--limit N``: the first N
trajectories of each split). ``--pool A.json B.json ...`` (no ``--data``) pools outputs over their trajectories,
row by row where every file has the row: mean, standard error, and the paired ratio and difference to the
model's own MSE over the same (stable) trajectories.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dispgns import tuning
from dispgns.data import load_dataset
from dispgns.evaluation import chaos_floor_trajectories, predict_trajectories
from dispgns.metrics import rollout_mse
from dispgns.pretrained import load_pretrained, shipped_models
from dispgns.training.checkpoint import load_params

HANDOVERS = (1, 10, 25, 50, 100, 200, 300)
"""Predicted frames the model makes before the physics takes over."""


def load(source: str):
    """A model as shipped (mirror average, box guard), on the CPU kernels (same results, faster)."""
    params, config, _ = load_pretrained(source) if source in shipped_models() else load_params(source)
    config = dataclasses.replace(config, symmetrize=True, keep_inside_box=True)
    return params, tuning.tuned_model_config(config)


def backward_velocity(last_three, frame_dt):
    """Velocity at the last of three frames ``frame_dt`` apart: the second-order backward difference.

    ``last_three`` is ``(3, ..., D)`` positions (any length unit; the result is in that unit per second); exact
    for a path quadratic in time.
    """
    x0, x1, x2 = last_three
    return (3 * x2 - 4 * x1 + x0) / (2 * frame_dt)


def handed_over(frames, trajectories, metadata, step):
    """``frames[k]`` up to absolute frame ``step``, then the exact physics (float64) from that frame's state.

    ``frames`` are ``(T, N_k, D)`` normalised positions (frames ``0 .. C-1`` the inputs); returns one ``(T, N_k, D)``
    float64 array each, ``frames[k][:step]`` followed by the physics' frames ``step .. T-1`` divided by ``L``.
    """
    scale = metadata.length_scale  # L in m: the stored frames are positions / L
    config = metadata.physics_config
    states = []
    for f, traj in zip(frames, trajectories, strict=True):
        x = f[step - 2 : step + 1].astype(np.float64) * scale
        a = np.asarray(traj.initial_radius, np.float64)
        walls = np.asarray(config.half_sizes(x.shape[-1]))
        # The physics refuses centres past a wall's contact position; the box guard keeps them within float32 of it.
        position = np.clip(x[2], -walls + a[:, None], walls - a[:, None])
        velocity = backward_velocity(x, metadata.frame_dt)
        states.append(SimpleNamespace(initial_position=position, initial_velocity=velocity, initial_radius=a))
    # The chaos floor's batched float64 physics, without its perturbation: the exact physics from each state.
    continued = chaos_floor_trajectories(
        states,
        config,
        n_frames=frames[0].shape[0] - step,
        save_every=metadata.save_every,
        perturbation=0.0,
        x64=True,
        compiler_options=tuning.physics_compiler_options(),
        length_scale=scale,
    )
    return [np.concatenate([f[:step], x]) for f, x in zip(frames, continued, strict=True)]


def mse(predicted, truth, c):
    """Full-rollout MSE of ``(T, N, D)`` normalised positions over frames ``c ..`` (:func:`rollout_mse`)."""
    return float(rollout_mse(predicted, truth, input_frames=c))


def hybrid_mse(hybrid, truth, trajectories, c):
    """:func:`mse` of each hybrid, ``None`` where its physics blew up (a move of more than a radius in a frame)."""
    scores = []
    for f, t, traj in zip(hybrid, truth, trajectories, strict=True):
        stable = np.abs(np.diff(f, axis=0)).max() <= np.min(traj.radius)
        scores.append(mse(f, t, c) if stable else None)
    return scores


def summary(values):
    """Mean over the stable hybrids and how many were not."""
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)), len(values) - len(kept)


def pool(results):
    """Rows of several outputs pooled over their trajectories (see the module's docstring)."""
    pooled = {"files": [{"data": r["data"], "splits": r["splits"]} for r in results], "models": {}}
    for name in results[0]["models"]:
        if not all(name in r["models"] for r in results):
            continue
        tables = [r["models"][name]["per_trajectory"] for r in results]
        rows = {}
        for key in [k for k in tables[0] if all(k in t for t in tables)]:
            values = [v for t in tables for v in t[key]]
            own = [v for t in tables for v in t.get("model", [None] * len(t[key]))]
            kept = [v for v in values if v is not None]
            row = {"n": len(kept), "unstable": len(values) - len(kept), "mean": float(np.mean(kept))}
            row["se"] = float(np.std(kept, ddof=1) / np.sqrt(len(kept)))
            pairs = np.array([(v, m) for v, m in zip(values, own, strict=True) if v is not None and m is not None])
            if key != "model" and len(pairs):
                difference = pairs[:, 0] - pairs[:, 1]
                row["over_model"] = float(pairs[:, 0].mean() / pairs[:, 1].mean())
                row["paired_difference"] = float(difference.mean())
                row["paired_se"] = float(difference.std(ddof=1) / np.sqrt(len(difference)))
            rows[key] = row
        pooled["models"][name] = rows
    return pooled


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pool", nargs="+", help="outputs of this script to pool (nothing is computed)")
    parser.add_argument("--data")
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--models", nargs="+", help="NAME=SOURCE (a shipped name, run or export)")
    parser.add_argument("--handovers", type=int, nargs="+", default=list(HANDOVERS))
    parser.add_argument("--scales", type=float, nargs="*", default=[], help="error scales s < 1 (rows h@s)")
    parser.add_argument("--scale-until", type=int, default=100, help="largest hand-over step to scale")
    parser.add_argument("--input-frames", type=int, default=6, help="C, the frames a model is given (the truth row's)")
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    if args.pool:
        write(pool([json.loads(Path(p).read_text()) for p in args.pool]), Path(args.out))
        return
    if not args.data or not args.models:
        parser.error("--data and --models are needed (or --pool)")

    metadata, splits = load_dataset(args.data, args.splits)
    trajectories = [t for split in args.splits for t in splits[split][: args.limit]]
    truth = [np.asarray(t.position) for t in trajectories]
    result = {"data": args.data, "splits": args.splits, "trajectories": len(trajectories), "models": {}}
    sources = dict(item.split("=", 1) for item in args.models)
    for name, source in [("truth", None), *sources.items()]:
        start = time.perf_counter()
        if source is None:
            frames = truth
        else:
            params, config = load(source)
            if config.input_sequence_length != args.input_frames:
                parser.error(
                    f"{source} takes C = {config.input_sequence_length} frames, not --input-frames {args.input_frames}"
                )
            frames = predict_trajectories(
                params, trajectories, model_config=config, compiler_options=tuning.network_compiler_options(config)
            )
        c = args.input_frames
        rows = {} if source is None else {"model": [mse(f, t, c) for f, t in zip(frames, truth, strict=True)]}
        for h in args.handovers:
            hybrid = handed_over(frames, trajectories, metadata, c - 1 + h)
            rows[str(h)] = hybrid_mse(hybrid, truth, trajectories, c)
            for scale in [] if source is None or h > args.scale_until else args.scales:
                scaled = [t + np.float32(scale) * (f - t) for f, t in zip(frames, truth, strict=True)]
                hybrid = handed_over(scaled, trajectories, metadata, c - 1 + h)
                rows[f"{h}@{scale:g}"] = hybrid_mse(hybrid, truth, trajectories, c)
        summaries = {k: summary(v) for k, v in rows.items()}
        result["models"][name] = {
            "source": source,
            "per_trajectory": rows,
            "mean": {k: mean for k, (mean, _) in summaries.items()},
            "unstable": {k: unstable for k, (_, unstable) in summaries.items() if unstable},
            "seconds": round(time.perf_counter() - start, 1),
        }
        print(name, {k: f"{v:.3e}" for k, v in result["models"][name]["mean"].items()}, flush=True)
        print("  unstable:", result["models"][name]["unstable"], flush=True)
    write(result, Path(args.out))
    plot(result, Path(args.out).with_suffix(".png"))


def write(result, out):
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    tmp.replace(out)
    print("wrote", out)


def plot(result, path):
    """Hybrid full-rollout MSE against the hand-over step, one line per model (its own MSE dotted)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for name, entry in result["models"].items():
        steps = sorted(int(k) for k in entry["mean"] if k.isdigit())
        (line,) = ax.plot(steps, [entry["mean"][str(h)] for h in steps], "o-", label=f"{name}, then exact physics")
        if "model" in entry["mean"]:
            ax.axhline(entry["mean"]["model"], ls=":", color=line.get_color(), label=f"{name} alone")
    ax.set_xscale("log")
    ax.set_xlabel("model steps before the exact physics takes over")
    ax.set_ylabel("full-rollout MSE (normalised)")
    ax.set_ylim(bottom=0)
    ax.set_title(
        f"{Path(result['data']).name} {'+'.join(result['splits'])}, {result['trajectories']} trajectories", fontsize=9
    )
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
