"""Which part of the pair force a model gets wrong, by distance (issue 19).

``far_field.py`` projected a model's one-step error on the pair force from beyond its graph and found it points
against that force (``beta`` 2-3: the model moves particles too little towards where more of them lie). This splits
the exact pair force into bands of distance and regresses the one-step error on all of them at once, so the far
field's share is told apart from the bands the graph does see:

- bands within the graph's reach by ``r / (a_i + a_j)``: below ``--edges[0]`` (1.122: the repulsive side of the
  force's zero, contacts and overlaps), the well up to ``--edges[1]``, the tail beyond; and ``far``, the pairs at
  least the connectivity radius apart (the graph does not join them);
- per window of 100 frames, pooled over the trajectories: ``beta`` solving ``e ~ -sum_k beta_k f_k`` in least
  squares (``e`` the one-step next-position error at true frames, ``f_k`` band ``k``'s force as a per-frame
  acceleration, as in ``far_field.py``). ``beta_k = 1``: the model is blind to band ``k``; ``0``: its errors do
  not follow band ``k``; ``< 0``: it overshoots it. ``explained`` is the share of the squared one-step error the
  fitted combination removes. The single-band ``beta`` of ``far_field.py`` is reported beside it;
- with ``--correct``: the model's rollout with ``sum_k beta_k f_k`` added at every step (``beta`` fitted on frames
  0-300 of these trajectories, or read from ``--betas``, an earlier output, for a fit out of sample), paired
  against its own rollout (``far_field.hybrid_rollouts``, ``s = 0`` and ``1``). This is an oracle (it uses the
  exact force law): it says how much a model that erred less along those bands would gain, not a lever to ship.
  ``--without-far`` leaves the far band out of the correction (the bands within the graph alone).
- with ``--own``: the model's own predicted acceleration is one more regressor (``beta > 0``: the model's steps
  are too short along themselves), and ``--correct`` scales the model's acceleration by ``1 + beta_own``. The
  error holds the model's own acceleration, so the joint ``beta_own`` is confounded with the bands' (it differs
  from ``single_band_beta``, the own acceleration fitted alone, which is the gain that needs no force law).
  ``--gain-only`` rolls out with that gain alone (the bands' ``beta`` set to 0).

    python experiments/accuracy/band_projection.py --data datasets/acc400-valid --splits valid \\
        --model sedimentation-2d --out experiments/accuracy/results/band_projection_valid12.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from far_field import frame_acceleration, hybrid_rollouts, one_step_errors, paired_rows  # sibling scripts
from handover import load

from dispgns.data import load_dataset
from dispgns.files import write_atomic
from dispgns.physics.forces import pair_force_over_distance

EDGES = (1.122, 1.5, 2.5)
"""Band edges within the graph in ``r / (a_i + a_j)``: the force's zero (``2^(1/6)``), the well's end, the tail."""


def band_names(edges):
    """``"r/sigma 0-1.122", ..., "far (beyond the graph)"``: one name per band of :func:`band_fields_fn`."""
    cuts = (0.0, *edges, None)
    names = [f"r/sigma {lo:g}-{hi:g}" if hi else f"r/sigma >= {lo:g}, in graph" for lo, hi in zip(cuts, cuts[1:])]
    return names + ["far (beyond the graph)"]


def band_fields_fn(metadata, model_config, edges=EDGES):
    """``fields(x, radius_m, mask) -> (K, N, D)``: the pair force by band, as per-frame accelerations.

    ``x`` ``(N, D)`` normalised centres, ``radius_m`` ``(N,)`` in m, ``mask`` ``(N,)`` (padding neither feels nor
    exerts a force). Bands: within the connectivity radius by ``r / (a_i + a_j)`` cut at ``edges``
    (``len(edges) + 1`` bands), then every pair beyond it. They partition the pairs, so the bands sum to the exact
    all-pairs force (normalised units per frame^2, ``F T^2 / (m L)`` as in ``far_field.far_field_fn``).
    """
    physics = metadata.physics_config
    scale = metadata.length_scale
    reach = model_config.connectivity_radius * scale
    bounds = jnp.asarray((0.0, *edges, np.inf))

    def fields(x, radius_m, mask):
        xm = x * scale
        d = xm[:, None, :] - xm[None, :, :]  # x_i - x_j, m
        r2 = (d * d).sum(-1)
        n = x.shape[0]
        valid = mask[:, None] & mask[None, :] & ~jnp.eye(n, dtype=bool)
        a_i, a_j = radius_m[:, None], radius_m[None, :]
        # Coincident particles (r = 0) get no force, as in the physics; r2 = 1 keeps inf/NaN out of the masked branch.
        valid = valid & (r2 > 0)
        coeff = jnp.where(valid, pair_force_over_distance(jnp.where(valid, r2, 1.0), a_i, a_j, physics), 0.0)
        r_over_sigma = jnp.sqrt(r2) / (a_i + a_j)
        inside = r2 < reach * reach
        masks = [inside & (r_over_sigma >= lo) & (r_over_sigma < hi) for lo, hi in zip(bounds[:-1], bounds[1:])]
        masks.append(~inside)
        force = jnp.stack([jnp.einsum("ij,ijd->id", jnp.where(m, coeff, 0.0), d) for m in masks])
        return jnp.where(mask[None, :, None], frame_acceleration(force, radius_m, metadata), 0.0)

    return fields


def fit(error, fields):
    """Least-squares ``beta`` for ``error ~ -sum_k beta_k fields[k]`` and the share of ``|error|^2`` it removes.

    ``error`` ``(...)``, ``fields`` ``(K, ...)`` of the same trailing shape. Also each band's own projection
    ``-<e, f_k> / <f_k, f_k>`` (``far_field.beta``), which ignores the other bands.
    """
    f = fields.reshape(fields.shape[0], -1).astype(np.float64)
    e = error.reshape(-1).astype(np.float64)
    gram, rhs = f @ f.T, -(f @ e)
    # lstsq, not solve: a band empty in one window (no contacts yet) makes the Gram matrix singular; its beta is 0.
    beta = np.linalg.lstsq(gram, rhs, rcond=None)[0]
    residual = e + beta @ f
    return {
        "beta": beta.tolist(),
        "explained": float(1.0 - (residual @ residual) / (e @ e)),
        "single_band_beta": (rhs / np.where(np.diag(gram) > 0, np.diag(gram), np.inf)).tolist(),
        "field_rms": np.sqrt((f * f).mean(1)).tolist(),
        "error_rms": float(np.sqrt((e * e).mean())),
    }


def band_errors(params, model_config, metadata, trajectories, every, until, edges, own=False):
    """Per trajectory ``(frames, error (F, N, D), fields (K, F, N, D))`` at the true frames ``C-1, C-1+every, ...``.

    With ``own`` the model's own acceleration (normalised units per frame^2, before the box guard: what
    ``far_field.hybrid_rollouts``' gain scales) is one more field, the last.
    """
    fields_fn = jax.jit(jax.vmap(band_fields_fn(metadata, model_config, edges), in_axes=(0, None, None), out_axes=1))
    out = []
    for traj in trajectories:
        frames, error, acceleration = one_step_errors(params, model_config, traj, every, until)
        x, n = np.asarray(traj.position), traj.position.shape[1]
        radius_m = jnp.asarray(traj.initial_radius, jnp.float32)
        fields = np.asarray(fields_fn(jnp.asarray(x[frames]), radius_m, jnp.ones(n, bool)))
        if own:
            fields = np.concatenate([fields, acceleration[None].astype(fields.dtype)])
        out.append((frames, error, fields))
    return out


def windows_fit(per_trajectory, width=100):
    """:func:`fit` per window of ``width`` frames, pooled over the trajectories.

    ``beta_standard_error`` is the spread of the trajectories' own fits (their standard deviation over the square
    root of their number): a measure of how much ``beta`` varies between trajectories, not the pooled fit's own
    error (the pooled ``beta`` weighs each trajectory by its fields' energy, not equally).
    """
    last = max(int(frames[-1]) for frames, _, _ in per_trajectory)
    out = {}
    for first in range(0, last + 1, width):
        picks = [((frames >= first) & (frames < first + width), e, f) for frames, e, f in per_trajectory]
        picks = [(e[s], f[:, s]) for s, e, f in picks if s.any()]
        if not picks:
            continue
        pooled = fit(
            np.concatenate([e.reshape(-1) for e, _ in picks]),
            np.concatenate([f.reshape(f.shape[0], -1) for _, f in picks], 1),
        )
        own = np.array([fit(e, f)["beta"] for e, f in picks])
        # A band empty in a trajectory's window has no beta there (fit gives 0): left out of the spread.
        present = np.array([(f.reshape(f.shape[0], -1) ** 2).sum(1) > 0 for _, f in picks])
        own = np.where(present, own, np.nan)
        count = present.sum(0)
        spread = np.nanstd(np.where(count > 1, own, 0.0), 0, ddof=1) / np.sqrt(np.maximum(count, 1))
        pooled["beta_standard_error"] = [float(v) if n > 1 else None for v, n in zip(spread, count)]
        out[f"{first}-{first + width}"] = pooled
    return out


def correction_terms(fit, n_bands, own, without_far=False, gain_only=False):
    """``(beta (n_bands,), gain)`` of the correction ``--correct`` rolls out, from a fit's frames 0-``until`` record.

    The bands add ``sum_k beta_k f_k``; the model's own acceleration, if fitted (``own``), scales the model's step by
    ``1 + gain``. ``without_far`` zeroes the far band's ``beta``; ``gain_only`` keeps the own acceleration's
    single-regressor ``beta`` alone (the gain that needs no force law; the joint one is confounded with the bands').
    """
    window = fit["windows"]["all"]
    beta = jnp.asarray(window["beta"][:n_bands], jnp.float32)
    gain = float(window["beta"][n_bands]) if own else 0.0
    if without_far:
        beta = beta.at[-1].set(0.0)
    if gain_only:
        beta, gain = jnp.zeros_like(beta), float(window["single_band_beta"][n_bands])
    return beta, gain


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--model", required=True, help="a shipped name, run or export")
    parser.add_argument("--edges", type=float, nargs="+", default=list(EDGES), help="band edges in r / sigma")
    parser.add_argument("--every", type=int, default=2, help="true frames between one-step checks")
    parser.add_argument("--until", type=int, default=300, help="last frame of the one-step checks")
    parser.add_argument("--limit", type=int, default=None, help="the first N trajectories of each split")
    parser.add_argument("--own", action="store_true", help="the model's own acceleration as one more regressor")
    parser.add_argument("--correct", action="store_true", help="roll out with the fitted combination added")
    parser.add_argument("--betas", help="an earlier output whose frames 0-until beta --correct uses")
    parser.add_argument("--without-far", action="store_true", help="--correct with the far band's beta set to 0")
    parser.add_argument(
        "--gain-only", action="store_true",
        help="--correct with the own acceleration's single-regressor beta alone (a scalar gain; needs --own --correct)",
    )  # fmt: skip
    parser.add_argument("--group", type=int, default=12, help="trajectories rolled out together")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    edges = tuple(args.edges)
    if edges[0] <= 0 or any(b <= a for a, b in zip(edges, edges[1:])):
        parser.error(f"--edges must be strictly increasing and > 0, got {args.edges}")
    if args.gain_only and not (args.own and args.correct):
        parser.error("--gain-only needs --own and --correct")
    if args.gain_only and args.without_far:
        parser.error("--gain-only sets every band's beta to 0: --without-far has nothing to do")

    metadata, splits = load_dataset(args.data, args.splits)
    trajectories = [t for split in args.splits for t in splits[split][: args.limit]]
    if any(t.initial_radius is None for t in trajectories):
        parser.error(f"{args.data}: the trajectories carry no radii in m (generated data needed)")
    params, config = load(args.model)
    names = band_names(edges) + (["the model's own acceleration"] if args.own else [])
    result = {"data": args.data, "splits": args.splits, "model": args.model, "bands": names}
    start = time.perf_counter()
    per = band_errors(params, config, metadata, trajectories, args.every, args.until, edges, own=args.own)
    result["windows"] = windows_fit(per)
    result["windows"]["all"] = windows_fit(per, width=args.until + 1)[f"0-{args.until + 1}"]
    result["fit_seconds"] = round(time.perf_counter() - start)
    for window, w in result["windows"].items():
        print(window, "explained", f"{w['explained']:.4f}", flush=True)
        for k, name in enumerate(names):
            se = w["beta_standard_error"][k]
            se = float("nan") if se is None else se
            print(
                f"  {name:28s} beta {w['beta'][k]:+.3f} ± {se:.3f}  single {w['single_band_beta'][k]:+.3f}"
                f"  field rms {w['field_rms'][k]:.2e}  (error rms {w['error_rms']:.2e})",
                flush=True,
            )
    if args.correct:
        source = json.loads(Path(args.betas).read_text()) if args.betas else result
        if args.betas and source["bands"] != names:
            parser.error(f"{args.betas}: its bands {source['bands']} are not these {names}")
        beta, gain = correction_terms(source, len(edges) + 2, args.own, args.without_far, args.gain_only)
        fields = band_fields_fn(metadata, config, edges)
        if args.gain_only:  # every band's beta is 0: skip the all-pairs band forces at every step

            def correction(x, rm, m):
                return jnp.zeros_like(x)
        else:

            def correction(x, rm, m):
                return jnp.tensordot(beta, fields(x, rm, m), 1)

        start = time.perf_counter()
        rollouts = hybrid_rollouts(
            params, config, metadata, trajectories, [0.0, 1.0], args.group, field=correction, gain=gain
        )
        result["correction"] = {
            "beta": np.asarray(beta).tolist(),
            "gain": gain,
            "beta_from": args.betas or "this fit",
            "without_far": args.without_far,
            "gain_only": args.gain_only,
            **paired_rows(rollouts, trajectories, config.input_sequence_length, "model + correction"),
            "seconds": round(time.perf_counter() - start),
        }
    write_atomic(Path(args.out), (json.dumps(result, indent=1) + "\n").encode())
    print("wrote", args.out)


if __name__ == "__main__":
    main()
