"""The ground-truth physics against trajectories of an independent float64 implementation."""

from pathlib import Path

import jax
import numpy as np
import pytest

from dispgns import PhysicsConfig, euler_integrator, simulate

DATA = Path(__file__).parent / "data"


def reference_config(data) -> PhysicsConfig:
    return PhysicsConfig(
        thickness=float(data["s"]),
        density=float(data["rho"]),
        fluid_density=float(data["rho_f"]),
        gravity=float(data["g"]),
        box_half_size=float(data["L"]),
        drag=float(data["k"]),
        lj_exponent=int(data["p"]),
        well_depth_coeff=float(data["U0_coeff"]),
        min_distance_coeff=float(data["r_m_coeff"]),
        restitution=float(data["gamma"]),
        dt=float(data["dt"]),
    )


def collision_counters(data, n_steps):
    """Cumulative wall crossings and corner events of the exact (capacity None) integrator."""
    config = reference_config(data)
    init_fn, step_fn = euler_integrator(config)
    state = init_fn(data["x0"], data["v0"], data["radius"])
    state = jax.jit(lambda s: jax.lax.fori_loop(0, n_steps, lambda _, s: step_fn(s), s))(state)
    return np.asarray(state.wall_hits), int(state.corner_events)


def test_reference_parameters_are_the_defaults():
    data = np.load(DATA / "wall_collisions.npz")
    assert reference_config(data) == PhysicsConfig()
    assert str(data["semantics"]) == "vectorized"


@pytest.mark.parametrize("name, n_steps", [("wall_collisions", 600), ("corner_collisions", 200)])
@pytest.mark.parametrize("capacity", ["auto", None])
def test_collisions_match_reference(name, n_steps, capacity):
    data = np.load(DATA / f"{name}.npz")
    with jax.enable_x64(True):
        positions, velocities = simulate(
            data["x0"],
            data["v0"],
            data["radius"],
            reference_config(data),
            n_frames=n_steps + 1,
            save_every=1,
            return_velocity=True,
            collision_capacity=capacity,
        )
        assert positions.dtype == np.float64
        np.testing.assert_allclose(np.asarray(positions), data["frames"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(velocities), data["velocities"], rtol=0, atol=1e-10)
        if capacity is None:
            hits, corners = collision_counters(data, n_steps)
            np.testing.assert_array_equal(hits, data["collision_counts"])
            assert corners == int(data["corner_events"])


def test_sedimentation_first_300_steps_match_reference():
    data = np.load(DATA / "sedimentation.npz")
    with jax.enable_x64(True):
        positions = simulate(data["x0"], data["v0"], data["radius"], reference_config(data), n_frames=21)
        np.testing.assert_allclose(np.asarray(positions), data["frames"][:21], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_sedimentation_full_run_matches_reference_statistics():
    data = np.load(DATA / "sedimentation.npz")
    with jax.enable_x64(True):
        positions = np.asarray(simulate(data["x0"], data["v0"], data["radius"], reference_config(data), n_frames=500))
        hits, corners = collision_counters(data, 7500)
    # Chaotic: early frames tightly, late frames through statistics.
    np.testing.assert_allclose(positions[:301], data["frames"][:301], rtol=0, atol=1e-9)
    assert np.max(np.abs(positions[:, :, 1].mean(axis=1) - data["mean_height"])) < 2e-3
    hist, _ = np.histogram(positions[-1, :, 1], bins=data["final_height_hist_edges"])
    assert np.abs(hist - data["final_height_hist"]).sum() <= 4
    np.testing.assert_array_equal(hits, data["collision_counts"])
    assert corners == int(data["corner_events"])


@pytest.mark.parametrize("name, n_steps", [("walls_3d", 600), ("corners_3d", 300)])
def test_3d_collisions_match_reference(name, n_steps):
    # Spheres: six walls, two- and three-wall events with the tie order and the clipped contact time.
    data = np.load(DATA / f"{name}.npz")
    assert int(data["dim"]) == 3
    with jax.enable_x64(True):
        positions, velocities = simulate(
            data["x0"],
            data["v0"],
            data["radius"],
            reference_config(data),
            n_frames=n_steps + 1,
            save_every=1,
            return_velocity=True,
        )
        assert positions.dtype == np.float64 and positions.shape == data["frames"].shape
        np.testing.assert_allclose(np.asarray(positions), data["frames"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(velocities), data["velocities"], rtol=0, atol=1e-10)
        hits, multi_wall = collision_counters(data, n_steps)
    np.testing.assert_array_equal(hits, data["collision_counts"])  # +x, -x, +y, -y, +z, -z
    assert multi_wall == int(data["two_wall_events"]) + int(data["three_wall_events"])


def test_3d_sedimentation_first_300_steps_match_reference():
    # tests/data/sedimentation_3d.npz keeps frames 0..20 (steps 0, 15, ..., 300) of the reference run.
    data = np.load(DATA / "sedimentation_3d.npz")
    with jax.enable_x64(True):
        positions = simulate(data["x0"], data["v0"], data["radius"], reference_config(data), n_frames=21)
        assert positions.shape == (21, 182, 3)
        np.testing.assert_allclose(np.asarray(positions), data["frames"], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_3d_sedimentation_full_run_matches_reference_statistics():
    data = np.load(DATA / "sedimentation_3d.npz")
    with jax.enable_x64(True):
        positions = np.asarray(simulate(data["x0"], data["v0"], data["radius"], reference_config(data), n_frames=500))
        hits, multi_wall = collision_counters(data, 7485)
    np.testing.assert_allclose(positions[:21], data["frames"], rtol=0, atol=1e-9)
    assert np.max(np.abs(positions[:, :, 2].mean(axis=1) - data["mean_height"])) < 2e-3
    hist, _ = np.histogram(positions[-1, :, 2], bins=data["final_height_hist_edges"])
    assert np.abs(hist - data["final_height_hist"]).sum() <= 4
    np.testing.assert_array_equal(hits, data["collision_counts"])
    assert multi_wall == 0


def test_sedimentation_float32_stays_close_early_and_statistically_late():
    data = np.load(DATA / "sedimentation.npz")
    positions = np.asarray(simulate(data["x0"], data["v0"], data["radius"], reference_config(data), n_frames=500))
    assert positions.dtype == np.float32
    np.testing.assert_allclose(positions[:21], data["frames"][:21], rtol=0, atol=2e-6)
    assert np.max(np.abs(positions[:, :, 1].mean(axis=1) - data["mean_height"])) < 2e-3
