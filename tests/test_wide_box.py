"""Rectangular boxes (one half-size per axis): the square box unchanged, symmetries, walls, the sampler."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import PhysicsConfig, sample_initial_state, simulate
from dispgns.physics import PlacementError, particle_count_range, place_particles

SQUARE = PhysicsConfig()
WIDE = PhysicsConfig(box_half_size=(0.3, 0.1))


@pytest.fixture(scope="module")
def square_state():
    return sample_initial_state(jax.random.PRNGKey(3), [8e-3, 10e-3], SQUARE)


@pytest.mark.parametrize("cutoff", [None, 0.03])
def test_equal_half_sizes_give_bit_identical_results_to_the_square_box(square_state, cutoff):
    square = dataclasses.replace(SQUARE, cutoff=cutoff)
    per_axis = dataclasses.replace(square, box_half_size=(0.1, 0.1))
    args = (square_state.position, square_state.velocity, square_state.radius)
    a = np.asarray(simulate(*args, square, n_frames=6))
    b = np.asarray(simulate(*args, per_axis, n_frames=6))
    np.testing.assert_array_equal(a, b)
    # The sampler too: a tuple of equal half-sizes places exactly the same disks.
    again = sample_initial_state(jax.random.PRNGKey(3), [8e-3, 10e-3], per_axis)
    np.testing.assert_array_equal(np.asarray(again.position), np.asarray(square_state.position))


def test_half_sizes_are_validated_and_read_from_text():
    assert PhysicsConfig.from_dict({"box_half_size": "0.4,0.1"}).box_half_size == (0.4, 0.1)
    assert PhysicsConfig.from_dict({"box_half_size": [0.4, 0.1]}).half_sizes(2) == (0.4, 0.1)
    assert PhysicsConfig.from_dict({"box_half_size": "0.2"}).half_sizes(3) == (0.2, 0.2, 0.2)
    with pytest.raises(ValueError, match="box_half_size"):
        PhysicsConfig(box_half_size=(0.4, -0.1))
    with pytest.raises(ValueError, match="one per axis"):
        WIDE.half_sizes(3)


@pytest.fixture(scope="module")
def wide_state():
    """~40 disks of 8-10 mm in a box three times wider than tall, settling with a cut-off."""
    return sample_initial_state(jax.random.PRNGKey(4), [8e-3, 10e-3], WIDE, n_particles=40)


def test_wide_box_mirror_symmetry_and_walls(wide_state):
    config = dataclasses.replace(WIDE, cutoff=0.03)
    x0, v0, a = (np.asarray(t) for t in (wide_state.position, wide_state.velocity, wide_state.radius))
    v0 = v0 + np.array([0.3, 0.0], np.float32)  # hit the side walls within the run
    flip = np.array([-1.0, 1.0], np.float32)
    x = np.asarray(simulate(x0, v0, a, config, n_frames=15))
    mirrored = np.asarray(simulate(x0 * flip, v0 * flip, a, config, n_frames=15))
    np.testing.assert_allclose(mirrored * flip, x, rtol=0, atol=2e-5)
    half = np.array(config.half_sizes(2))
    assert np.all(np.abs(x) <= (half[None, None, :] - a[None, :, None]) + 1e-6)
    assert np.max(x[:, :, 0]) > 0.3 - 0.011  # some disk reached the right wall, 0.2 m beyond the square box


def test_wide_box_translation_symmetry():
    """A cluster moved sideways (far from the side walls) does the same thing, shifted."""
    config = PhysicsConfig(box_half_size=(0.4, 0.1), cutoff=0.03)
    small = PhysicsConfig(box_half_size=(0.08, 0.1))
    state = sample_initial_state(jax.random.PRNGKey(6), [8e-3, 10e-3], small, n_particles=20)
    x0, v0, a = (np.asarray(t) for t in (state.position, state.velocity, state.radius))
    shift = np.array([0.25, 0.0], np.float32)
    left = np.asarray(simulate(x0 - shift, v0, a, config, n_frames=15))
    right = np.asarray(simulate(x0 + shift, v0, a, config, n_frames=15))
    np.testing.assert_allclose(right - 2 * shift, left, rtol=0, atol=2e-5)


def _all_pairs_placement(key, radius, start_height, half, candidates=64, max_rounds=64):
    """The placement protocol with an all-pairs overlap test, written out plainly."""
    n, dim = radius.shape[0], len(half)
    position, placed = np.zeros((n, dim), np.float32), np.zeros(n, bool)
    for i in range(n):
        low = np.array([-h for h in half[:-1]] + [start_height], np.float32) + radius[i]
        high = np.array(half, np.float32) - radius[i]
        for round_index in range(max_rounds):
            round_key = jax.random.fold_in(jax.random.fold_in(key, i), round_index)
            trial = np.asarray(jax.random.uniform(round_key, (candidates, dim), jnp.float32, low, high))
            gap = np.asarray(jnp.linalg.norm(trial[:, None, :] - position[None, :, :], axis=-1))
            ok = np.all((gap >= radius[i] + radius[None, :]) | ~placed[None, :], axis=1)
            if ok.any():
                position[i], placed[i] = trial[np.argmax(ok)], True
                break
    return position, placed


def test_cell_grid_placement_equals_an_all_pairs_placement():
    config = PhysicsConfig(box_half_size=(0.12, 0.05))
    key = jax.random.PRNGKey(7)
    radius = np.asarray(jax.random.choice(key, jnp.array([6e-3, 9e-3]), (60,)), np.float32)
    position, placed = place_particles(key, radius, -0.02, config)
    expected, expected_placed = _all_pairs_placement(key, radius, -0.02, config.half_sizes(2))
    np.testing.assert_array_equal(np.asarray(placed), expected_placed)
    np.testing.assert_array_equal(np.asarray(position)[expected_placed], expected[expected_placed])


@pytest.mark.parametrize("half", [(0.8, 0.1), (0.15, 0.1, 0.05)])
def test_sampler_fills_wide_boxes_without_overlap(half):
    dim = len(half)
    config = PhysicsConfig(box_half_size=half)
    radii = [5e-3, 7e-3] if dim == 2 else [6e-3, 8e-3]
    if dim == 3:
        # The paper's count at this size jams in 3-D random placement; fill half of it.
        low, _ = particle_count_range(-0.01, max(radii), config, dim)
        state = sample_initial_state(jax.random.PRNGKey(1), radii, config, dim=3, n_particles=low // 2)
    else:
        state = sample_initial_state(jax.random.PRNGKey(1), radii, config)
        low, high = particle_count_range(state.start_height, max(radii), config)
        assert low <= state.position.shape[0] <= high and -0.025 <= state.start_height <= 0
    x, a = np.asarray(state.position, np.float64), np.asarray(state.radius, np.float64)
    bound = np.array(half)[None] - a[:, None]
    assert np.all(np.abs(x) <= bound + 1e-7)
    assert np.all(x[:, -1] >= state.start_height + a - 1e-7)
    gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) - (a[:, None] + a[None]) + np.eye(len(a))
    assert gaps.min() >= -1e-7
    # It spreads over the whole width, not only the paper's square.
    assert np.ptp(x[:, 0]) > 1.5 * half[0]


def test_sampler_error_names_the_packing():
    with pytest.raises(PlacementError, match="too dense"):
        sample_initial_state(jax.random.PRNGKey(0), [9e-3], WIDE, n_particles=500, max_rounds=4)
    with pytest.raises(ValueError, match="smallest box half-size"):
        sample_initial_state(jax.random.PRNGKey(0), [0.06], PhysicsConfig(box_half_size=(0.4, 0.05)))


def _wide_metadata(**overrides):
    from dispgns.data.format import DatasetMetadata, radii_groups

    physics = PhysicsConfig(box_half_size=(0.4, 0.1), cutoff=0.02)
    values = dict(
        dim=2,
        sequence_length=3,
        frame_dt=15e-4,
        save_every=15,
        box_half_size=physics.box_half_size,
        length_scale=0.1,
        connectivity_radius=0.2,
        trajectory_counts={"test": 1},
        radii={"test": radii_groups([(1, [0.005])])},
        physics=physics.to_dict(),
    )
    values.update(overrides)
    return DatasetMetadata(**values)


def test_dataset_metadata_separates_the_length_scale_from_the_box(tmp_path):
    import json

    from dispgns.data.format import DatasetError, DatasetMetadata, Trajectory, load_dataset, write_metadata, write_split

    metadata = _wide_metadata()
    assert metadata.bounds == ((-4.0, 4.0), (-1.0, 1.0)) and metadata.length_scale == 0.1
    again = DatasetMetadata.from_dict(json.loads(json.dumps(metadata.to_dict())))
    assert again == metadata and again.physics_config.box_half_size == (0.4, 0.1)
    with pytest.raises(DatasetError, match="'bounds'"):
        _wide_metadata(bounds=((-1.0, 1.0), (-1.0, 1.0)))
    # A dataset written before the change (no length_scale; box_half_size = L) reads unchanged.
    old = _wide_metadata(box_half_size=0.1, physics=PhysicsConfig().to_dict()).to_dict()
    del old["length_scale"]
    read = DatasetMetadata.from_dict(old)
    assert read.length_scale == 0.1 and read.bounds == ((-1.0, 1.0), (-1.0, 1.0))
    # Positions beyond 1 are valid in the wide box, and only there.
    x0 = np.array([[0.35, -0.05], [-0.3, 0.02]])
    position = np.repeat((x0 / 0.1).astype(np.float32)[None], 3, axis=0)
    trajectory = Trajectory(
        position=position,
        radius=np.full(2, 0.05, np.float32),
        particle_type=np.zeros(2, np.int32),
        initial_position=x0,
        initial_velocity=np.zeros((2, 2)),
        initial_radius=np.full(2, 0.005),
    )
    with pytest.raises(DatasetError, match=r"expected inside the box \[-1, 1\]"):
        write_split(tmp_path / "bad.h5", [trajectory], box_half_size=0.1)
    write_split(tmp_path / "test.h5", [trajectory], box_half_size=0.1, bounds=metadata.bounds)
    write_metadata(tmp_path, dataclasses.replace(metadata, particle_counts={"test": [2]}))
    read_metadata, splits = load_dataset(tmp_path)
    np.testing.assert_array_equal(splits["test"][0].position, position)
    assert read_metadata.bounds == metadata.bounds


def test_wide_preset_generates_a_dataset_in_the_wide_box(tmp_path):
    from dispgns.data.format import load_dataset
    from dispgns.data.generate import DatasetSpec, RadiiGroup, generate_dataset, preset

    wide = preset("wide4")
    assert wide.bounds == ((-4.0, 4.0), (-1.0, 1.0)) and wide.physics.half_sizes(2) == (0.4, 0.1)
    assert preset("wide16").bounds == ((-16.0, 16.0), (-1.0, 1.0))
    spec = DatasetSpec(
        splits={"test": (RadiiGroup(1, (8e-3, 10e-3)),)},
        n_frames=4,
        physics=PhysicsConfig(box_half_size=(0.25, 0.05), cutoff=0.02),
        length_scale=0.05,
    )
    metadata = generate_dataset(spec, tmp_path / "wide", seed=0)
    assert metadata.bounds == ((-5.0, 5.0), (-1.0, 1.0)) and metadata.length_scale == 0.05
    _, splits = load_dataset(tmp_path / "wide")
    (trajectory,) = splits["test"]
    np.testing.assert_allclose(trajectory.position[0], trajectory.initial_position / 0.05, atol=1e-5)
    assert np.abs(trajectory.position[..., 0]).max() > 2.0  # the disks fill the whole width


def test_wall_violations_use_the_wide_box():
    from dispgns.metrics import wall_violations

    positions = np.array([[[3.5, 0.0], [-3.952, 0.5], [4.2, 0.0]]], np.float32)
    radius = np.full(3, 0.05, np.float32)
    wide = ((-4.0, 4.0), (-1.0, 1.0))
    assert int(wall_violations(positions, radius, bounds=wide)[0]) == 1  # only the disk beyond x = 4
    assert int(wall_violations(positions, radius)[0]) == 3  # in the paper's box all three are outside


WIDE_MODEL_BOUNDS = ((-4.0, 4.0), (-1.0, 1.0))


def _group(key, centre_x, n=10):
    """``n`` disks (radius 0.03) on a jittered grid around ``centre_x``, moving a little: (C, n, 2) frames."""
    from dispgns import ModelConfig

    c = ModelConfig().input_sequence_length
    grid = np.stack(np.meshgrid(np.arange(5), np.arange(n // 5)), -1).reshape(-1, 2) * 0.1
    jitter = np.asarray(jax.random.uniform(key, (n, 2), minval=-0.02, maxval=0.02))
    start = grid - grid.mean(0) + np.array([centre_x, -0.5]) + jitter
    drift = np.asarray(jax.random.normal(jax.random.fold_in(key, 1), (n, 2))) * 2e-3
    return (start[None] + np.arange(c)[:, None, None] * drift[None]).astype(np.float32)


def test_learned_simulator_is_local_in_a_wide_box():
    """Two groups farther apart than the connectivity radius (plus what 8 steps can close) roll out alone."""
    from dispgns import ModelConfig, init_params, rollout

    config = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, bounds=WIDE_MODEL_BOUNDS)
    params = init_params(jax.random.PRNGKey(0), config)
    left, right = _group(jax.random.PRNGKey(1), -2.5), _group(jax.random.PRNGKey(2), 2.5)
    radius = np.full(10, 0.03, np.float32)
    both = rollout(params, np.concatenate([left, right], 1), np.tile(radius, 2), 8, model_config=config)
    alone_left = rollout(params, left, radius, 8, model_config=config)
    alone_right = rollout(params, right, radius, 8, model_config=config)
    both = np.asarray(both)
    assert both[:, 10:, 0].min() - both[:, :10, 0].max() > config.connectivity_radius
    np.testing.assert_allclose(both[:, :10], np.asarray(alone_left), rtol=0, atol=1e-6)
    np.testing.assert_allclose(both[:, 10:], np.asarray(alone_right), rtol=0, atol=1e-6)


def test_one_learned_step_at_ten_thousand_particles_needs_no_quadratic_memory():
    """The compiled step at N = 10^4 needs under 128 MB of scratch (one N^2 float32 array alone is 381 MB)."""
    from dispgns import ModelConfig, init_params, predict_step
    from dispgns.graph import fit_capacity

    n, c = 10_000, ModelConfig().input_sequence_length
    bounds = ((-50.0, 50.0), (-1.0, 1.0))
    config = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, bounds=bounds)
    params = init_params(jax.random.PRNGKey(0), config)
    # A settled-bed-like layer: 10^4 disks on a jittered grid 100 L wide.
    columns = np.arange(n) % 1000
    rows = np.arange(n) // 1000
    x = np.stack([-49.9 + 0.1 * columns, -0.95 + 0.1 * rows], -1).astype(np.float32)
    frames = np.repeat(x[None], c, axis=0)
    radius = np.full(n, 0.03, np.float32)
    capacity = fit_capacity(x, connectivity_radius=config.connectivity_radius, bounds=bounds)
    step = jax.jit(lambda p, f, r: predict_step(p, f, r, model_config=config, capacity=capacity).position)
    compiled = step.lower(params, frames, radius).compile()
    memory = compiled.memory_analysis()
    scratch = memory.temp_size_in_bytes + memory.output_size_in_bytes
    assert scratch < 128 * 2**20, scratch / 2**20  # 55 MB measured (2026-12-02)
    out = np.asarray(compiled(params, frames, radius))
    assert np.all(np.isfinite(out))


def test_render_draws_the_dataset_box(tmp_path):
    """dispgns render draws a wide dataset's own box (bounds from metadata.json), panels stacked to its aspect."""
    import json

    from PIL import Image

    from dispgns.cli import main
    from dispgns.data.format import Trajectory, write_metadata, write_split
    from dispgns.render import WIDE_WIDTH_IN

    # Two disks falling near the side walls of the wide4 box, far beyond the paper's square.
    x0 = np.array([[-0.37, 0.05], [0.36, -0.02]])
    fall = np.linspace(0.0, 0.01, 8)[:, None, None] * np.array([0.0, -1.0])
    position = ((x0[None] + fall) / 0.1).astype(np.float32)
    trajectory = Trajectory(
        position=position,
        radius=np.full(2, 0.05, np.float32),
        particle_type=np.zeros(2, np.int32),
        initial_position=x0,
        initial_velocity=np.zeros((2, 2)),
        initial_radius=np.full(2, 0.005),
    )
    metadata = _wide_metadata(sequence_length=8)
    data = tmp_path / "wide"
    data.mkdir()
    write_split(data / "test.h5", [trajectory], box_half_size=0.1, bounds=metadata.bounds)
    write_metadata(data, dataclasses.replace(metadata, particle_counts={"test": [2]}))
    # A "prediction" that is the truth: what is drawn, not the model, is under test here.
    predicted = tmp_path / "test_pred.h5"
    write_split(predicted, [Trajectory(position=position, radius=trajectory.radius)], predicted=True)
    out = tmp_path / "pictures"
    args = ["render", "--data", str(data), "--split", "test", "--predictions", str(predicted), "--out", str(out)]
    assert main([*args, "--no-mp4", "--stride", "1"]) == 0
    assert json.loads((out / "render.json").read_text())["bounds"] == [[-4.0, 4.0], [-1.0, 1.0]]
    aspect = 8.08 / 2.08  # the box and its margins
    width = min(WIDE_WIDTH_IN, 2.4 * aspect)
    with Image.open(out / "rollout_grid.png") as png:  # 5 frames x (truth, prediction) in one column, dpi 100
        assert png.size == (round((width + 1.2) * 100), round((10 * (width / aspect + 0.35) + 0.2) * 100))
    width = min(WIDE_WIDTH_IN, 3.0 * aspect)
    with Image.open(out / "rollout.gif") as gif:  # truth above prediction, dpi 80
        assert gif.n_frames == 8
        assert gif.size == (int((width + 1.2) * 80), int((2 * (width / aspect + 0.35) + 0.45) * 80))


def test_demo_refuses_a_wide_preset_in_three_dimensions(tmp_path, capsys):
    from dispgns.cli import main

    assert main(["demo", "--preset", "wide16", "--dim", "3", "--out", str(tmp_path / "demo")]) == 2
    assert "--preset wide16: a 2-D container" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


@pytest.mark.slow
def test_demo_in_the_wide4_container(tmp_path, capsys):
    """dispgns demo --preset wide4: ~700 disks in the 0.8 m box, the shipped model given that box, drawn to scale."""
    import json

    from PIL import Image

    from dispgns.cli import main
    from dispgns.render import WIDE_WIDTH_IN

    out = tmp_path / "demo"
    argv = ["demo", "--preset", "wide4", "--frames", "12", "--no-chaos", "--no-mp4", "--stride", "3", "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "box 0.8x0.2 m (wide4)" in printed and "rollout MSE" in printed
    report = json.loads((out / "metrics.json").read_text())
    assert report["preset"] == "wide4" and report["box_half_sizes_m"] == [0.4, 0.1]
    assert report["n_particles"] > 400  # the paper's ~150-225 disks per unit of width, 4 widths
    metrics = report["metrics"]
    assert metrics["finite"] and metrics["wall_violations_total"] == 0
    # Far below constant velocity: with the paper's [-1, 1]^2 every disk beyond |x| = 1 would be pinned.
    assert metrics["mse"] < 0.2 * metrics["constant_velocity_mse"]
    aspect = 8.08 / 2.08  # the box and its margins
    width = min(WIDE_WIDTH_IN, 2.4 * aspect)
    with Image.open(out / "rollout_grid.png") as png:  # 10 stacked panels, not a 5 x 2 grid of squares
        assert png.size == (round((width + 1.2) * 100), round((10 * (width / aspect + 0.35) + 0.2) * 100))
    width = min(WIDE_WIDTH_IN, 3.0 * aspect)
    with Image.open(out / "rollout.gif") as gif:
        assert gif.n_frames == 4
        assert gif.size == (int((width + 1.2) * 80), int((2 * (width / aspect + 0.35) + 0.45) * 80))
