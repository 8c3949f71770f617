"""The authors' ``.npz`` importer and ``dispgns import-npz``."""

import numpy as np
import pytest

from dispgns.cli import main
from dispgns.data import DatasetError, load_dataset
from dispgns.data.importers import UntrustedPickleError, import_authors_npz, read_authors_npz

L = 0.1


def authors_trajectory(seed, n_frames=7, n=5, radii_mm=(2.0, 3.5, 5.0)):
    """One entry in the authors' layout: an object array (positions / L, radii / L)."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-0.9, 0.9, (1, n, 2)) - 0.01 * np.arange(n_frames)[:, None, None] * [0, 1]
    radii = rng.choice(np.asarray(radii_mm) * 1e-3 / L, n)
    entry = np.empty(2, dtype=object)
    entry[0], entry[1] = positions, radii
    return entry


def write_npz(path, entries):
    # np.savez pickles object arrays: exactly what the authors' files hold.
    np.savez(path, **{f"simulation_trajectory_{i}": entry for i, entry in enumerate(entries)})
    return path


@pytest.fixture
def npz(tmp_path):
    return write_npz(tmp_path / "train.npz", [authors_trajectory(0), authors_trajectory(1, n=8)])


def test_refuses_without_trust(npz, tmp_path):
    with pytest.raises(UntrustedPickleError, match=r"train\.npz: .*pickle.*trust_pickle=True \(--trust-pickle\)"):
        import_authors_npz(npz, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_import_with_trust(npz, tmp_path):
    out = tmp_path / "out"
    metadata = import_authors_npz(npz, out, trust_pickle=True)
    assert not metadata.has_initial_state and metadata.source == "authors_npz" and metadata.seed is None
    assert metadata.trajectory_counts == {"train": 2}
    assert metadata.particle_counts == {"train": [5, 8]}
    assert metadata.sequence_length == 7 and metadata.dim == 2 and metadata.box_half_size == L
    assert metadata.frame_dt == pytest.approx(1.5e-3)
    (group,) = metadata.radii["train"]
    assert group["source_file"] == "train.npz" and set(group["radii_mm"]) <= {2.0, 3.5, 5.0}
    assert metadata.connectivity_radius == pytest.approx(4 * max(group["radii_m"]) / L)
    read, splits = load_dataset(out)
    assert read == metadata
    original = np.load(npz, allow_pickle=True)
    for trajectory, key in zip(splits["train"], original.files):
        positions, radii = original[key]
        assert trajectory.initial_position is None and not trajectory.has_initial_state
        np.testing.assert_array_equal(trajectory.position, positions.astype(np.float32))
        np.testing.assert_array_equal(trajectory.radius, radii.astype(np.float32))
        np.testing.assert_array_equal(trajectory.particle_type, 0)
        assert trajectory.attrs["source_key"] == key


def test_import_further_splits(npz, tmp_path):
    out = tmp_path / "out"
    import_authors_npz(npz, out, trust_pickle=True)
    test = write_npz(tmp_path / "test.npz", [authors_trajectory(5, radii_mm=(2.75, 4.25))])
    metadata = import_authors_npz(test, out, trust_pickle=True, split="test_unseen")
    assert metadata.trajectory_counts == {"train": 2, "test_unseen": 1}
    assert load_dataset(out)[0] == metadata
    with pytest.raises(FileExistsError, match="already has a 'train' split"):
        import_authors_npz(test, out, trust_pickle=True, split="train")
    metadata = import_authors_npz(test, out, trust_pickle=True, split="train", overwrite=True)
    assert metadata.trajectory_counts == {"train": 1, "test_unseen": 1}
    longer = write_npz(tmp_path / "valid.npz", [authors_trajectory(6, n_frames=9)])
    with pytest.raises(DatasetError, match=r"valid\.npz: sequence_length is 9, expected 7"):
        import_authors_npz(longer, out, trust_pickle=True, split="valid")
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "test_unseen.h5", "train.h5"]


def _bad(edit):
    entry = authors_trajectory(0)
    edit(entry)
    return entry


def _nan(entry):
    entry[0] = entry[0].copy()
    entry[0][3, 2, 0] = np.nan


@pytest.mark.parametrize(
    "entry, message",
    [
        (_bad(_nan), r"positions have a non-finite value at index \(3, 2, 0\)"),
        (
            _bad(lambda e: e.__setitem__(0, e[0] * 20)),
            r"position of particle 0 at frame 0, axis 0 is 4.93062, expected inside the normalised box \[-1, 1\]",
        ),
        (_bad(lambda e: e.__setitem__(1, e[1][:4])), r"radii have shape \(4,\), expected \(5,\)"),
        (_bad(lambda e: e.__setitem__(1, -e[1])), r"radius of particle 0 is -0\.\d+, expected 0 < radius / L < 1"),
        (_bad(lambda e: e.__setitem__(0, e[0][0])), r"positions have shape \(5, 2\), expected \(T, N, 2\)"),
        (np.zeros((3, 2)), r"is an array of dtype float64 and shape \(3, 2\), expected an object array"),
    ],
)
def test_rejects_malformed_files(tmp_path, entry, message):
    path = write_npz(tmp_path / "bad.npz", [entry])
    with pytest.raises(DatasetError, match=r"bad\.npz: key 'simulation_trajectory_0': " + message):
        read_authors_npz(path, trust_pickle=True)
    with pytest.raises(DatasetError):
        import_authors_npz(path, tmp_path / "out", trust_pickle=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"]


def test_rejects_missing_and_non_npz(tmp_path):
    with pytest.raises(DatasetError, match=r"missing\.npz: file not found"):
        read_authors_npz(tmp_path / "missing.npz", trust_pickle=True)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(DatasetError, match=r"junk\.npz: cannot be read as .npz: not a zip archive"):
        read_authors_npz(tmp_path / "junk.npz", trust_pickle=True)


def test_cli_import(npz, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["import-npz", str(npz), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "--trust-pickle" in error and "train.npz" in error
    assert not out.exists()
    assert main(["import-npz", str(npz), "--out", str(out), "--split", "valid", "--trust-pickle"]) == 0
    printed = capsys.readouterr().out
    assert "2 trajectories, 7 frames each, 5-8 particles" in printed
    assert load_dataset(out)[0].trajectory_counts == {"valid": 2}
    assert main(["import-npz", str(npz), "--out", str(out), "--split", "valid", "--trust-pickle"]) == 2
    assert "already has a 'valid' split" in capsys.readouterr().err
