"""How much rollout MSE does a given per-frame error cost in this chaotic suspension? (issue 19)

The exact physics is re-run from each test trajectory's stored initial state, and after every frame
(``save_every`` Euler steps) from frame ``C`` on (the frames a model predicts; it is given the true frames
``0 .. C-1``) every real coordinate is shifted by an independent normal draw of standard deviation
``delta * L``: a "model" that is the exact physics plus a one-step error of ``delta``. Its
full-rollout MSE against the stored truth (frames ``C`` to the end, normalised units, the same
average as ``rollout_metrics``) is the least MSE any model with that one-step error can expect, if its
errors are no more harmful than white noise. A learned model's own one-step error (its rollout MSE at
horizon 1) then places it on the curve: what a target MSE demands of the one-step accuracy.

Every rung also has the chaos floor's one-off ``1e-6 L`` shift of the initial state, so ``delta = 0`` is the
chaos floor of ``dispgns evaluate`` (with other random draws: its numbers differ from ``evaluate``'s by the
spread of the draws). Positions are perturbed, velocities are not; a perturbed centre is kept inside the walls'
contact positions.

    python experiments/accuracy/error_ladder.py --data datasets/paper --out experiments/accuracy/error_ladder
    python experiments/accuracy/error_ladder.py --data datasets/paper3d --out experiments/three_d/error_ladder \
        --deltas 1e-5 1e-4 3e-4 1e-3 3e-3

(any dimension: the 3-D one, whose model errs more per frame, with larger deltas)

writes ``error_ladder.json`` (per split and delta: mean and std over trajectories of the full-rollout
MSE and of the MSE at horizons 10, 50 and 100) and ``error_ladder.png``.
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

from dispgns.data import load_dataset
from dispgns.physics import euler_integrator

DELTAS = (0.0, 1e-6, 1e-5, 3e-5, 1e-4, 3e-4)
"""Per-frame position errors in units of L (0: only the chaos floor's one-off 1e-6 L shift)."""

HORIZONS = (10, 50, 100)


def perturbed_rollouts(trajectories, config, *, length_scale, save_every, n_frames, delta, seed, input_frames):
    """``(K, n_frames, N_max, D)`` positions / L of the physics with a per-frame error ``delta`` from frame
    ``input_frames`` on (float64)."""
    count = len(trajectories)
    budget = max(t.initial_position.shape[0] for t in trajectories)
    dim = trajectories[0].dim
    x0 = np.zeros((count, budget, dim))
    v0 = np.zeros_like(x0)
    radius = np.full((count, budget), float(trajectories[0].initial_radius.min()))
    mask = np.zeros((count, budget), bool)
    for k, traj in enumerate(trajectories):
        n = traj.initial_position.shape[0]
        x0[k, :n], v0[k, :n], radius[k, :n], mask[k, :n] = (
            traj.initial_position,
            traj.initial_velocity,
            traj.initial_radius,
            True,
        )
    half = np.broadcast_to(np.asarray(config.box_half_size, float), (dim,))
    init_fn, step_fn = euler_integrator(config)

    def one(x, v, a, m, key):
        lo, hi = -half + a[:, None], half - a[:, None]
        # The chaos floor's one-off shift of the initial state, then the same ladder for every delta.
        key, first = jax.random.split(key)
        x = jnp.where(m[:, None], jnp.clip(x + 1e-6 * length_scale * jax.random.normal(first, x.shape), lo, hi), x)
        state = init_fn(x, v, a, m)

        def frame(carry, inputs):
            index, frame_key = inputs
            state = jax.lax.fori_loop(0, save_every, lambda _, s: step_fn(s), carry)
            # Frames 1 .. C-1 are the model's true inputs; its first prediction is frame C.
            size = jnp.where(index >= input_frames, delta * length_scale, 0.0)
            shifted = state.position + size * jax.random.normal(frame_key, state.position.shape)
            position = jnp.where(m[:, None], jnp.clip(shifted, lo, hi), state.position)
            state = dataclasses.replace(state, position=position)
            return state, position

        indices = jnp.arange(1, n_frames)
        _, xs = jax.lax.scan(frame, state, (indices, jax.random.split(key, n_frames - 1)))
        return jnp.concatenate([state.position[None], xs]) / length_scale

    with jax.enable_x64(True):
        keys = jax.vmap(lambda k: jax.random.fold_in(jax.random.PRNGKey(seed), k))(jnp.arange(count))
        out = jax.jit(jax.vmap(one))(jnp.asarray(x0), jnp.asarray(v0), jnp.asarray(radius), jnp.asarray(mask), keys)
        return np.asarray(out)


def scores(truth, predicted, c):
    """Full-rollout MSE and MSE at the horizons, over frames ``c ..`` (normalised units)."""
    err = np.mean((predicted[c:] - truth[c:]) ** 2, axis=(1, 2))
    return {"mse": float(err.mean()), **{f"mse_h{h}": float(err[:h].mean()) for h in HORIZONS}}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True, help="output prefix (writes PREFIX.json and PREFIX.png)")
    parser.add_argument("--splits", nargs="+", default=["test", "test_unseen"])
    parser.add_argument("--input-frames", type=int, default=6, help="C: frames given to a model")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--deltas", type=float, nargs="+", default=list(DELTAS), help="per-frame errors (L); 0, the floor, is added"
    )
    args = parser.parse_args()
    deltas = sorted(set([0.0, *args.deltas]))

    metadata, splits = load_dataset(args.data, args.splits)
    config, scale = metadata.physics_config, metadata.length_scale
    result = {"data": Path(args.data).name, "deltas_L": deltas, "input_frames": args.input_frames, "splits": {}}
    for split, trajectories in splits.items():
        n_frames = trajectories[0].n_frames
        rows = []
        for delta in deltas:
            start = time.perf_counter()
            runs = perturbed_rollouts(
                trajectories,
                config,
                length_scale=scale,
                save_every=metadata.save_every,
                n_frames=n_frames,
                delta=delta,
                seed=args.seed,
                input_frames=args.input_frames,
            )
            per = [
                scores(t.position.astype(np.float64), runs[k, :, : t.n_particles], args.input_frames)
                for k, t in enumerate(trajectories)
            ]
            row = {"delta_L": delta, "trajectories": len(per), "seconds": round(time.perf_counter() - start, 1)}
            for name in per[0]:
                values = np.array([p[name] for p in per])
                row[name] = {"mean": float(values.mean()), "std": float(values.std())}
            rows.append(row)
            print(split, delta, f"mse {row['mse']['mean']:.3e}", f"h10 {row['mse_h10']['mean']:.2e}", flush=True)
        result["splits"][split] = rows

    json_path, png_path = Path(f"{args.out}.json"), Path(f"{args.out}.png")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(f"{args.out}.json.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    tmp.replace(json_path)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for split, rows in result["splits"].items():
        d = [r["delta_L"] for r in rows if r["delta_L"] > 0]
        m = [r["mse"]["mean"] for r in rows if r["delta_L"] > 0]
        ax.loglog(d, m, "o-", label=f"{split}: physics + per-frame error")
        ax.axhline(rows[0]["mse"]["mean"], ls=":", color=ax.lines[-1].get_color(), label=f"{split}: chaos floor")
    ax.set_xlabel("per-frame position error delta (units of L)")
    ax.set_ylabel("full-rollout MSE (normalised)")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    print("wrote", json_path, png_path)


if __name__ == "__main__":
    main()
