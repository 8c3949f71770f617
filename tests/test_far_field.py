"""experiments/accuracy/far_field.py and error_places.py: the far field, the hybrid rollout, the error's places."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import NORM, experiment_fixture

from dispgns.model import ModelConfig, init_params
from dispgns.physics.forces import pair_force_over_distance, particle_mass
from dispgns.simulator import fit_capacity, rollout_scan

far_field = experiment_fixture("far_field")


error_places = experiment_fixture("error_places")


def test_the_far_field_is_the_pair_force_beyond_the_reach_as_a_per_frame_acceleration(far_field, tiny_pair):
    metadata, _ = tiny_pair
    config = ModelConfig(connectivity_radius=0.2, latent_size=8, hidden_size=8, message_passing_steps=1)
    scale, physics = metadata.length_scale, metadata.physics_config
    radius_m = jnp.array([0.002, 0.003, 0.004], jnp.float32)
    # Particles 0 and 1 are 0.1 L apart (inside the reach); particle 2 is 0.5 L from both (beyond it).
    x = jnp.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.5]], jnp.float32)
    got = np.asarray(far_field.far_field_fn(metadata, config)(x, radius_m, jnp.ones(3, bool)))
    mass = np.asarray(particle_mass(radius_m, physics, 2))
    expected = np.zeros((3, 2))
    for i, j in [(0, 2), (2, 0), (1, 2), (2, 1)]:
        d = (np.asarray(x[i]) - np.asarray(x[j])) * scale
        coeff = pair_force_over_distance(jnp.asarray((d * d).sum()), radius_m[i], radius_m[j], physics)
        expected[i] += float(coeff) * d / mass[i] * metadata.frame_dt**2 / scale
    assert np.abs(expected).max() > 0
    np.testing.assert_allclose(got, expected, rtol=2e-3, atol=1e-12)
    # The near pair (0, 1) adds nothing: particle 0's field comes from 2 alone, along the vertical.
    assert abs(got[0, 0]) < 1e-6 * abs(got[0, 1])
    # A padding particle far from all three neither adds to their field nor gets one.
    x4 = jnp.concatenate([x, jnp.array([[0.5, -0.5]], jnp.float32)])
    masked = np.asarray(
        far_field.far_field_fn(metadata, config)(x4, jnp.append(radius_m, 0.004), jnp.array([True] * 3 + [False]))
    )
    np.testing.assert_array_equal(masked[:3], got)
    np.testing.assert_array_equal(masked[3], 0.0)


def test_beta_is_one_for_a_model_blind_to_the_field_and_zero_for_errors_across_it(far_field):
    rng = np.random.default_rng(2)
    field = rng.normal(size=(50, 2))
    assert far_field.beta(-field, field) == pytest.approx(1.0)
    assert far_field.beta(-3 * field, field) == pytest.approx(3.0)
    across = np.stack([-field[:, 1], field[:, 0]], -1)  # each error at right angles to its field
    assert far_field.beta(across, field) == pytest.approx(0.0, abs=1e-12)


def test_the_hybrid_without_the_far_field_is_the_models_own_rollout(far_field, tiny_pair):
    metadata, trajectories = tiny_pair
    config = ModelConfig(connectivity_radius=0.4, latent_size=8, hidden_size=8, message_passing_steps=1)
    config = dataclasses.replace(config, keep_inside_box=True)
    params = init_params(jax.random.key(0), config, NORM)
    n_frames = 20
    short = [dataclasses.replace(t, position=np.asarray(t.position[:n_frames])) for t in trajectories]
    rollouts = far_field.hybrid_rollouts(params, config, metadata, short, [0.0, 1e3], group=2)
    for traj, got in zip(short, rollouts[0.0], strict=True):
        capacity = fit_capacity(traj.position, config, margin=0.5)
        want, overflow = rollout_scan(
            params, traj.position[:6], traj.radius, n_frames - 6, model_config=config, capacity=capacity
        )
        assert not np.asarray(overflow).any()
        np.testing.assert_array_equal(got[:6], traj.position[:6])
        np.testing.assert_allclose(got[6:], np.asarray(want), atol=1e-6)
    # A (hugely) scaled far field moves the rollout: the term is wired in.
    assert max(np.abs(a - b).max() for a, b in zip(rollouts[1e3], rollouts[0.0], strict=True)) > 1e-6


@pytest.mark.slow  # two compilations of the physics, ~30 s
def test_the_physics_cut_beyond_the_box_is_the_truth(far_field, tiny_pair):
    metadata, trajectories = tiny_pair
    trajectories = [dataclasses.replace(t, position=np.asarray(t.position[:20])) for t in trajectories[:1]]
    truth = [np.asarray(t.position) for t in trajectories]
    cut = far_field.truncated(metadata, trajectories, 10 * metadata.length_scale)  # every pair is nearer than that
    rows = far_field.scores(cut, truth, 6)
    assert max(rows["full"]) < 1e-9
    near = far_field.scores(far_field.truncated(metadata, trajectories, 0.2 * metadata.length_scale), truth, 6)
    assert max(near["full"]) > 100 * max(max(rows["full"]), 1e-14)


def test_the_scores_are_the_per_frame_mses_by_window(far_field):
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(506, 3, 2)).astype(np.float32)
    predicted = truth.copy()
    predicted[6:] += np.arange(500, dtype=np.float32)[:, None, None] * 1e-3  # frame k errs by k ms on both axes
    rows = far_field.scores([predicted], [truth], 6)
    curve = (np.arange(500) * 1e-3) ** 2
    assert rows["h1"][0] == pytest.approx(curve[0], abs=1e-12)
    assert rows["h100"][0] == pytest.approx(curve[99], rel=1e-5)
    assert rows["11-50"][0] == pytest.approx(curve[10:50].mean(), rel=1e-5)
    assert rows["401-end"][0] == pytest.approx(curve[400:].mean(), rel=1e-5)
    assert rows["full"][0] == pytest.approx(curve.mean(), rel=1e-5)


def test_wall_gaps_and_neighbour_gaps_by_hand(error_places):
    radius = np.array([0.1, 0.05])
    x = np.array([[[0.85, 0.0], [0.0, -0.9]]])
    gap = error_places.wall_gap(x, radius)
    np.testing.assert_allclose(gap[0, 0], [0.5, 9.0])  # (1 - 0.85 - 0.1) / 0.1; (1 - 0 - 0.1) / 0.1
    np.testing.assert_allclose(gap[0, 1], [19.0, 1.0])  # (1 - 0.05) / 0.05; (-0.9 + 1 - 0.05) / 0.05
    q = error_places.nearest_neighbour(x, radius)
    np.testing.assert_allclose(q, [[np.hypot(0.85, 0.9) / 0.15] * 2])


def test_the_classes_partition_the_error(error_places):
    rng = np.random.default_rng(1)
    error2 = rng.exponential(size=1000)
    values = rng.uniform(-1, 3, size=1000)
    masks = error_places.classes(values, error_places.WALL_GAPS, "gap")
    assert sum(m.sum() for m in masks.values()) == 1000
    shares = error_places.shares(error2, masks)
    assert sum(s["error"] for s in shares.values()) == pytest.approx(1.0)
    assert sum(s["particles"] for s in shares.values()) == pytest.approx(1.0)


def test_the_rollout_view_tells_the_floor_from_the_lid(error_places):
    from types import SimpleNamespace

    radius = np.array([0.05, 0.05, 0.05], np.float32)
    frame = np.array([[0.0, -0.95], [0.3, 0.95], [-0.3, 0.0]], np.float32)  # on the floor, at the lid, in the bulk
    truth = np.repeat(frame[None], 500, 0)
    predicted = truth.copy()
    predicted[6:, 0, 0] += 0.01  # only the particle on the floor errs
    report = error_places.rollout_report(
        [SimpleNamespace(position=predicted)], [SimpleNamespace(position=truth, radius=radius)], 6
    )
    for row in report.values():
        assert row["floor_contact"] == {"particles": pytest.approx(1 / 3), "error": pytest.approx(1.0)}
        assert row["lid_contact"] == {"particles": pytest.approx(1 / 3), "error": 0.0}
        assert row["side_wall_contact"]["particles"] == 0.0
        assert row["mse"] == pytest.approx(0.01**2 / 6, rel=1e-4)


def test_the_one_step_report_splits_the_error_by_window_and_class(error_places):
    data = {
        "error2": np.array([1.0, 3.0, 2.0, 2.0]),
        "frame": np.array([10, 10, 100, 250]),
        "wall_gap": np.array([0.0, 5.0, 5.0, 5.0]),
        "neighbour": np.array([1.05, 1.05, 1.3, 1.3]),
    }
    report = error_places.one_step_report(data)
    first = report["windows"]["frames 0-60"]
    assert first["share_of_all"] == pytest.approx(0.5)
    assert first["classes"]["wall gap -inf-0.05"] == {"particles": 0.5, "error": 0.25, "mean": 1.0}
    assert first["classes"]["neighbour 1-1.1"]["error"] == pytest.approx(1.0)
    assert first["worst_1_percent"] == pytest.approx(0.75)  # the worst of two entries holds 3 of 4
    assert report["windows"]["frames 60-200"]["share_of_all"] == pytest.approx(0.25)
    assert "frames 300-400" not in report["windows"]  # no checked frame there
