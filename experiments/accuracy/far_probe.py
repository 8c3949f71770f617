"""Can a model learn the far field from generic inputs? A linear probe on shell descriptors (issue 19).

``band_projection.py`` found the shipped model's one-step error runs against the far field (the pairs beyond the
graph's 0.2 L) by ~2.4 far fields, and that of the bands of the pair force the far field is the only one whose
correction at every step lowers the rollout error over the first hundreds of frames. The exact far field needs the
force law; a learned simulator does not have it. This asks whether generic inputs carry the same information:
per particle ``i``, descriptors of its surroundings out to ~0.45 L that know nothing of the force law,

    V_i[k, q, p] = (a_i / a_ref)^p  sum_j  (sigma_ij / (2 a_ref))^q  phi_k(r_ij)  (x_j - x_i) / r_ij

(``phi_k`` Gaussian shells of width ``--width`` at ``--centres``, normalised units; ``sigma_ij = a_i + a_j``; the
powers let a linear map weigh particles by size), and a linear head ``c . V_i`` fitted by least squares to the
negated one-step errors of ``--fit-data`` (training trajectories: the head is learnt, not told). Then:

- the share of the one-step squared error the head removes, in and out of sample (``--data``);
- with ``--rollouts``: the model's rollout on ``--data`` with the head's output added at every step, paired
  against its own rollout (``far_field.hybrid_rollouts``, ``s = 0`` and ``1``).

A head that recovers the exact far field's gain says an input of this kind (computed in the simulator) is worth
building into the model; one that does not says the gain needs the force law or more than a linear map.

    python experiments/accuracy/far_probe.py --fit-data datasets/acc400 --fit-split train --fit-count 24 \\
        --data datasets/acc400-valid --splits valid --model sedimentation-2d --rollouts \\
        --out experiments/accuracy/results/far_probe_valid12.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from far_field import hybrid_rollouts, one_step_errors, paired_rows  # sibling scripts
from handover import load

from dispgns.data import load_dataset
from dispgns.files import write_atomic

CENTRES = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45)
"""Shell centres in normalised units (the box is [-1, 1]; the graph reaches 0.2)."""
SIGMA_POWERS = (0, 4, 8)
"""Powers of ``sigma_ij / (2 a_ref)`` weighing each neighbour (the pair force grows steeply with the radii)."""
SELF_POWERS = (0, -2)
"""Powers of ``a_i / a_ref`` multiplying particle ``i``'s sums (an acceleration is a force over a mass ~ a_i^2)."""
A_REF = 0.035
"""Reference radius (normalised units: 3.5 mm, the middle of the training radii)."""


def shell_features_fn(centres=CENTRES, width=0.05, sigma_powers=SIGMA_POWERS, self_powers=SELF_POWERS, a_ref=A_REF):
    """``features(x, radius, mask) -> (N, F, D)``: the shell descriptors ``V`` (module docstring), all pairs.

    ``x`` ``(N, D)`` and ``radius`` ``(N,)`` normalised; ``mask`` ``(N,)`` (padding neither has nor adds any).
    ``F = len(centres) len(sigma_powers) len(self_powers)``, ordered shell-minor.
    """
    centres = jnp.asarray(centres)

    def features(x, radius, mask):
        n = x.shape[0]
        d = x[None, :, :] - x[:, None, :]  # x_j - x_i, (i, j, D)
        valid = mask[:, None] & mask[None, :] & ~jnp.eye(n, dtype=bool)
        r = jnp.sqrt(jnp.where(valid, (d * d).sum(-1), 1.0))
        unit = d / r[..., None]
        phi = jnp.exp(-0.5 * ((r[..., None] - centres) / width) ** 2)  # (i, j, K)
        sigma = (radius[:, None] + radius[None, :]) / (2 * a_ref)
        out = []
        for q in sigma_powers:
            v = jnp.einsum("ijk,ijd->ikd", phi * jnp.where(valid, sigma**q, 0.0)[..., None], unit)
            out += [v * ((radius / a_ref) ** p)[:, None, None] for p in self_powers]
        return jnp.where(mask[:, None, None], jnp.concatenate(out, axis=1), 0.0)

    return features


def design(params, config, trajectories, features, every, until):
    """``(X (rows, F), y (rows,))``: the descriptors and the negated one-step errors, a row per particle-axis-frame."""
    batched = jax.jit(jax.vmap(features, in_axes=(0, None, None)))
    xs, ys = [], []
    for traj in trajectories:
        frames, error, _ = one_step_errors(params, config, traj, every, until)
        n = traj.position.shape[1]
        v = np.asarray(batched(jnp.asarray(traj.position[frames]), jnp.asarray(traj.radius), jnp.ones(n, bool)))
        xs.append(v.transpose(0, 1, 3, 2).reshape(-1, v.shape[2]).astype(np.float64))  # (frame, i, D) rows
        ys.append(-error.reshape(-1).astype(np.float64))
    return np.concatenate(xs), np.concatenate(ys)


def fit_head(x, y, ridge=1e-6):
    """Least-squares ``c`` for ``y ~ X c`` on standardised columns, with a small ridge for conditioning."""
    scale = np.sqrt((x * x).mean(0)) + 1e-30
    xs = x / scale
    gram = xs.T @ xs + ridge * len(y) * np.eye(x.shape[1])
    return np.linalg.solve(gram, xs.T @ y) / scale


def explained(x, y, c):
    """Share of ``|y|^2`` that ``X c`` removes."""
    residual = y - x @ c
    return float(1.0 - (residual @ residual) / (y @ y))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fit-data", help="trajectories the head is fitted on (not with --head)")
    parser.add_argument("--fit-split", default="train")
    parser.add_argument("--fit-count", type=int, default=24, help="the first N trajectories of --fit-split")
    parser.add_argument("--data", required=True, help="where the head is scored (out of sample)")
    parser.add_argument("--splits", nargs="+", default=["test"])
    parser.add_argument("--limit", type=int, default=None, help="the first N trajectories of each split")
    parser.add_argument("--model", required=True)
    parser.add_argument("--centres", type=float, nargs="+", default=list(CENTRES))
    parser.add_argument("--width", type=float, default=0.05)
    parser.add_argument("--every", type=int, default=3)
    parser.add_argument("--until", type=int, default=300)
    parser.add_argument("--head", help="an earlier output whose fitted head to use (no fit)")
    parser.add_argument("--rollouts", action="store_true")
    parser.add_argument("--group", type=int, default=12)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    if bool(args.head) == bool(args.fit_data):
        parser.error("give either --fit-data (fit a head) or --head (use an earlier one), not both or neither")
    params, config = load(args.model)
    # Every setting of the descriptors, recorded: a head is only valid with the descriptors it was fitted on.
    settings = {
        "centres": list(args.centres),
        "width": args.width,
        "sigma_powers": list(SIGMA_POWERS),
        "self_powers": list(SELF_POWERS),
        "a_ref": A_REF,
    }
    features = shell_features_fn(tuple(args.centres), args.width, SIGMA_POWERS, SELF_POWERS, A_REF)
    result = {"model": args.model, "descriptors": settings}
    start = time.perf_counter()
    if args.head:
        previous = json.loads(Path(args.head).read_text())
        if previous.get("descriptors") != settings:
            fitted = previous.get("descriptors")
            parser.error(f"{args.head}: its head was fitted on descriptors {fitted}, not these {settings}")
        if previous.get("model") != args.model:
            parser.error(f"{args.head}: its head was fitted on {previous.get('model')}'s errors, not {args.model}'s")
        coefficients = np.asarray(previous["coefficients"])
        result |= {"head_from": args.head, "fit": previous["fit"]}
    else:
        _, fit_splits = load_dataset(args.fit_data, [args.fit_split])
        fit_set = fit_splits[args.fit_split][: args.fit_count]
        x_fit, y_fit = design(params, config, fit_set, features, args.every, args.until)
        coefficients = fit_head(x_fit, y_fit)
        result["fit"] = {
            "data": args.fit_data,
            "split": args.fit_split,
            "trajectories": len(fit_set),
            "explained_in_sample": explained(x_fit, y_fit, coefficients),
        }
        print("fit", result["fit"], f"{time.perf_counter() - start:.0f} s", flush=True)
    result["coefficients"] = coefficients.tolist()
    metadata, splits = load_dataset(args.data, args.splits)
    trajectories = [t for split in args.splits for t in splits[split][: args.limit]]
    x_out, y_out = design(params, config, trajectories, features, args.every, args.until)
    result["explained_out_of_sample"] = explained(x_out, y_out, coefficients)
    print("explained out of sample", result["explained_out_of_sample"], flush=True)
    if args.rollouts:
        c_head = jnp.asarray(coefficients, jnp.float32)
        scale = metadata.length_scale

        def head(x, radius_m, mask):
            return jnp.einsum("f,nfd->nd", c_head, features(x, radius_m / scale, mask))

        start = time.perf_counter()
        rollouts = hybrid_rollouts(params, config, metadata, trajectories, [0.0, 1.0], args.group, field=head)
        result["rollouts"] = {
            **paired_rows(rollouts, trajectories, config.input_sequence_length, "model + head"),
            "seconds": round(time.perf_counter() - start),
        }
    write_atomic(Path(args.out), (json.dumps(result, indent=1) + "\n").encode())
    print("wrote", args.out)


if __name__ == "__main__":
    main()
