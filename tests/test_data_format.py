"""The HDF5 dataset format: round trips, validation errors, atomic writes."""

import json
import os
import re

import h5py
import numpy as np
import pytest

from dispgns.data import format as fmt
from dispgns.data.format import (
    DatasetError,
    DatasetMetadata,
    Trajectory,
    load_dataset,
    read_metadata,
    read_split,
    write_metadata,
    write_split,
)
from dispgns.physics import PhysicsConfig

L = 0.1


def make_trajectory(seed=0, n_frames=5, n=4, dim=2, initial=True):
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(-0.08, 0.08, (n, dim))
    radius_m = rng.choice([0.002, 0.003, 0.005], n)
    position = x0[None] / L + rng.normal(0, 1e-3, (n_frames, n, dim)) * np.arange(n_frames)[:, None, None]
    kwargs = {}
    if initial:
        kwargs = dict(initial_position=x0, initial_velocity=rng.normal(0, 0.01, (n, dim)), initial_radius=radius_m)
    return Trajectory(
        position=position.astype(np.float32),
        radius=(radius_m / L).astype(np.float32),
        particle_type=np.zeros((n,), np.int32),
        attrs={"seed": seed, "split": "train", "radii_m": [0.002, 0.003, 0.005]},
        **kwargs,
    )


def make_metadata(counts=None, n_frames=5, particles=None, **overrides):
    counts = counts or {"train": 2, "valid": 1}
    values = dict(
        dim=2,
        sequence_length=n_frames,
        frame_dt=15 * 1e-4,
        save_every=15,
        box_half_size=L,
        connectivity_radius=0.2,
        trajectory_counts=counts,
        radii={s: fmt.radii_groups([(c, [0.002, 0.003, 0.005])]) for s, c in counts.items()},
        physics=PhysicsConfig().to_dict(),
        seed=3,
        precision="float32",
        particle_counts=particles,
    )
    values.update(overrides)
    return DatasetMetadata(**values)


@pytest.fixture
def dataset(tmp_path):
    """A small valid dataset directory: 2 train + 1 valid trajectories."""
    train = [make_trajectory(0, n=4), make_trajectory(1, n=6)]
    valid = [make_trajectory(2, n=5)]
    write_split(tmp_path / "train.h5", train, box_half_size=L)
    write_split(tmp_path / "valid.h5", valid, box_half_size=L)
    write_metadata(tmp_path, make_metadata(particles={"train": [4, 6], "valid": [5]}))
    return tmp_path, {"train": train, "valid": valid}


def assert_same(a: Trajectory, b: Trajectory):
    for name in ("position", "radius", "initial_position", "initial_velocity", "initial_radius", "particle_type"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
            continue
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert dict(a.attrs) == dict(b.attrs)


def test_round_trip(dataset):
    directory, written = dataset
    metadata, splits = load_dataset(directory)
    assert metadata == make_metadata(particles={"train": [4, 6], "valid": [5]})
    assert set(splits) == {"train", "valid"}
    for split, trajectories in written.items():
        assert len(splits[split]) == len(trajectories)
        for a, b in zip(trajectories, splits[split]):
            assert_same(a, b)
    assert splits["train"][1].position.dtype == np.float32
    assert splits["train"][1].initial_position.dtype == np.float64
    # One split only, and reading without metadata.
    _, only = load_dataset(directory, splits=["valid"])
    assert list(only) == ["valid"]
    assert_same(read_split(directory / "valid.h5")[0], written["valid"][0])


def test_round_trip_without_initial_state(tmp_path):
    trajectory = make_trajectory(initial=False)
    write_split(tmp_path / "test.h5", [trajectory])
    (read,) = read_split(tmp_path / "test.h5")
    assert not read.has_initial_state
    assert_same(trajectory, read)


def test_metadata_dict_round_trip_and_physics():
    metadata = make_metadata(physics=PhysicsConfig(cutoff=0.02).to_dict())
    again = DatasetMetadata.from_dict(json.loads(json.dumps(metadata.to_dict())))
    assert again == metadata
    assert again.physics_config == PhysicsConfig(cutoff=0.02)
    assert again.bounds == ((-1.0, 1.0), (-1.0, 1.0))
    assert again.splits == ("train", "valid")


def _edit(path, trajectory, field, value):
    with h5py.File(path, "r+") as file:
        group = file[trajectory]
        del group[field]
        if value is not None:
            group.create_dataset(field, data=value)


def _clean(path, trajectory, field):
    with h5py.File(path, "r") as file:
        return file[trajectory][field][()]


@pytest.mark.parametrize(
    "field, change, message",
    [
        ("radius", lambda r: r[:, None], r"'radius' has shape \(6, 1\), expected \(6,\)"),
        ("position", lambda p: p.astype(np.float64), r"'position' has dtype float64, expected float32"),
        ("position", lambda p: p[:, :, :1], r"'position' has shape \(5, 6, 1\), expected \(5, \?, 2\)"),
        (
            "position",
            lambda p: np.where(np.arange(p.size).reshape(p.shape) == 7, np.nan, p).astype(np.float32),
            r"'position' has a non-finite value nan at index \(0, 3, 1\)",
        ),
        (
            "position",
            lambda p: np.where(np.arange(p.size).reshape(p.shape) == 13, 1.5, p).astype(np.float32),
            r"'position' frame 1 particle 0 axis 1 is 1.5, expected inside the box \[-1, 1\]",
        ),
        (
            "radius",
            lambda r: np.where(np.arange(r.size) == 2, 0.0, r).astype(np.float32),
            r"'radius' of particle 2 is 0, expected 0 < radius / L < 1",
        ),
        ("radius", lambda r: -r, r"'radius' of particle 0 is -0\.\d+, expected 0 < radius / L < 1"),
        ("radius", lambda r: r.astype(np.float16), r"'radius' has dtype float16, expected float32"),
        ("particle_type", lambda t: t.astype(np.float32), r"'particle_type' has dtype float32, expected an integer"),
        ("initial_position", lambda x: x[:5], r"'initial_position' has shape \(5, 2\), expected \(6, 2\)"),
        ("initial_velocity", lambda v: v.astype(np.float32), r"'initial_velocity' has dtype float32, expected float64"),
        ("initial_position", lambda x: x + 0.01, r"'initial_position' / L differs from 'position' frame 0"),
        ("initial_position", lambda x: x * 20, r"'initial_position' particle \d+ axis \d+ is .* expected inside"),
        ("radius", None, r"missing field 'radius'"),
        ("position", None, r"missing field 'position'"),
        ("initial_velocity", None, r"missing field 'initial_velocity'"),
    ],
)
def test_read_rejects_bad_field(dataset, field, change, message):
    directory, _ = dataset
    path = directory / "train.h5"
    value = None if change is None else change(_clean(path, "00001", field))
    _edit(path, "00001", field, value)
    # The message names the file with its directory.
    with pytest.raises(DatasetError, match="^" + re.escape(str(path)) + r": trajectory 00001: " + message):
        load_dataset(directory)


def test_missing_initial_state_is_fine_without_the_metadata_flag(dataset):
    directory, _ = dataset
    for field in ("initial_position", "initial_velocity", "initial_radius"):
        _edit(directory / "train.h5", "00000", field, None)
    with pytest.raises(DatasetError, match="missing field 'initial_position', expected because metadata.json"):
        load_dataset(directory)
    write_metadata(directory, make_metadata(particles={"train": [4, 6], "valid": [5]}, has_initial_state=False))
    _, splits = load_dataset(directory)
    assert not splits["train"][0].has_initial_state and splits["train"][1].has_initial_state


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(n_frames=7), r"train\.h5: trajectory 00000: 'position' has shape \(5, 4, 2\), expected \(7, \?, 2\)"),
        (dict(counts={"train": 3, "valid": 1}), r"train\.h5: holds 2 trajectories, expected 3 \(metadata.json\)"),
        (
            dict(particles={"train": [4, 7], "valid": [5]}),
            r"train\.h5: trajectory 00001: 'position' holds 6 particles, expected 7",
        ),
        (
            dict(box_half_size=0.05, physics=PhysicsConfig(box_half_size=0.05).to_dict()),
            r"train\.h5: trajectory 00000: 'initial_position'",
        ),
    ],
)
def test_read_rejects_metadata_mismatch(dataset, overrides, message):
    directory, _ = dataset
    write_metadata(directory, make_metadata(**overrides))
    with pytest.raises(DatasetError, match=message):
        load_dataset(directory)


def test_metadata_dim_mismatch(dataset):
    directory, _ = dataset
    metadata = make_metadata(dim=3)
    write_metadata(directory, metadata)
    with pytest.raises(
        DatasetError,
        match=r"train\.h5: trajectory 00000: 'position' has shape \(5, 4, 2\), "
        r"expected \(5, \?, 3\)",
    ):
        load_dataset(directory)


def test_missing_split_file_and_unknown_split(dataset):
    directory, _ = dataset
    os.remove(directory / "valid.h5")
    with pytest.raises(DatasetError, match=r"valid\.h5: file not found"):
        load_dataset(directory)
    with pytest.raises(DatasetError, match=r"no split 'test'"):
        load_dataset(directory, splits=["test"])


def test_trajectory_groups_must_be_numbered(dataset):
    directory, _ = dataset
    with h5py.File(directory / "train.h5", "r+") as file:
        file.move("00001", "00005")
    with pytest.raises(DatasetError, match=r"train\.h5: group '00005' found where '00001' was expected"):
        read_split(directory / "train.h5")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.pop("sequence_length"), r"missing field 'sequence_length'"),
        (lambda d: d.update(colour="red"), r"unknown field\(s\) \['colour'\]"),
        (lambda d: d.update(dim=4), r"'dim' is 4, expected 2 or 3"),
        (lambda d: d.update(frame_dt=1.0), r"'frame_dt' is 1.0, expected save_every \* physics.dt"),
        (
            lambda d: d["trajectory_counts"].update(train=5),
            r"'radii'\['train'\] groups hold 2 trajectories, expected 5",
        ),
        (lambda d: d["physics"].update(density=-1.0), r"'physics' is not a valid PhysicsConfig"),
        (lambda d: d.update(format_version=99), r"'format_version' is 99, expected 1"),
        (lambda d: d.update(seed="abc"), r"'seed' is 'abc', expected null or an integer"),
        (lambda d: d.update(seed=-5), r"'seed' is -5"),
        (lambda d: d.update(has_initial_state="yes"), r"'has_initial_state' is 'yes', expected true or false"),
        (lambda d: d["trajectory_counts"].update(train=True), r"'trajectory_counts'\['train'\] is True"),
        (lambda d: d["radii"]["train"][0].update(radii_m=[-0.002]), r"'radii'\['train'\] radii_m \[-0.002\], expected"),
        (lambda d: d.update(split_ids={"train": "x"}), r"'split_ids' is"),
        (lambda d: d.update(source=5), r"'source' is 5, expected a string"),
    ],
)
def test_read_metadata_rejects_bad_json(dataset, edit, message):
    directory, _ = dataset
    values = json.loads((directory / "metadata.json").read_text())
    edit(values)
    (directory / "metadata.json").write_text(json.dumps(values))
    with pytest.raises(DatasetError, match=r"metadata\.json: " + message):
        read_metadata(directory)


def test_read_metadata_rejects_missing_and_garbage(tmp_path):
    with pytest.raises(DatasetError, match=r"metadata\.json: not found"):
        read_metadata(tmp_path)
    (tmp_path / "metadata.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"metadata\.json: cannot be read as JSON"):
        read_metadata(tmp_path)
    (tmp_path / "train.h5").write_text("not hdf5")
    with pytest.raises(DatasetError, match=r"train\.h5: cannot be opened as HDF5"):
        read_split(tmp_path / "train.h5")


def test_write_validates_before_writing(tmp_path):
    bad = make_trajectory()
    bad = Trajectory(position=bad.position, radius=bad.radius.astype(np.float64))
    with pytest.raises(DatasetError, match=r"train\.h5: trajectory 00000: 'radius' has dtype float64"):
        write_split(tmp_path / "train.h5", [bad])
    half = make_trajectory()
    half = Trajectory(position=half.position, radius=half.radius, initial_position=half.initial_position)
    with pytest.raises(DatasetError, match=r"missing field 'initial_velocity'"):
        write_split(tmp_path / "train.h5", [half])
    assert list(tmp_path.iterdir()) == []


def test_write_split_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "train.h5"
    write_split(target, [make_trajectory(0)])
    before = target.read_bytes()
    calls = []
    original = h5py.Group.create_dataset

    def failing(self, name, *args, **kwargs):
        calls.append(name)
        if len(calls) == 8:
            raise OSError("disk full")
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing)
    with pytest.raises(OSError, match="disk full"):
        write_split(target, [make_trajectory(1), make_trajectory(2)])
    assert len(calls) == 8
    # The old file is untouched and no temporary file is left.
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["train.h5"]


def test_write_metadata_is_atomic(tmp_path, monkeypatch):
    write_metadata(tmp_path, make_metadata())
    before = (tmp_path / "metadata.json").read_text()

    def failing(*args, **kwargs):
        raise OSError("rename failed")

    monkeypatch.setattr(fmt.os, "replace", failing)
    with pytest.raises(OSError, match="rename failed"):
        write_metadata(tmp_path, make_metadata(seed=4))
    assert (tmp_path / "metadata.json").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["metadata.json"]


def test_staged_directory(tmp_path):
    target = tmp_path / "a" / "b" / "dataset"
    with pytest.raises(RuntimeError):
        with fmt.staged_directory(target) as staging:
            (staging / "metadata.json").write_text("{}")
            raise RuntimeError("boom")
    # Neither the target, nor the parents made for it, nor the staging directory remain.
    assert list(tmp_path.iterdir()) == []
    with fmt.staged_directory(target) as staging:
        (staging / "metadata.json").write_text("{}")
    assert (target / "metadata.json").read_text() == "{}"
    assert sorted(p.name for p in target.parent.iterdir()) == ["dataset"]
    with pytest.raises(FileExistsError, match="not empty"):
        with fmt.staged_directory(target):
            pass
    with fmt.staged_directory(target, overwrite=True) as staging:
        (staging / "metadata.json").write_text("[]")
    assert (target / "metadata.json").read_text() == "[]"
    assert sorted(p.name for p in target.parent.iterdir()) == ["dataset"]
    other = tmp_path / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not a dispgns dataset"):
        with fmt.staged_directory(other, overwrite=True):
            pass
    assert (other / "todo.txt").read_text() == "keep me"
