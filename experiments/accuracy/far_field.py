"""How much of a model's error is the pair force beyond its graph's reach (issue 19).

The paper's physics applies the pair force to every pair of particles; the learned simulator's graph joins only
pairs closer than its connectivity radius (0.2 L, 0.02 m). This measures three things on a generated dataset
(one with initial states):

- ``--cutoffs`` (m): the exact physics (float64, the dataset's ``PhysicsConfig``) from the true initial states with
  the pair force dropped beyond each distance, scored against the all-pairs truth like a model (frames ``C ..``).
  A model whose dynamics matched the physics within that distance and ignored the rest would score about the same.
  ``0`` is the chaos floor (the exact physics from the initial states shifted by 1e-6 L), for scale.
- ``--model`` with ``--scales``: the model's rollout with ``s`` times the exact far field (the pair force from
  the pairs beyond its connectivity radius, computed at its own last frame and turned into a per-frame
  acceleration, ``F T^2 / (m L)``) added to its acceleration at every step, before the box guard; ``s = 0`` is the
  model's own rollout computed the same way, so the rows pair like for like.
- with ``--model``: the one-step error at true frames projected on the far field, ``beta = -<e, f> / <f, f>``
  (``e`` the model's next-position error, ``f`` the far-field acceleration), per trajectory and window of
  frames: ``beta = 1`` is the error a model ignoring the far field and otherwise unbiased would carry, ``0`` a model
  that has learnt it; and the far field's RMS beside the error's.

    python experiments/accuracy/far_field.py --data datasets/acc400-valid --splits valid --cutoffs 0.02 0.04 0 \\
        --model sedimentation-2d --scales 0 1 3 --out experiments/accuracy/results/far_field_valid12.json

writes, per row, every trajectory's full-rollout MSE (the mean of ``rollout_metrics``), its MSE over the windows of
``paired.py`` and at frames 1, 10, 100 and 300, and their means; rows with ``--model`` also the paired difference
to ``s = 0`` (mean and standard error over the trajectories).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from paired import WINDOWS  # the sibling script, on sys.path as this one's folder

from dispgns import fit_capacity, tuning
from dispgns.data import load_dataset
from dispgns.evaluation import CHAOS_PERTURBATION, chaos_floor_trajectories
from dispgns.files import write_atomic
from dispgns.metrics import per_frame_mse
from dispgns.physics.forces import interaction_force, particle_mass
from dispgns.pretrained import load_pretrained, shipped_models
from dispgns.simulator import predict_step
from dispgns.training.checkpoint import load_params

HORIZONS = (1, 10, 100, 300)
"""Predicted frames whose MSE is reported on its own."""


def load(source: str):
    """A model as shipped (mirror average, box guard), on the CPU kernels (same results, faster)."""
    params, config, _ = load_pretrained(source) if source in shipped_models() else load_params(source)
    config = dataclasses.replace(config, symmetrize=True, keep_inside_box=True)
    return params, tuning.tuned_model_config(config)


def scores(frames, truth, c):
    """Per trajectory: full-rollout MSE, the windows' and the horizons' MSEs (frames ``c ..``; those that fit)."""
    curves = [np.asarray(per_frame_mse(f, t, input_frames=c), np.float64) for f, t in zip(frames, truth, strict=True)]
    length = min(len(k) for k in curves)
    out = {"full": [float(k.mean()) for k in curves]}
    for first, last in WINDOWS:
        if first <= length:
            out[f"{first}-{last or 'end'}"] = [float(k[first - 1 : last].mean()) for k in curves]
    for h in HORIZONS:
        if h <= length:
            out[f"h{h}"] = [float(k[h - 1]) for k in curves]
    return out


def summarize(rows, baseline=None):
    """Means over the trajectories; with ``baseline`` (rows of the same trajectories) the paired differences."""
    out = {"mean": {k: float(np.mean(v)) for k, v in rows.items()}}
    if baseline is not None:
        paired = {}
        for k, v in rows.items():
            d = np.asarray(v) - np.asarray(baseline[k])
            paired[k] = {
                "ratio": float(np.mean(v) / np.mean(baseline[k])),
                "difference": float(d.mean()),
                "standard_error": float(d.std(ddof=1) / np.sqrt(d.size)),
            }
        out["paired_to_s0"] = paired
    return out


def truncated(metadata, trajectories, cutoff):
    """The exact physics from the true initial states with the pair force cut at ``cutoff`` m (0: the floor)."""
    config = metadata.physics_config
    if cutoff > 0:
        config = dataclasses.replace(config, cutoff=cutoff)
    return chaos_floor_trajectories(
        trajectories,
        config,
        n_frames=trajectories[0].position.shape[0],
        save_every=metadata.save_every,
        perturbation=0.0 if cutoff > 0 else CHAOS_PERTURBATION,
        x64=metadata.precision == "float64",
        compiler_options=tuning.physics_compiler_options(),
        length_scale=metadata.length_scale,
    )


def padded(trajectories):
    """``(B, T, N, D)`` positions, ``(B, N)`` radii (normalised and in m) and masks, padded to the largest ``N``."""
    b, n = len(trajectories), max(t.position.shape[1] for t in trajectories)
    t_len, dim = trajectories[0].position.shape[0], trajectories[0].position.shape[2]
    position = np.zeros((b, t_len, n, dim), np.float32)
    radius, radius_m, mask = np.ones((b, n), np.float32), np.ones((b, n), np.float32), np.zeros((b, n), bool)
    for k, t in enumerate(trajectories):
        m = t.position.shape[1]
        # Padding particles sit at the box centre with unit radii; the mask keeps them out of graphs and forces.
        position[k, :, :m], radius[k, :m], radius_m[k, :m], mask[k, :m] = t.position, t.radius, t.initial_radius, True
    return position, radius, radius_m, mask


def far_field_fn(metadata, model_config):
    """``(x (N, D) normalised, radius_m, mask) -> (N, D)``: the far field as a per-frame acceleration, normalised."""
    physics = metadata.physics_config
    scale, frame_time = metadata.length_scale, metadata.frame_dt
    reach = model_config.connectivity_radius * scale
    everything, near = dataclasses.replace(physics, cutoff=None), dataclasses.replace(physics, cutoff=reach)

    def far(x, radius_m, mask):
        xm, index = x * scale, jnp.arange(x.shape[0])
        force = interaction_force(xm, index, xm, radius_m, mask, everything)
        force = force - interaction_force(xm, index, xm, radius_m, mask, near)
        # A force held for one frame changes the per-frame velocity by F T / m, the position by F T^2 / m (the
        # Euler sub-steps sum to it exactly when the force is constant).
        acc = force / particle_mass(radius_m, physics, x.shape[-1])[:, None] * (frame_time**2 / scale)
        return jnp.where(mask[:, None], acc, 0.0)

    return far


def hybrid_rollouts(params, model_config, metadata, trajectories, scales, group):
    """Per scale, the model's rollouts with ``scale`` times the far field added at every step (lists of arrays)."""
    position, radius, radius_m, mask = padded(trajectories)
    c, t_len = model_config.input_sequence_length, position.shape[1]
    capacity = fit_capacity(position, model_config, mask=mask[:, None, :], margin=0.5)
    far = far_field_fn(metadata, model_config)
    low, high = (jnp.asarray(model_config.bounds, jnp.float32)[:, k] for k in (0, 1))

    def rollout(window, r, rm, m, s):
        def body(win, _):
            step = predict_step(params, win, r, model_config=model_config, capacity=capacity, mask=m)
            velocity = win[-1] - win[-2] + step.acceleration + s * far(win[-1], rm, m)
            nxt = jnp.clip(win[-1] + velocity, low + r[:, None], high - r[:, None])  # the box guard
            nxt = jnp.where(m[:, None], nxt, win[-1])
            return jnp.concatenate([win[1:], nxt[None]]), (nxt, step.overflow)

        _, (frames, overflow) = lax.scan(body, window, None, length=t_len - c)
        return frames, overflow.any()

    run = jax.jit(jax.vmap(rollout, in_axes=(0, 0, 0, 0, None)))
    out = {}
    for s in scales:
        frames = []
        for lo in range(0, len(trajectories), group):
            # Every group is padded to ``group`` trajectories (repeats) so one program serves them all.
            idx = [min(k, len(trajectories) - 1) for k in range(lo, lo + group)]
            args = (position[idx, :c], radius[idx], radius_m[idx], mask[idx])
            f, overflow = run(*(jnp.asarray(a) for a in args), jnp.float32(s))
            if np.asarray(overflow).any():
                raise RuntimeError("a hybrid rollout outgrew its graph capacity; raise the margin")
            f = np.asarray(f)
            frames += [f[j - lo] for j in range(lo, min(lo + group, len(trajectories)))]
        out[s] = [
            np.concatenate([t.position[:c], f[:, : t.position.shape[1]]])
            for t, f in zip(trajectories, frames, strict=True)
        ]
    return out


def projection(params, model_config, metadata, trajectories, every, until):
    """Per trajectory and window: beta of the one-step error on the far field, and both RMS (per coordinate)."""
    far = jax.jit(jax.vmap(far_field_fn(metadata, model_config), in_axes=(0, None, None)))
    c = model_config.input_sequence_length
    out = []
    for traj in trajectories:
        x, n = np.asarray(traj.position), traj.position.shape[1]
        capacity = fit_capacity(x, model_config, margin=0.1)
        step = jax.jit(
            jax.vmap(
                lambda w, a=traj.radius, cap=capacity: predict_step(
                    params, w, a, model_config=model_config, capacity=cap
                )
            )
        )
        frames = np.arange(c - 1, min(until, x.shape[0] - 1), every)
        windows = np.stack([x[t - c + 1 : t + 1] for t in frames])
        result = step(jnp.asarray(windows))
        if np.asarray(result.overflow).any():
            raise RuntimeError("a one-step prediction outgrew its graph capacity")
        error = np.asarray(result.position) - x[frames + 1]
        field = np.asarray(far(jnp.asarray(x[frames]), jnp.asarray(traj.initial_radius, jnp.float32), np.ones(n, bool)))
        rows = {}
        for first in range(0, until, 100):
            sel = (frames >= first) & (frames < first + 100)
            e, f = error[sel], field[sel]
            rows[f"{first}-{first + 100}"] = {
                "beta": float(-(e * f).sum() / (f * f).sum()),
                "error_rms": float(np.sqrt((e * e).mean())),
                "far_field_rms": float(np.sqrt((f * f).mean())),
            }
        out.append(rows)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--cutoffs", type=float, nargs="*", default=[], help="pair-force cutoffs in m (0: floor)")
    parser.add_argument("--model", help="a shipped name, run or export")
    parser.add_argument("--scales", type=float, nargs="*", default=[0.0, 1.0])
    parser.add_argument("--group", type=int, default=12, help="trajectories rolled out together")
    parser.add_argument("--projection-every", type=int, default=3, help="true frames between one-step checks")
    parser.add_argument("--projection-until", type=int, default=300, help="last frame of the one-step checks")
    parser.add_argument("--limit", type=int, default=None, help="the first N trajectories of each split")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    if any(c < 0 for c in args.cutoffs):
        parser.error(f"--cutoffs must be >= 0 m, got {args.cutoffs}")
    if args.model and 0.0 not in args.scales:
        parser.error("--scales must include 0 (the model's own rollout, the rows' pair)")

    metadata, splits = load_dataset(args.data, args.splits)
    trajectories = [t for split in args.splits for t in splits[split][: args.limit]]
    if any(t.initial_position is None for t in trajectories):
        parser.error(f"{args.data}: the trajectories carry no initial state (generated data needed)")
    truth = [np.asarray(t.position) for t in trajectories]
    params, config = load(args.model) if args.model else (None, None)
    c = config.input_sequence_length if args.model else 6
    result = {"data": args.data, "splits": args.splits, "trajectories": len(trajectories), "rows": {}}
    for cutoff in args.cutoffs:
        start = time.perf_counter()
        rows = scores(truncated(metadata, trajectories, cutoff), truth, c)
        name = f"physics cut at {cutoff:g} m" if cutoff else "chaos floor"
        result["rows"][name] = {
            "per_trajectory": rows,
            **summarize(rows),
            "seconds": round(time.perf_counter() - start),
        }
        print(name, {k: f"{v:.3e}" for k, v in result["rows"][name]["mean"].items()}, flush=True)
    if args.model:
        result["model"] = args.model
        start = time.perf_counter()
        rollouts = hybrid_rollouts(params, config, metadata, trajectories, sorted(args.scales), args.group)
        baseline = scores(rollouts[0.0], truth, c)
        for s in sorted(args.scales):
            rows = baseline if s == 0 else scores(rollouts[s], truth, c)
            name = f"model + {s:g} x far field"
            result["rows"][name] = {"per_trajectory": rows, **summarize(rows, None if s == 0 else baseline)}
            print(name, {k: f"{v:.3e}" for k, v in result["rows"][name]["mean"].items()}, flush=True)
        result["hybrid_seconds"] = round(time.perf_counter() - start)
        per = projection(params, config, metadata, trajectories, args.projection_every, args.projection_until)
        beta = {}
        for window in per[0]:
            values = np.array([p[window]["beta"] for p in per])
            beta[window] = {
                "beta_mean": float(values.mean()),
                "beta_standard_error": float(values.std(ddof=1) / np.sqrt(values.size)) if values.size > 1 else None,
                "error_rms": float(np.mean([p[window]["error_rms"] for p in per])),
                "far_field_rms": float(np.mean([p[window]["far_field_rms"] for p in per])),
            }
        result["projection"] = {"per_trajectory": per, "mean": beta}
        print("projection", json.dumps(beta), flush=True)
    write_atomic(Path(args.out), (json.dumps(result, indent=1) + "\n").encode())
    print("wrote", args.out)


if __name__ == "__main__":
    main()
