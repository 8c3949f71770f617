"""Dataset generation and ``dispgns generate``: determinism, re-runnability, atomicity."""

import dataclasses
import math

import h5py
import jax
import numpy as np
import pytest

import dispgns.physics.initial
from dispgns.cli import main
from dispgns.data import generate as gen
from dispgns.data.format import DatasetError, load_dataset
from dispgns.data.generate import (
    DatasetSpec,
    RadiiGroup,
    generate_dataset,
    paper_spec,
    preset,
    sample_initial_states,
    tiny_spec,
    trajectory_key,
)
from dispgns.physics import PhysicsConfig, PlacementError, particle_count_range, sample_initial_state, simulate

# Every real generation here uses the tiny preset at this length, so the
# compiled simulation is shared between tests.
FRAMES = 12


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny") / "dataset"
    metadata = generate_dataset(tiny_spec().replace(n_frames=FRAMES), out, seed=0)
    return out, metadata


def fake_simulate_batch(calls=None):
    """A stand-in for simulate_batch: frame k is x0 + k * 1e-6 m along x (no compilation)."""

    def fake(x0, v0, radius, mask, config, *, n_frames, save_every, progress=None, compiler_options=None):
        if calls is not None:
            calls.append(x0.shape)
        steps = np.arange(n_frames)[None, :, None, None] * np.array([1e-6, 0.0])
        if progress is not None:
            progress(n_frames - 1)
        return np.asarray(x0)[:, None] + steps.astype(x0.dtype)

    return fake


def listing(directory):
    return sorted(p.name for p in directory.iterdir())


# ----------------------------------------------------------------------------- specs


def test_paper_preset():
    spec = paper_spec()
    assert spec.counts == {"train": 16, "valid": 6, "test": 6, "test_unseen": 12}
    assert spec.n_trajectories == 40 and spec.n_frames == 500 and spec.save_every == 15
    assert spec.splits["train"][0].radii_m == (0.002, 0.0025, 0.003, 0.0035, 0.004, 0.0045, 0.005)
    assert spec.splits["valid"] == spec.splits["test"] == (RadiiGroup(6, spec.splits["train"][0].radii_m),)
    unseen = spec.splits["test_unseen"]
    assert [g.count for g in unseen] == [6, 6]
    assert unseen[0].radii_m == (0.00275, 0.00425)
    assert unseen[1].radii_m == (0.00225, 0.00325, 0.00375, 0.00475)
    assert spec.connectivity_radius == 0.2
    assert spec.physics == PhysicsConfig()
    assert spec.save_every * spec.physics.dt == pytest.approx(1.5e-3)


def test_paper3d_preset_places_its_spheres_in_the_cube():
    spec = preset("paper3d")
    assert spec.dim == 3 and spec.physics.box_half_size == 0.04 and spec.n_frames == 200
    assert spec.counts == {"train": 32, "valid": 4, "test": 6, "test_unseen": 12}
    assert spec.splits["train"][0].radii_m == paper_spec().splits["train"][0].radii_m
    assert spec.splits["test_unseen"] == paper_spec().splits["test_unseen"]
    assert spec.connectivity_radius == 0.5  # 4 x 5 mm / 40 mm
    # The densest list (unseen {2.75, 4.25} mm) still places: the packing rule works in this cube.
    items = [item for item in spec.items() if item[0] in ("train", "test_unseen")][31:34]
    keys = [trajectory_key(0, split, index) for split, index, _ in items]
    states = sample_initial_states(keys, [radii for _, _, radii in items], spec.physics, dim=3)
    half = spec.physics.box_half_size
    for state, (_, _, radii) in zip(states, items):
        x, a, v = np.asarray(state.position), np.asarray(state.radius), np.asarray(state.velocity)
        low, high = particle_count_range(state.start_height, max(radii), spec.physics, 3)
        assert x.shape == (len(a), 3) and low <= len(a) <= high and len(a) >= 179
        assert np.all(np.abs(x[:, :2]) <= half - a[:, None] + 1e-7) and np.all(x[:, 2] >= state.start_height + a - 1e-7)
        gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) - (a[:, None] + a[None]) + 2 * np.eye(len(a))
        assert gaps.min() >= -1e-7
        vs = spec.physics.settling_speed(min(radii), 3)
        assert np.all(v == v[0]) and np.all(np.abs(v[0, :2]) <= vs) and abs(v[0, 2]) <= vs / 4


def _largest_frame_acceleration(spec, physics, save_every, split, index, n_frames):
    """max over frames and spheres of |x_{t+1} - 2 x_t + x_{t-1}| / a (radii per frame^2) of one paper3d trajectory."""
    radii = {(s, i): r for s, i, r in spec.items()}[(split, index)]
    (state,) = sample_initial_states([trajectory_key(0, split, index)], [radii], physics, dim=3)
    x = np.asarray(
        simulate(state.position, state.velocity, state.radius, physics, n_frames=n_frames, save_every=save_every)
    )
    return float(np.max(np.abs(np.diff(x, n=2, axis=0)) / np.asarray(state.radius)[None, :, None]))


def test_paper3d_ground_truth_stays_stable_when_the_bed_forms():
    # Train trajectory 10 of seed 0 forms its bed by frame ~100. With the paper's Euler step (1e-4 s)
    # the bed blew up there (12 of the 32 training trajectories did: accelerations up to 70 radii
    # per frame^2, spheres crossing the cube in a frame), the data a 3-D model was trained on at
    # first. With the preset's step the largest acceleration of converged runs is ~1.5 radii per
    # frame^2 (physical: small spheres squeezed through the bed). Both runs cover 1.5 ms frames.
    spec = preset("paper3d")
    assert spec.save_every * spec.physics.dt == pytest.approx(1.5e-3)
    calm = _largest_frame_acceleration(spec, spec.physics, spec.save_every, "train", 10, 130)
    assert calm < 5.0
    paper_step = dataclasses.replace(spec.physics, dt=1e-4)
    assert _largest_frame_acceleration(spec, paper_step, 15, "train", 10, 130) > 10 * calm


def test_spec_replace():
    spec = paper_spec().replace(counts={"train": 3, "test_unseen": 5, "valid": 0}, n_frames=20)
    assert spec.counts == {"train": 3, "test": 6, "test_unseen": 5}
    assert [g.count for g in spec.splits["test_unseen"]] == [3, 2]
    spec = spec.replace(radii_m=[0.004, 0.006], unseen_radii_m=[[0.005]])
    assert spec.splits["train"] == (RadiiGroup(3, (0.004, 0.006)),)
    assert spec.splits["test"] == (RadiiGroup(6, (0.004, 0.006)),)
    assert spec.splits["test_unseen"] == (RadiiGroup(5, (0.005,)),)
    assert spec.connectivity_radius == 0.24
    with pytest.raises(ValueError, match="does not fit the box"):
        spec.replace(radii_m=[0.06])
    with pytest.raises(ValueError, match="at least one trajectory"):
        DatasetSpec(splits={"train": [(0, [0.004])]})
    with pytest.raises(ValueError, match="unknown split"):
        DatasetSpec(splits={"training": [(1, [0.004])]})


def test_trajectory_keys_are_independent():
    keys = {
        (seed, split, index): tuple(np.asarray(jax.random.key_data(trajectory_key(seed, split, index))))
        for seed in (0, 1)
        for split in ("train", "valid", "test", "test_unseen")
        for index in range(3)
    }
    assert len(set(keys.values())) == len(keys)
    # A split's trajectories do not depend on the counts of the others.
    small = tiny_spec().replace(counts={"train": 0, "valid": 0, "test_unseen": 0, "test": 1}).items()
    assert small == [("test", 0, tiny_spec().splits["test"][0].radii_m)]


def test_sample_initial_states_equals_sample_initial_state():
    spec = tiny_spec()
    items = spec.items()[:1] + spec.items()[-1:]
    keys = [trajectory_key(5, split, index) for split, index, _ in items]
    states = sample_initial_states(keys, [radii for _, _, radii in items], spec.physics)
    assert len({s.position.shape[0] for s in states}) > 1  # padding is exercised
    for key, (_, _, radii), state in zip(keys, items, states):
        expected = sample_initial_state(key, radii, spec.physics)
        np.testing.assert_array_equal(state.position, expected.position)
        np.testing.assert_array_equal(state.velocity, expected.velocity)
        np.testing.assert_array_equal(state.radius, expected.radius)
        assert state.start_height == expected.start_height
        assert state.position.dtype == np.float32


# ----------------------------------------------------------------------------- generated data


def test_generated_dataset_and_metadata(tiny):
    out, metadata = tiny
    assert listing(out) == ["metadata.json", "test.h5", "test_unseen.h5", "train.h5", "valid.h5"]
    read, splits = load_dataset(out)
    assert read == metadata
    assert read.trajectory_counts == {"train": 2, "valid": 1, "test": 1, "test_unseen": 1}
    assert read.sequence_length == FRAMES and read.save_every == 15 and read.dim == 2
    assert read.frame_dt == pytest.approx(1.5e-3)
    assert read.connectivity_radius == pytest.approx(4 * 0.010 / 0.1)
    assert read.physics_config == PhysicsConfig()
    assert read.has_initial_state and read.seed == 0 and read.preset == "tiny" and read.precision == "float32"
    assert read.radii["test_unseen"] == [
        {"count": 1, "radii_m": [0.0045, 0.0055, 0.007, 0.009], "radii_mm": [4.5, 5.5, 7.0, 9.0]}
    ]
    for split, trajectories in splits.items():
        assert [t.n_particles for t in trajectories] == read.particle_counts[split]
        allowed = read.radii[split][0]["radii_m"]
        for index, t in enumerate(trajectories):
            assert 30 <= t.n_particles <= 60
            assert t.position.dtype == np.float32 and t.position.shape == (FRAMES, t.n_particles, 2)
            assert t.initial_position.dtype == np.float64
            assert set(t.initial_radius.tolist()) <= set(allowed)
            np.testing.assert_array_equal(t.radius, (t.initial_radius / 0.1).astype(np.float32))
            np.testing.assert_allclose(t.position[0], t.initial_position / 0.1, atol=1e-7)
            assert t.attrs["split"] == split and t.attrs["index"] == index and t.attrs["seed"] == 0
            # Every disk stays inside the box.
            assert np.all(np.abs(t.position) <= 1 - t.radius[None, :, None] + 1e-4)


def test_positions_match_a_rerun_from_the_stored_initial_state(tiny):
    out, metadata = tiny
    _, splits = load_dataset(out, splits=["train", "test_unseen"])
    for trajectory in (splits["train"][0], splits["test_unseen"][0]):
        frames = simulate(
            trajectory.initial_position.astype(np.float32),
            trajectory.initial_velocity.astype(np.float32),
            trajectory.initial_radius.astype(np.float32),
            metadata.physics_config,
            n_frames=metadata.sequence_length,
            save_every=metadata.save_every,
        )
        np.testing.assert_allclose(np.asarray(frames) / metadata.box_half_size, trajectory.position, atol=1e-5)


def test_concurrent_batches_match_one_batch(tiny, tmp_path):
    out, _ = tiny
    generate_dataset(tiny_spec().replace(n_frames=FRAMES), tmp_path / "batched", seed=0, batch_size=3)
    _, one = load_dataset(out)
    _, batched = load_dataset(tmp_path / "batched")
    for split in one:
        for a, b in zip(one[split], batched[split]):
            np.testing.assert_array_equal(a.initial_position, b.initial_position)
            # Padding to another count may change float summation order only.
            np.testing.assert_allclose(a.position, b.position, atol=1e-5)


def _read_all(directory):
    metadata, splits = load_dataset(directory)
    return metadata, {
        s: [(t.position, t.initial_position, t.initial_velocity, t.radius) for t in ts] for s, ts in splits.items()
    }


def test_same_seed_same_dataset_and_different_seed_differs(tiny, tmp_path):
    out, _ = tiny
    again = generate_dataset(tiny_spec().replace(n_frames=FRAMES), tmp_path / "again", seed=0)
    first_meta, first = _read_all(out)
    second_meta, second = _read_all(tmp_path / "again")
    assert first_meta == second_meta == again
    for split in first:
        for a, b in zip(first[split], second[split]):
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
    other = generate_dataset(tiny_spec().replace(n_frames=FRAMES), tmp_path / "other", seed=1)
    assert other.seed == 1
    _, third = _read_all(tmp_path / "other")
    for split in first:
        for a, b in zip(first[split], third[split]):
            assert a[1].shape != b[1].shape or not np.array_equal(a[1], b[1])


# ----------------------------------------------------------------------------- failures and atomicity


def test_failure_while_writing_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", fake_simulate_batch())

    def failing(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(gen, "write_metadata", failing)
    with pytest.raises(OSError, match="disk full"):
        generate_dataset(tiny_spec(), tmp_path / "parent" / "out", seed=0)
    assert listing(tmp_path) == []


def test_overwrite_rules(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", fake_simulate_batch())
    out = tmp_path / "out"
    out.mkdir()
    first = generate_dataset(tiny_spec(), out, seed=0)  # an empty directory is fine
    before = (out / "train.h5").read_bytes()
    with pytest.raises(FileExistsError, match="exists and is not empty"):
        generate_dataset(tiny_spec(), out, seed=1)
    assert (out / "train.h5").read_bytes() == before
    second = generate_dataset(tiny_spec(), out, seed=1, overwrite=True)
    assert (first.seed, second.seed) == (0, 1)
    assert load_dataset(out)[0].seed == 1
    assert listing(tmp_path) == ["out"]
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "keep.txt").write_text("keep")
    with pytest.raises(FileExistsError, match="not a dispgns dataset"):
        generate_dataset(tiny_spec(), notes, seed=0, overwrite=True)
    assert listing(notes) == ["keep.txt"]


def test_batches_keep_trajectories_in_order(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(gen, "simulate_batch", fake_simulate_batch(calls))
    progress = []
    metadata = generate_dataset(
        tiny_spec(), tmp_path / "out", seed=0, batch_size=2, progress=lambda *event: progress.append(event)
    )
    assert sorted(shape[0] for shape in calls) == [1, 2, 2]
    assert progress[0] == ("place", 1, 5) and ("place", 5, 5) in progress
    assert progress[-1] == ("simulate", 60, 60)
    _, splits = load_dataset(tmp_path / "out")
    for trajectories in splits.values():
        for t in trajectories:
            np.testing.assert_allclose(t.position[5], t.initial_position / 0.1 + [5e-5, 0], atol=1e-6)
    assert metadata.particle_counts["train"] == [t.n_particles for t in splits["train"]]
    assert metadata.batch_size == 2 and load_dataset(tmp_path / "out")[0].batch_size == 2


def test_plan_batches():
    # The paper's counts: a few unseen-radii trajectories hold many more disks.
    counts = [150 + i for i in range(32)] + [187, 194, 197, 212, 228, 232, 240, 240]
    shuffled = counts[::-1]
    groups = gen.plan_batches(shuffled, 7500)
    assert sorted(i for g in groups for i in g) == list(range(40))
    assert 2 <= len(groups) <= 4
    for group in groups:  # contiguous in sorted order
        assert [shuffled[i] for i in group] == sorted(shuffled[i] for i in group)
    one_lane = gen.plan_batches(shuffled, 7500, lanes=1)
    assert [max(shuffled[i] for i in g) for g in one_lane] == [181, 240]

    def wall(plan, lanes):
        costs = [
            gen._SECONDS_PER_COMPILE + gen._SECONDS_PER_PAIR_STEP * 7500 * len(g) * max(shuffled[i] for i in g) ** 2
            for g in plan
        ]
        return gen._makespan(costs, lanes)

    assert wall(groups, 2) < wall(one_lane, 2) < wall([list(range(40))], 2)
    # Small counts: one group, one compilation.
    assert gen.plan_batches([44, 46, 38, 40, 40], 900) == [[2, 3, 4, 0, 1]]
    limited = gen.plan_batches(shuffled, 7500, batch_size=7)
    assert max(len(g) for g in limited) <= 7 and sorted(i for g in limited for i in g) == list(range(40))


def test_worker_threads_keep_float64(tmp_path, monkeypatch):
    fake = fake_simulate_batch()
    seen = []

    def recording(x0, *args, **kwargs):
        seen.append((jax.config.jax_enable_x64, x0.dtype))
        return fake(x0, *args, **kwargs)

    monkeypatch.setattr(gen, "simulate_batch", recording)
    with jax.enable_x64(True):
        metadata = generate_dataset(tiny_spec().replace(precision="float64"), tmp_path / "out", seed=0, batch_size=2)
    assert metadata.precision == "float64"
    assert seen == [(True, np.float64)] * 3


def test_a_failing_batch_stops_the_others(tmp_path, monkeypatch):
    fake = fake_simulate_batch()
    started = []

    def failing(x0, *args, **kwargs):
        started.append(x0.shape[0])
        if len(started) == 1:
            raise RuntimeError("out of memory")
        return fake(x0, *args, **kwargs)

    monkeypatch.setattr(gen, "simulate_batch", failing)
    with pytest.raises(RuntimeError, match="out of memory"):
        generate_dataset(tiny_spec(), tmp_path / "out", seed=0, batch_size=2)
    assert listing(tmp_path) == []


def test_impossible_packing_raises_and_leaves_nothing(tmp_path, monkeypatch):
    # 20 mm disks only, and the protocol's own count (without the cap below random jamming): more than the
    # region can hold.
    monkeypatch.setattr(dispgns.physics.initial, "RANDOM_PACKING_LIMIT", {})
    spec = DatasetSpec(splits={"train": [(1, [0.02])]}, n_frames=4)
    with pytest.raises(PlacementError, match="train trajectory 00000: could not place particle"):
        generate_dataset(spec, tmp_path / "out", seed=0)
    assert listing(tmp_path) == []


def test_float64_needs_x64(tmp_path):
    spec = tiny_spec().replace(precision="float64")
    with pytest.raises(ValueError, match="jax_enable_x64"):
        generate_dataset(spec, tmp_path / "out", seed=0)
    assert listing(tmp_path) == []
    with pytest.raises(ValueError, match="seed"):
        generate_dataset(tiny_spec(), tmp_path / "out", seed=-1)


# ----------------------------------------------------------------------------- command line


def test_cli_generate(tiny, tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["generate", "--preset", "tiny", "--out", str(out), "--seed", "0", "--frames", str(FRAMES)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed
    assert "5 trajectories (train 2, valid 1, test 1, test_unseen 1), 12 frames each" in printed
    _, ours = _read_all(out)
    _, reference = _read_all(tiny[0])
    for split in reference:
        for a, b in zip(reference[split], ours[split]):
            np.testing.assert_array_equal(a[0], b[0])


def test_cli_generate_options(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", fake_simulate_batch())
    out = tmp_path / "custom"
    code = main(
        [
            "generate",
            "--preset",
            "paper",
            "--out",
            str(out),
            "--frames",
            "9",
            "--train-count",
            "2",
            "--valid-count",
            "0",
            "--test-count",
            "1",
            "--unseen-count",
            "3",
            "--radii",
            "4,6,8,10",
            "--unseen-radii",
            "3,5",
            "--unseen-radii",
            "4,6,9",
        ]
    )
    assert code == 0
    metadata, splits = load_dataset(out)
    assert metadata.trajectory_counts == {"train": 2, "test": 1, "test_unseen": 3}
    assert metadata.sequence_length == 9 and metadata.preset == "paper"
    assert [g["radii_mm"] for g in metadata.radii["test_unseen"]] == [[3.0, 5.0], [4.0, 6.0, 9.0]]
    assert [g["count"] for g in metadata.radii["test_unseen"]] == [2, 1]
    assert metadata.radii["train"][0]["radii_mm"] == [4.0, 6.0, 8.0, 10.0]
    assert set(np.round(splits["test_unseen"][0].initial_radius * 1e3, 6)) <= {3.0, 5.0}
    assert set(np.round(splits["test_unseen"][2].initial_radius * 1e3, 6)) <= {4.0, 6.0, 9.0}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--radii", "90"], "does not fit the box"),
        (["--radii", "4,x"], "expected comma-separated radii in mm"),
        (["--radii", "0"], "expected radii > 0 mm"),
        (["--train-count", "-1"], "expected a count >= 0"),
        (["--frames", "1"], "expected at least 2 frames"),
    ],
)
def test_cli_generate_user_errors(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    code = main(["generate", "--preset", "tiny", "--out", str(out), "--frames", "4"] + extra)
    assert code == 2
    error = capsys.readouterr().err
    assert error.startswith("dispgns generate: error:") and message in error
    assert listing(tmp_path) == []


def test_cli_generate_refuses_occupied_or_unwritable_targets(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", fake_simulate_batch())
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "metadata.json").write_text("{}")
    assert main(["generate", "--preset", "tiny", "--out", str(occupied)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert (occupied / "metadata.json").read_text() == "{}"
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["generate", "--preset", "tiny", "--out", str(blocker / "out")]) != 0
    assert "cannot write to" in capsys.readouterr().err
    assert listing(tmp_path) == ["file", "occupied"]


def test_cli_generate_x64_is_scoped(tmp_path):
    out = tmp_path / "f64"
    code = main(
        [
            "generate",
            "--preset",
            "tiny",
            "--out",
            str(out),
            "--x64",
            "--frames",
            "3",
            "--train-count",
            "1",
            "--valid-count",
            "0",
            "--test-count",
            "0",
            "--unseen-count",
            "0",
        ]
    )
    assert code == 0
    assert not jax.config.jax_enable_x64
    metadata, splits = load_dataset(out)
    assert metadata.precision == "float64"
    (trajectory,) = splits["train"]
    # A float64 initial state is not float32-representable.
    assert not np.array_equal(trajectory.initial_position, trajectory.initial_position.astype(np.float32))
    with h5py.File(out / "train.h5") as file:
        assert file["00000/position"].dtype == np.float32
    assert math.isclose(metadata.frame_dt, 1.5e-3)


def test_dataset_error_is_a_value_error():
    assert issubclass(DatasetError, ValueError)


def test_cli_rejects_unusable_radii_before_writing(tmp_path, capsys):
    base = ["generate", "--preset", "tiny", "--frames", "2", "--valid-count", "0", "--test-count", "0"]
    out = tmp_path / "a"
    assert (
        main(base + ["--out", str(out), "--unseen-count", "1", "--unseen-radii", "3,4", "--unseen-radii", "5,6"]) == 2
    )
    assert "every group needs at least one" in capsys.readouterr().err
    assert main(base + ["--out", str(out), "--unseen-count", "0", "--radii", "0.001"]) == 2
    assert "particle indices can address" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- stability


def jumping_simulate_batch(jump=None, value=None, frame=7, particle=1):
    """fake_simulate_batch, with particle ``particle`` of every trajectory displaced along y from
    ``frame`` on by ``jump`` of the trajectory's smallest radius (or set to ``value``)."""
    smooth = fake_simulate_batch()

    def fake(x0, v0, radius, mask, config, **kwargs):
        xs = np.array(smooth(x0, v0, radius, mask, config, **kwargs))
        for row in range(xs.shape[0]):
            if value is not None:
                xs[row, frame, particle, 1] = value
            else:
                xs[row, frame:, particle, 1] += jump * np.min(radius[row][mask[row]])
        return xs

    return fake


def test_largest_frame_move_by_hand():
    position = np.zeros((5, 3, 2))
    position[:, 0, 0] = [0.0, 0.1, 0.2, 0.3, 0.4]  # 0.1 per frame
    position[3:, 1] = [0.3, 0.4]  # a 0.5 jump of the largest particle, from frame 2 to 3
    radius = np.array([0.5, 1.0, 0.25])
    move, frame, particle = gen.largest_frame_move(position, radius)
    assert (frame, particle) == (3, 1)
    assert move == pytest.approx(0.5 / 0.25)  # in units of the smallest radius, not the mover's
    position[4, 2, 0] = np.nan
    assert gen.largest_frame_move(position, radius) == (math.inf, 4, 2)
    assert gen.largest_frame_move(position[4:], radius) == (math.inf, 0, 2)  # one frame: still checked
    assert gen.largest_frame_move(position[:1], radius) == (0.0, 0, 0)
    assert gen.largest_frame_move(np.zeros((5, 0, 2)), np.zeros(0)) == (0.0, 0, 0)
    with pytest.raises(ValueError, match=r"\(T, N, D\)"):
        gen.largest_frame_move(position[0], radius)


def test_a_blown_up_trajectory_refuses_the_dataset_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", jumping_simulate_batch(jump=3.0))

    def written(*args, **kwargs):
        raise AssertionError("a split was written before every trajectory was checked")

    monkeypatch.setattr(gen, "write_split", written)
    with pytest.raises(gen.UnstableSimulationError) as error:
        generate_dataset(tiny_spec(), tmp_path / "out", seed=0)
    message = str(error.value)
    assert "train trajectory 00000: particle 1 moves 3 smallest radii between frames 6 and 7" in message
    assert "max_frame_move = 2" in message and "dt = 0.0001 s" in message
    assert listing(tmp_path) == []
    monkeypatch.setattr(gen, "simulate_batch", jumping_simulate_batch(value=np.nan))
    with pytest.raises(gen.UnstableSimulationError, match="particle 1's position is not finite at frame 7"):
        generate_dataset(tiny_spec(), tmp_path / "out", seed=0)
    assert listing(tmp_path) == []
    for bad in (0, -1.0, math.nan, True, "2"):
        with pytest.raises(ValueError, match="max_frame_move must be a number > 0"):
            generate_dataset(tiny_spec(), tmp_path / "out", seed=0, max_frame_move=bad)


def test_a_marginal_trajectory_is_kept_with_a_warning_and_its_move_recorded(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", jumping_simulate_batch(jump=1.5))
    with pytest.warns(gen.FrameMoveWarning, match="moves 1.5 smallest radii between frames 6 and 7") as caught:
        generate_dataset(tiny_spec(), tmp_path / "out", seed=0, max_frame_move=np.float32(2))
    assert all(warning.filename == __file__ for warning in caught)  # attributed to the caller
    assert len(caught) == 5  # one per trajectory
    _, splits = load_dataset(tmp_path / "out")
    for trajectory in (t for group in splits.values() for t in group):
        assert trajectory.attrs["largest_frame_move"] == pytest.approx(1.5, rel=1e-4)
    with pytest.raises(gen.UnstableSimulationError, match="more than max_frame_move = 1.2"):
        generate_dataset(tiny_spec(), tmp_path / "tight", seed=0, max_frame_move=1.2)
    assert listing(tmp_path) == ["out"]


def test_real_trajectories_record_a_healthy_largest_move(tiny):
    _, splits = load_dataset(tiny[0])
    for trajectory in (t for group in splits.values() for t in group):
        recorded = trajectory.attrs["largest_frame_move"]
        assert 0 < recorded < gen.WARN_FRAME_MOVE
        # The stored positions (float32, units of L) give the same move as the simulated ones (m).
        move, _, _ = gen.largest_frame_move(trajectory.position, trajectory.radius)
        assert move == pytest.approx(recorded, rel=1e-3)


def test_cli_generate_stability_bound(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(gen, "simulate_batch", jumping_simulate_batch(jump=1.5))
    out = tmp_path / "out"
    assert main(["generate", "--preset", "tiny", "--out", str(out), "--max-frame-move", "1.2"]) == 2
    error = capsys.readouterr().err
    assert "dispgns generate: error: train trajectory 00000: particle 1 moves 1.5 smallest radii" in error
    assert listing(tmp_path) == []
    assert main(["generate", "--preset", "tiny", "--out", str(out)]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 5 and "test_unseen trajectory 00000: particle 1 moves 1.5" in warnings[-1]
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "x"), "--max-frame-move", "-1"]) == 2
    assert "--max-frame-move -1.0: expected a number of radii > 0" in capsys.readouterr().err
