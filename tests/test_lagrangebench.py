"""LagrangeBench compatibility: the metadata keys it reads, and ``dispgns export lagrangebench``.

The fast tests check the keys, their values against an independent computation, the padding and
the shift of the export, and that dispgns reads the export back. The slow test runs LagrangeBench
0.2.0's own H5Dataset and case_builder on an export (tools/check_lagrangebench.py) in its own venv.
"""

import json
import os
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from dispgns.cli import main
from dispgns.data import DatasetError, DatasetMetadata, Trajectory, load_dataset, read_metadata, write_split
from dispgns.data.format import (
    LAGRANGEBENCH_KEYS,
    PAD_TYPE,
    motion_statistics,
    radii_groups,
    training_statistics,
    write_metadata,
)
from dispgns.data.lagrangebench import OFFSET, export_lagrangebench
from dispgns.physics import PhysicsConfig

L = 0.1
RADII_M = [0.002, 0.003, 0.005]
COUNTS = {"train": [4, 7], "valid": [5], "test": [6], "test_unseen": [9]}


def _trajectory(rng, n, n_frames=8):
    start = rng.uniform(-0.7, 0.7, (n, 2))
    drift = rng.normal(0, 0.01, (n, 2))
    wobble = rng.normal(0, 1e-3, (n_frames, n, 2))
    position = start[None] + drift[None] * np.arange(n_frames)[:, None, None] + wobble
    radius = rng.choice(RADII_M, n) / L
    return Trajectory(position=position.astype(np.float32), radius=radius.astype(np.float32))


@pytest.fixture
def dataset(tmp_path):
    """A small dispgns dataset whose trajectories have different particle counts."""
    rng = np.random.default_rng(0)
    splits = {s: [_trajectory(rng, n) for n in counts] for s, counts in COUNTS.items()}
    directory = tmp_path / "data"
    directory.mkdir()
    for split, trajectories in splits.items():
        write_split(directory / f"{split}.h5", trajectories)
    metadata = DatasetMetadata(
        dim=2,
        sequence_length=8,
        frame_dt=15e-4,
        save_every=15,
        box_half_size=L,
        connectivity_radius=0.2,
        trajectory_counts={s: len(c) for s, c in COUNTS.items()},
        radii={s: radii_groups([(len(c), RADII_M)]) for s, c in COUNTS.items()},
        physics=PhysicsConfig().to_dict(),
        has_initial_state=False,
        particle_counts=COUNTS,
        **training_statistics(splits),
    )
    write_metadata(directory, metadata)
    return directory, splits


def _independent_statistics(positions):
    velocity = np.concatenate([np.diff(p.astype(np.float64), axis=0).reshape(-1, 2) for p in positions])
    acceleration = np.concatenate([np.diff(p.astype(np.float64), n=2, axis=0).reshape(-1, 2) for p in positions])
    return {
        "vel_mean": velocity.mean(0),
        "vel_std": velocity.std(0),
        "acc_mean": acceleration.mean(0),
        "acc_std": acceleration.std(0),
    }


def test_metadata_carries_every_lagrangebench_key_with_its_value(dataset):
    directory, splits = dataset
    values = json.loads((directory / "metadata.json").read_text())
    assert set(LAGRANGEBENCH_KEYS) <= set(values)
    assert values["dim"] == 2 and values["bounds"] == [[-1.0, 1.0], [-1.0, 1.0]]
    assert values["dt"] == PhysicsConfig().dt == 1e-4 and values["write_every"] == 15
    assert values["dt"] * values["write_every"] == pytest.approx(values["frame_dt"])
    assert values["dx"] == pytest.approx(2 * np.mean(RADII_M) / L)
    assert values["default_connectivity_radius"] == values["connectivity_radius"] == 0.2
    assert values["num_particles_max"] == 9
    assert values["periodic_boundary_conditions"] == [False, False]
    want = _independent_statistics([t.position for t in splits["train"]])
    for name, expected in want.items():
        np.testing.assert_allclose(values[name], expected, rtol=1e-9, atol=1e-15)
    # Only the training split counts: the valid trajectories change nothing.
    assert motion_statistics([t.position for t in splits["train"]]) == {
        k: values[k] for k in ("vel_mean", "vel_std", "acc_mean", "acc_std")
    }


def test_metadata_round_trip_old_files_and_inconsistent_keys(dataset):
    directory, _ = dataset
    metadata = read_metadata(directory)
    assert DatasetMetadata.from_dict(json.loads(json.dumps(metadata.to_dict()))) == metadata
    values = json.loads((directory / "metadata.json").read_text())
    # A dataset written before these keys existed still loads, without statistics.
    old = {k: v for k, v in values.items() if k not in LAGRANGEBENCH_KEYS or k in ("dim", "bounds")}
    del old["position_offset"]
    loaded = DatasetMetadata.from_dict(old)
    assert loaded.vel_mean is None and "acc_std" not in loaded.to_dict()
    with pytest.raises(DatasetError, match=r"'write_every' is 10, expected 15"):
        DatasetMetadata.from_dict({**values, "write_every": 10})
    with pytest.raises(DatasetError, match=r"'acc_std' is missing"):
        DatasetMetadata.from_dict({k: v for k, v in values.items() if k != "acc_std"})
    with pytest.raises(DatasetError, match=r"'num_particles_max' is 3, expected null or an integer >= 9"):
        DatasetMetadata.from_dict({**values, "num_particles_max": 3})


def test_export_pads_shifts_and_reads_back(dataset, tmp_path):
    directory, splits = dataset
    out = tmp_path / "lb"
    result = export_lagrangebench(directory, out)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "test.h5", "test_unseen", "train.h5", "valid.h5"]
    unseen = out / "test_unseen"
    assert sorted(p.name for p in unseen.iterdir()) == ["metadata.json", "test.h5", "train.h5", "valid.h5"]
    values = json.loads((out / "metadata.json").read_text())
    assert values["bounds"] == [[0.0, 2.0], [0.0, 2.0]] and values["num_particles_max"] == 9
    assert set(values["trajectory_counts"]) == {"train", "valid", "test"}
    unseen_values = json.loads((unseen / "metadata.json").read_text())
    assert unseen_values["trajectory_counts"] == {"train": 2, "valid": 1, "test": 1}
    for name in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        # Statistics of the training split as exported (shifted float32), in both directories.
        want = _independent_statistics([t.position + np.float32(OFFSET) for t in splits["train"]])[name]
        np.testing.assert_allclose(values[name], want, rtol=1e-9, atol=1e-15)
        assert unseen_values[name] == values[name]
    with h5py.File(out / "train.h5") as file:
        group = file["00000"]
        position, kinds, radius = group["position"][()], group["particle_type"][()], group["radius"][()]
        assert all(group[name].fletcher32 for name in ("position", "particle_type", "radius"))  # a flipped bit fails
    n = COUNTS["train"][0]
    assert position.shape == (8, 9, 2) and kinds.shape == radius.shape == (9,)
    assert np.all(kinds[:n] == 0) and PAD_TYPE == -1 and np.all(kinds[n:] == PAD_TYPE) and np.all(radius[n:] == 0)
    np.testing.assert_allclose(position[:, :n], splits["train"][0].position + 1.0, atol=1.2e-7, rtol=0)
    assert np.all(position[:, :n] >= 0) and np.all(position[:, :n] <= 2)
    # Padding sits further than the connectivity radius from the box, so from every real particle.
    assert np.all(position[:, n:] > 2.0 + 0.2)
    # dispgns reads the export as a dataset: padding dropped, shift undone (to float32 rounding).
    for path, mapping in (
        (out, {"train": "train", "valid": "valid", "test": "test"}),
        (unseen, {"test": "test_unseen"}),
    ):
        metadata, read = load_dataset(path)
        assert metadata.bounds == ((-1.0, 1.0), (-1.0, 1.0))
        for new, old in mapping.items():
            for got, want in zip(read[new], splits[old]):
                assert got.n_particles == want.n_particles
                np.testing.assert_allclose(got.position, want.position, atol=1.2e-7, rtol=0)
                np.testing.assert_array_equal(got.radius, want.radius)
    assert result[""] == read_metadata(out)


def test_export_refuses_existing_output_and_datasets_without_train(dataset, tmp_path, capsys):
    directory, _ = dataset
    out = tmp_path / "lb"
    assert main(["export", "lagrangebench", str(directory), "--out", str(out)]) == 0
    before = (out / "metadata.json").read_text()
    assert main(["export", "lagrangebench", str(directory), "--out", str(out)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert main(["export", "lagrangebench", str(directory), "--out", str(out), "--overwrite"]) == 0
    assert (out / "metadata.json").read_text() == before
    values = json.loads((directory / "metadata.json").read_text())
    (directory / "train.h5").unlink()
    values = {k: v for k, v in values.items() if k not in ("vel_mean", "vel_std", "acc_mean", "acc_std")}
    for key in ("trajectory_counts", "radii", "particle_counts"):
        values[key] = {s: v for s, v in values[key].items() if s != "train"}
    values["num_particles_max"] = 9
    (directory / "metadata.json").write_text(json.dumps(values))
    with pytest.raises(DatasetError, match=r"no 'train' split, expected one"):
        export_lagrangebench(directory, tmp_path / "other")
    assert not (tmp_path / "other").exists()


def _lagrangebench_python():
    candidates = [os.environ.get("DISPGNS_LAGRANGEBENCH_PYTHON"), "/work/lb-venv/bin/python", "/tmp/lb-venv/bin/python"]
    return next((Path(c) for c in candidates if c and Path(c).is_file()), None)


@pytest.mark.slow
def test_lagrangebench_reads_the_export_with_its_own_loader(tiny_dataset, tmp_path):
    """LagrangeBench 0.2.0's H5Dataset and case_builder on an exported tiny dataset (its own venv)."""
    python = _lagrangebench_python()
    if python is None:
        pytest.skip(
            "no LagrangeBench venv: build one with tools/lagrangebench_env.sh and point "
            "DISPGNS_LAGRANGEBENCH_PYTHON at its python"
        )
    out = tmp_path / "lb"
    export_lagrangebench(tiny_dataset, out)
    script = Path(__file__).resolve().parents[1] / "tools" / "check_lagrangebench.py"
    run = subprocess.run(
        [str(python), str(script), str(out), str(out / "test_unseen")], capture_output=True, text=True, timeout=900
    )
    assert run.returncode == 0, run.stderr[-3000:]
    reports = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    assert [r["ok"] for r in reports] == [True, True]
    assert reports[0]["num_particles_max"] == 46 and reports[0]["edges_checked"] > 0
