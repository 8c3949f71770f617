"""Whole-split evaluation: batched rollouts equal single ones, the chaos floor re-runs the physics exactly."""

import jax
import numpy as np
import pytest

from dispgns.data import load_dataset
from dispgns.evaluation import (
    chaos_floor_rollout,
    chaos_floor_trajectories,
    evaluate_trajectories,
    predict_trajectories,
)
from dispgns.model import init_params
from dispgns.simulator import rollout

FRAMES = 20


@pytest.fixture(scope="module")
def split(tiny_dataset):
    metadata, splits = load_dataset(tiny_dataset, ["train", "test_unseen"])
    return metadata, splits["train"] + splits["test_unseen"]


@pytest.fixture(scope="module")
def params(tiny_model_config):
    norm = {
        "velocity_mean": np.zeros(2),
        "velocity_std": np.full(2, 0.05),
        "acceleration_mean": np.zeros(2),
        "acceleration_std": np.full(2, 0.002),
    }
    return init_params(jax.random.key(0), tiny_model_config, norm)


def test_batched_predictions_equal_single_rollouts(split, params, tiny_model_config):
    _, trajectories = split
    assert len({t.n_particles for t in trajectories}) > 1  # different sizes share one padded batch
    steps = []
    batched = predict_trajectories(
        params, trajectories, model_config=tiny_model_config, n_frames=FRAMES, batch_size=2, progress=steps.append
    )
    assert sum(steps) == len(trajectories) * (FRAMES - 6)
    for traj, predicted in zip(trajectories, batched):
        single = rollout(params, traj.position[:6], traj.radius, FRAMES - 6, model_config=tiny_model_config)
        assert predicted.shape == (FRAMES, traj.n_particles, 2)
        np.testing.assert_array_equal(predicted[:6], traj.position[:6])
        np.testing.assert_allclose(predicted[6:], np.asarray(single), rtol=0, atol=2e-6)


def test_chaos_floor_batch_re_runs_the_physics(split):
    metadata, trajectories = split
    config = metadata.physics_config
    # Without perturbation the re-run is the stored truth (same precision, same program up to padding).
    exact = chaos_floor_trajectories(
        trajectories, config, n_frames=FRAMES, save_every=metadata.save_every, perturbation=0.0
    )
    for traj, rerun in zip(trajectories, exact):
        np.testing.assert_allclose(rerun.astype(np.float32), traj.position[:FRAMES], rtol=0, atol=2e-6)
    # With it, each trajectory equals its own chaos_floor_rollout with the same key.
    floors = chaos_floor_trajectories(trajectories, config, n_frames=FRAMES, save_every=metadata.save_every, seed=4)
    for k, (traj, floor) in enumerate(zip(trajectories, floors)):
        single = chaos_floor_rollout(
            traj.initial_position,
            traj.initial_velocity,
            traj.initial_radius,
            config,
            key=jax.random.fold_in(jax.random.PRNGKey(4), k),
            n_frames=FRAMES,
            x64=False,
        )
        np.testing.assert_allclose(floor, single, rtol=0, atol=2e-6)
        assert 0 < np.abs(floor[0] - traj.position[0]).max() < 1e-5


def test_evaluate_trajectories_report(split, params, tiny_model_config):
    metadata, trajectories = split
    result = evaluate_trajectories(
        params,
        trajectories[:2],
        model_config=tiny_model_config,
        box_half_size=metadata.box_half_size,
        frame_dt=metadata.frame_dt,
        physics_config=metadata.physics_config,
        n_frames=FRAMES,
    )
    assert result["chaos_floor"] and len(result["metrics"]) == 2
    assert result["summary"]["n_trajectories"] == 2
    m = result["metrics"][0]
    assert len(m["per_frame_mse"]) == FRAMES - 6 and m["chaos_floor_mse"] < m["constant_velocity_mse"]
    expected = np.mean([r["mse"] for r in result["metrics"]])
    assert np.isclose(result["summary"]["mse"]["mean"], expected)
