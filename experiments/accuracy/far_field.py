"""How much of a model's error is the pair force beyond its graph's reach (issue 19).

The paper's physics applies the pair force to every pair of particles; the learned simulator's graph joins only
pairs closer than its connectivity radius (0.2 L, 0.02 m). This measures three things on a generated dataset
(one with initial states):

- ``--cutoffs`` (m): the exact physics (the dataset's ``PhysicsConfig``, in its generation precision: float32 for the
  presets) from the true initial states with
  the pair force dropped beyond each distance, scored against the all-pairs truth like a model (frames ``C ..``).
  A model whose dynamics matched the physics within that distance and ignored the rest would score about the same.
  ``0`` is the chaos floor (the exact physics from the initial states shifted by 1e-6 L), for scale.
- ``--model`` with ``--scales``: the model's rollout with ``s`` times the exact far field (the pair force from
  the pairs beyond its connectivity radius, computed at its own last frame and turned into a per-frame
  acceleration, ``F T^2 / (m L)``) added to its acceleration at every step, before the box guard; ``s = 0`` is the
  model's own rollout computed the same way, so the rows pair like for like.
- with ``--model``: the one-step error at true frames projected on the far field, ``beta = -<e, f> / <f, f>``
  (``e`` the model's next-position error, ``f`` the far-field acceleration), per trajectory and window of
  frames, and the far field's RMS beside the error's. ``beta = 1`` if the model is blind to the far field and its
  other errors are orthogonal to it, ``0`` if its errors are orthogonal to the far field; errors near the graph
  that point against the far field add to it, so ``beta`` does not tell those apart from a far field not learnt.

    python experiments/accuracy/far_field.py --data datasets/acc400-valid --splits valid --cutoffs 0.02 0.03 0.04 0 \\
        --model sedimentation-2d --scales 0 1 3 --out experiments/accuracy/results/far_field_valid12.json

writes, per row, every trajectory's full-rollout MSE (the mean of its per-frame MSE curve, as ``rollout_metrics``
computes it), its MSE over the windows of
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
from handover import load  # a sibling script, like paired below: on sys.path as this one's folder
from jax import lax
from paired import WINDOWS

from dispgns import fit_capacity, tuning
from dispgns.data import load_dataset
from dispgns.evaluation import CHAOS_PERTURBATION, chaos_floor_trajectories
from dispgns.files import write_atomic
from dispgns.metrics import per_frame_mse
from dispgns.physics.forces import interaction_force, particle_mass
from dispgns.simulator import predict_step

HORIZONS = (1, 10, 100, 300)
"""Predicted frames whose MSE is reported on its own."""


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


def frame_acceleration(force, radius_m, metadata):
    """``force`` ``(..., N, D)`` in N held for one frame, as a per-frame acceleration ``F T^2 / (m L)``.

    A force held for one frame changes the per-frame velocity by ``F T / m``, the position by ``F T^2 / m`` (the
    Euler sub-steps sum to it exactly when the force is constant; the drag, with a time of 15-40 frames, takes a few
    percent off within the frame, left out here); ``/ L`` gives normalised units. ``radius_m`` ``(N,)`` in m.
    """
    mass = particle_mass(radius_m, metadata.physics_config, force.shape[-1])[:, None]
    return force / mass * (metadata.frame_dt**2 / metadata.length_scale)


def far_field_fn(metadata, model_config):
    """``far(x, radius_m, mask) -> (N, D)``: the far field as a per-frame acceleration (normalised units per frame^2).

    ``x`` is ``(N, D)`` normalised centres, ``radius_m`` ``(N,)`` radii in m, ``mask`` ``(N,)`` bool (``False``:
    padding, which neither feels nor exerts a force). The far field is the pair force from the pairs at least the
    model's connectivity radius apart (the graph keeps the nearer ones).
    """
    physics = metadata.physics_config
    scale = metadata.length_scale
    reach = model_config.connectivity_radius * scale
    everything, near = dataclasses.replace(physics, cutoff=None), dataclasses.replace(physics, cutoff=reach)

    def far(x, radius_m, mask):
        xm, index = x * scale, jnp.arange(x.shape[0])
        force = interaction_force(xm, index, xm, radius_m, mask, everything)
        force = force - interaction_force(xm, index, xm, radius_m, mask, near)
        return jnp.where(mask[:, None], frame_acceleration(force, radius_m, metadata), 0.0)

    return far


def hybrid_rollouts(params, model_config, metadata, trajectories, scales, group, field=None, gain=0.0):
    """``{s: [(T, N_k, D) positions]}``: the model's rollouts with ``s`` times a field added at every step.

    The first ``C`` frames are the truth's; the acceleration is the model's (``predict_step``), times
    ``1 + s gain``, plus ``s`` times ``field(x, radius_m, mask)`` (default :func:`far_field_fn`, the far field) at
    the window's last frame, and the next frame is made as the model's own step makes it.
    """
    position, radius, radius_m, mask = padded(trajectories)
    c, t_len = model_config.input_sequence_length, position.shape[1]
    capacity = fit_capacity(position, model_config, mask=mask[:, None, :], margin=0.5)
    far = far_field_fn(metadata, model_config) if field is None else field
    low, high = (jnp.asarray(model_config.bounds, jnp.float32)[:, k] for k in (0, 1))

    def rollout(window, r, rm, m, s):
        def body(win, _):
            step = predict_step(params, win, r, model_config=model_config, capacity=capacity, mask=m)
            # predict_step's own next-frame rule, in its order of operations (at s = 0 the same bits).
            velocity = win[-1] - win[-2] + (1 + s * gain) * step.acceleration + s * far(win[-1], rm, m)
            nxt = win[-1] + velocity
            if model_config.keep_inside_box:  # the box guard
                nxt = jnp.clip(nxt, low + r[:, None], high - r[:, None])
            nxt = jnp.where(m[:, None], nxt, win[-1])  # padding stays put
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
                names = ", ".join(str(trajectories[k].attrs.get("index", k)) for k in sorted(set(idx)))
                raise RuntimeError(f"a hybrid rollout of trajectories {names} outgrew its graph capacity (margin 0.5)")
            f = np.asarray(f)
            frames += [f[j - lo] for j in range(lo, min(lo + group, len(trajectories)))]
        out[s] = [
            np.concatenate([t.position[:c], f[:, : t.position.shape[1]]])
            for t, f in zip(trajectories, frames, strict=True)
        ]
    return out


def paired_rows(rollouts, trajectories, c, name):
    """``{"model": ..., name: ...}``: the scores of ``rollouts[0.0]`` and ``rollouts[1.0]``, the second paired to the
    first (:func:`scores`, :func:`summarize`), each paired window printed as its ratio and standard errors."""
    truth = [np.asarray(t.position) for t in trajectories]
    baseline, other = scores(rollouts[0.0], truth, c), scores(rollouts[1.0], truth, c)
    rows = {"model": {"per_trajectory": baseline, **summarize(baseline)}}
    rows[name] = {"per_trajectory": other, **summarize(other, baseline)}
    for key, p in rows[name]["paired_to_s0"].items():
        print(f"{key:10s} ratio {p['ratio']:.3f}  ({p['difference'] / p['standard_error']:+.1f} SE)", flush=True)
    return rows


def beta(error, field):
    """``-<e, f> / <f, f>`` over all entries: 1 for ``e = -f`` (blind to ``f``), 0 for ``e`` orthogonal to ``f``."""
    return float(-(error * field).sum() / (field * field).sum())


def one_step_errors(params, model_config, traj, every, until, chunk=64):
    """``(frames, error, acceleration)``: the model's one-step predictions from the true frames.

    ``frames`` are the last input frames ``C-1, C-1+every, ...`` below ``until`` (and below the trajectory's last
    frame); ``error`` ``(F, N, D)`` is the predicted minus the true next position and ``acceleration`` ``(F, N, D)``
    the model's acceleration (before the box guard), both in normalised units. Predicted ``chunk`` windows at a time.
    """
    c = model_config.input_sequence_length
    x = np.asarray(traj.position)
    capacity = fit_capacity(x, model_config, margin=0.1)
    step = jax.jit(
        jax.vmap(lambda w, a=traj.radius: predict_step(params, w, a, model_config=model_config, capacity=capacity))
    )
    frames = np.arange(c - 1, min(until, x.shape[0] - 1), every)
    errors, accelerations = [], []
    for lo in range(0, len(frames), chunk):
        part = frames[lo : lo + chunk]
        result = step(jnp.asarray(np.stack([x[t - c + 1 : t + 1] for t in part])))
        if np.asarray(result.overflow).any():
            raise RuntimeError(f"trajectory {traj.attrs.get('index', '?')}: a one-step prediction outgrew its graph")
        errors.append(np.asarray(result.position) - x[part + 1])
        accelerations.append(np.asarray(result.acceleration))
    return frames, np.concatenate(errors), np.concatenate(accelerations)


def projection(params, model_config, metadata, trajectories, every, until):
    """Per trajectory and window of 100 frames: :func:`beta` of the one-step error on the far field, both RMS.

    One-step predictions from the true frames ``C-1, C-1+every, ...`` below ``until``; the RMS are per coordinate
    (normalised units). Windows start at 0, 100, ... and only those holding a checked frame are reported.
    """
    far = jax.jit(jax.vmap(far_field_fn(metadata, model_config), in_axes=(0, None, None)))
    out = []
    for traj in trajectories:
        frames, error, _ = one_step_errors(params, model_config, traj, every, until)
        x, n = np.asarray(traj.position), traj.position.shape[1]
        field = np.asarray(far(jnp.asarray(x[frames]), jnp.asarray(traj.initial_radius, jnp.float32), np.ones(n, bool)))
        rows = {}
        for first in range(0, int(frames[-1]) + 1, 100):
            sel = (frames >= first) & (frames < first + 100)
            if not sel.any():
                continue
            e, f = error[sel], field[sel]
            rows[f"{first}-{first + 100}"] = {
                "beta": beta(e, f),
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
    parser.add_argument("--input-frames", type=int, default=6, help="C, the frames before the first scored one")
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
    c = args.input_frames
    if args.model and config.input_sequence_length != c:
        parser.error(f"{args.model} takes C = {config.input_sequence_length} frames, not --input-frames {c}")
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
        by_window = {}
        for window in per[0]:
            values = np.array([p[window]["beta"] for p in per])
            by_window[window] = {
                "beta_mean": float(values.mean()),
                "beta_standard_error": float(values.std(ddof=1) / np.sqrt(values.size)) if values.size > 1 else None,
                "error_rms": float(np.mean([p[window]["error_rms"] for p in per])),
                "far_field_rms": float(np.mean([p[window]["far_field_rms"] for p in per])),
            }
        result["projection"] = {"per_trajectory": per, "mean": by_window}
        print("projection", json.dumps(by_window), flush=True)
    write_atomic(Path(args.out), (json.dumps(result, indent=1) + "\n").encode())
    print("wrote", args.out)


if __name__ == "__main__":
    main()
