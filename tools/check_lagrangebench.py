"""Check a ``dispgns export lagrangebench`` directory with LagrangeBench 0.2.0's own loader and case setup.

Run it with the Python of a LagrangeBench venv (``tools/lagrangebench_env.sh``), not with
dispgns's (LagrangeBench pins jax 0.4.29); it imports no dispgns code:

    LB_VENV=/tmp/lb-venv bash tools/lagrangebench_env.sh
    /tmp/lb-venv/bin/python tools/check_lagrangebench.py EXPORT_DIR [EXPORT_DIR/test_unseen ...]

For each directory it
  1. opens train, valid and test with ``lagrangebench.data.H5Dataset`` (training windows and
     evaluation trajectories) and batches two of each with LagrangeBench's ``numpy_collate`` through
     a torch ``DataLoader`` (equal particle counts are needed for that);
  2. builds the case exactly as LagrangeBench's runner does (``box`` from ``bounds``,
     ``case_builder(box, metadata, ...)``) and runs its ``allocate``/``preprocess`` (with noise) and
     ``allocate_eval``/``preprocess_eval`` on those samples;
  3. checks what came out: the neighbour list of the real particles equals the brute-force pairs
     within ``default_connectivity_radius`` (padding has no edge), the targets are the
     normalised second differences of the positions, the metadata's statistics equal those
     recomputed from the training windows LagrangeBench serves (padding excluded), and the
     normalisation LagrangeBench derives from them.
Prints one JSON line per directory and exits non-zero on the first failure.
"""

from __future__ import annotations

import json
import sys
import warnings

import h5py
import numpy as np

warnings.filterwarnings("ignore", message="Dataset directory")  # our directory names are not LB's


def check(path: str) -> dict:
    import jax
    import jax.numpy as jnp
    from lagrangebench import case_builder
    from lagrangebench.data import H5Dataset
    from lagrangebench.data.utils import numpy_collate
    from lagrangebench.utils import NodeType
    from torch.utils.data import DataLoader

    input_seq_length = 3
    train = H5Dataset("train", path, input_seq_length=input_seq_length, extra_seq_length=1)
    evals = {s: H5Dataset(s, path, input_seq_length=input_seq_length, extra_seq_length=2) for s in ("valid", "test")}
    metadata = train.metadata
    n_max = metadata["num_particles_max"]
    for dataset in (train, *evals.values()):
        loader = DataLoader(dataset, batch_size=2, shuffle=False, collate_fn=numpy_collate)
        position, kinds = next(iter(loader))
        assert position.shape[1] == n_max and kinds.shape == (position.shape[0], n_max), (position.shape, kinds.shape)

    bounds = np.array(metadata["bounds"])
    box = bounds[:, 1] - bounds[:, 0]
    case = case_builder(box=box, metadata=metadata, input_seq_length=input_seq_length, noise_std=3e-4)
    radius = metadata["default_connectivity_radius"]
    key = jax.random.PRNGKey(0)
    checked_edges = 0
    for index in range(len(train.traj_keys)):
        window = sum(train._keylen_cumulative[:index][-1:]) if index else 0
        sample = train[window]
        position, kinds = sample
        real = kinds != NodeType.PAD_VALUE
        assert np.all(kinds[real] == NodeType.FLUID), "real particles must be fluid (type 0)"
        key, features, target, neighbors = case.allocate(key, sample, 0.0)
        assert not bool(neighbors.did_buffer_overflow)
        # Without noise the target is LagrangeBench's normalised acceleration of the data.
        stats = case.normalization_stats["acceleration"]
        acc = position[:, input_seq_length] - 2 * position[:, input_seq_length - 1] + position[:, input_seq_length - 2]
        np.testing.assert_allclose(
            np.asarray(target["acc"])[real], ((acc - stats["mean"]) / stats["std"])[real], rtol=1e-4, atol=1e-3
        )
        # Neighbours of the real particles at the last input frame == brute force.
        x = position[:, input_seq_length - 1]
        senders, receivers = np.asarray(neighbors.idx)
        keep = (senders < x.shape[0]) & (receivers < x.shape[0])
        got = {(int(s), int(r)) for s, r in zip(senders[keep], receivers[keep])}
        assert all(real[s] and real[r] for s, r in got), "an edge touches a padding particle"
        distance = np.linalg.norm(x[:, None] - x[None, :], axis=-1)
        want = {(int(s), int(r)) for s, r in np.argwhere((distance < radius) & real[:, None] & real[None, :])}
        missing, extra = want - got, got - want
        # jax-md's list is built with r_cutoff; pairs at exactly the cut-off may go either way.
        borderline = {p for p in missing | extra if abs(distance[p] - radius) < 1e-5}
        assert not (missing | extra) - borderline, f"{path} {index}: {len(missing)} missing, {len(extra)} extra"
        checked_edges += len(got)
        # With noise, jitted preprocess runs too.
        key, features, target, neighbors = case.preprocess(key, sample, 3e-4, neighbors)
        assert np.all(np.isfinite(np.asarray(target["acc"])[real]))
    for split, dataset in evals.items():
        sample = dataset[0]
        features, neighbors = case.allocate_eval(sample)
        features, neighbors = case.preprocess_eval(sample, neighbors)
        assert not bool(neighbors.did_buffer_overflow)
        assert np.all(np.isfinite(np.asarray(features["vel_hist"]))), split

    # The statistics in metadata.json are those of the training split as LagrangeBench serves it.
    with h5py.File(f"{path}/train.h5") as file:
        velocities, accelerations = [], []
        for name in file:
            x = file[name]["position"][()].astype(np.float64)
            real = file[name]["particle_type"][()] != NodeType.PAD_VALUE
            x = x[:, real]
            velocities.append(np.diff(x, axis=0).reshape(-1, x.shape[-1]))
            accelerations.append(np.diff(x, n=2, axis=0).reshape(-1, x.shape[-1]))
    for name, values in (("vel", np.concatenate(velocities)), ("acc", np.concatenate(accelerations))):
        np.testing.assert_allclose(metadata[f"{name}_mean"], values.mean(0), rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(metadata[f"{name}_std"], values.std(0), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(
        case.normalization_stats["velocity"]["std"],
        jnp.sqrt(jnp.array(metadata["vel_std"]) ** 2 + 3e-4**2),
        rtol=1e-5,
    )
    return {
        "path": path,
        "ok": True,
        "lagrangebench": __import__("lagrangebench").__version__,
        "jax": jax.__version__,
        "train_windows": len(train),
        "valid_samples": len(evals["valid"]),
        "test_samples": len(evals["test"]),
        "num_particles_max": n_max,
        "edges_checked": checked_edges,
    }


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__, file=sys.stderr)
        return 2
    for path in paths:
        print(json.dumps(check(path)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
