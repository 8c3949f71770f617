"""experiments/accuracy/handover.py: the exact physics continues a rollout from its frames, scored as evaluate does."""

import numpy as np
import pytest
from experiment_scripts import load_experiment

from dispgns.metrics import rollout_metrics


@pytest.fixture(scope="module")
def handover():
    return load_experiment("handover")


def test_the_physics_continues_the_frames_it_is_handed(handover, tiny_pair):
    metadata, trajectories = tiny_pair
    truth = [np.asarray(t.position) for t in trajectories]
    step, ahead = 20, 5
    hybrid = handover.handed_over(truth, trajectories, metadata, step)
    for got, want in zip(hybrid, truth, strict=True):
        assert got.shape == want.shape
        np.testing.assert_array_equal(got[:step], want[:step])
        np.testing.assert_allclose(got[step], want[step], atol=1e-6)
    # The velocity read from the last three frames carries the motion on: a few frames later the continuation is
    # far closer to the truth than one started at rest (a wrong sign, time step or frame order fails this).
    at_rest = [np.concatenate([t[: step + 1], np.repeat(t[step : step + 1], len(t) - step - 1, 0)]) for t in truth]
    moved = [np.abs(t[step + ahead] - t[step]).max() for t in truth]
    assert min(moved) > 1e-3
    for got, want, still in zip(hybrid, truth, at_rest, strict=True):
        error = np.abs(got[step + 1 : step + ahead + 1] - want[step + 1 : step + ahead + 1]).max()
        naive = np.abs(still[step + 1 : step + ahead + 1] - want[step + 1 : step + ahead + 1]).max()
        assert error < 0.02 * naive


def test_the_score_is_evaluates_full_rollout_mse(handover, tiny_pair):
    metadata, trajectories = tiny_pair
    truth = np.asarray(trajectories[0].position)
    rng = np.random.default_rng(0)
    predicted = truth.copy()
    predicted[6:] += rng.normal(0, 1e-3, predicted[6:].shape).astype(np.float32)
    expected = rollout_metrics(
        predicted, truth, np.asarray(trajectories[0].radius), box_half_size=metadata.length_scale, input_frames=6
    )["mse"]
    assert handover.mse(predicted, truth, 6) == pytest.approx(expected, rel=1e-5)


def test_a_hybrid_whose_physics_blew_up_is_left_out_and_counted(handover, tiny_pair):
    _, trajectories = tiny_pair
    truth = [np.asarray(t.position) for t in trajectories]
    blown = [t.copy() for t in truth]
    blown[1][40:, 3] += 0.5  # one particle jumps half the box in one frame, as in an Euler blow-up
    scores = handover.hybrid_mse(blown, truth, trajectories, 6)
    assert scores[0] == 0.0 and scores[1] is None
    assert handover.summary([2e-4, None, 4e-4]) == (pytest.approx(3e-4), 1)


def test_the_velocity_is_second_order(handover):
    # Exact on a quadratic path (a first-order difference is off by a dt / 2 there).
    dt, t = 1.5e-3, np.array([0.0, 1.5e-3, 3e-3])
    path = 0.02 + 0.3 * t[:, None] - 4.9 * t[:, None] ** 2
    np.testing.assert_allclose(handover.backward_velocity(path, dt), 0.3 - 9.8 * t[-1], rtol=1e-10)


def test_pooling_pairs_each_row_with_the_models_own_score_on_the_same_trajectories(handover):
    first = {
        "data": "a",
        "splits": ["valid"],
        "models": {"m": {"per_trajectory": {"model": [1.0, 2.0], "10": [0.5, None]}}},
    }
    second = {"data": "b", "splits": ["test"], "models": {"m": {"per_trajectory": {"model": [4.0], "10": [3.0]}}}}
    rows = handover.pool([first, second])["models"]["m"]
    assert rows["model"]["n"] == 3 and rows["model"]["mean"] == pytest.approx(7 / 3)
    ten = rows["10"]
    assert ten["n"] == 2 and ten["unstable"] == 1 and ten["mean"] == pytest.approx(1.75)
    # Paired over trajectories 1 (0.5 vs 1.0) and 3 (3.0 vs 4.0), not over the blown-up second one.
    assert ten["over_model"] == pytest.approx(3.5 / 5.0)
    assert ten["paired_difference"] == pytest.approx(-0.75)
    assert ten["paired_se"] == pytest.approx(np.std([-0.5, -1.0], ddof=1) / np.sqrt(2))
