"""experiments/accuracy/band_projection.py: the pair force by band of distance, the joint fit, the correction."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import NORM, experiment_fixture

from dispgns.model import ModelConfig, init_params
from dispgns.physics.forces import interaction_force, particle_mass
from dispgns.simulator import fit_capacity, predict_step

CONFIG = ModelConfig(connectivity_radius=0.2, latent_size=8, hidden_size=8, message_passing_steps=1)


bands = experiment_fixture("band_projection", "bands")


far_field = experiment_fixture("far_field")


def test_the_bands_partition_the_all_pairs_force_and_the_last_is_the_far_field(bands, far_field, tiny_pair):
    metadata, trajectories = tiny_pair
    x = jnp.asarray(trajectories[0].position[40], jnp.float32)
    radius_m = jnp.asarray(trajectories[0].initial_radius, jnp.float32)
    n = x.shape[0]
    mask = jnp.ones(n, bool)
    # The tiny preset's disks are large (up to 10 mm): a reach of 0.4 L puts pairs in the band beyond 2.5 sigma.
    config = dataclasses.replace(CONFIG, connectivity_radius=0.4)
    got = np.asarray(bands.band_fields_fn(metadata, config)(x, radius_m, mask))
    assert got.shape == (len(bands.EDGES) + 2, n, 2)
    scale, physics = metadata.length_scale, metadata.physics_config
    xm = x * scale
    exact = interaction_force(xm, jnp.arange(n), xm, radius_m, mask, dataclasses.replace(physics, cutoff=None))
    exact = np.asarray(exact / particle_mass(radius_m, physics, 2)[:, None] * (metadata.frame_dt**2 / scale))
    np.testing.assert_allclose(got.sum(0), exact, rtol=1e-4, atol=1e-5 * np.abs(exact).max())
    far = np.asarray(far_field.far_field_fn(metadata, config)(x, radius_m, mask))
    np.testing.assert_allclose(got[-1], far, rtol=1e-3, atol=1e-3 * np.abs(far).max())
    assert all(np.abs(band).max() > 0 for band in got)  # pairs in every band


def test_a_pair_lands_in_the_band_of_its_distance_over_its_radii(bands, tiny_pair):
    metadata, _ = tiny_pair
    radius_m = jnp.array([0.003, 0.002, 0.004], jnp.float32)
    sigma = 0.005 / metadata.length_scale  # a_0 + a_1, normalised
    # Particles 0 and 1 at 1.3 sigma (the well); particle 2 beyond the graph's 0.2 L.
    x = jnp.array([[0.0, 0.0], [1.3 * sigma, 0.0], [0.0, 0.6]], jnp.float32)
    got = np.asarray(bands.band_fields_fn(metadata, CONFIG)(x, radius_m, jnp.ones(3, bool)))
    mass = np.asarray(particle_mass(radius_m, metadata.physics_config, 2))
    # Particle 0 feels 1 across (the well) and 2 straight above (beyond the graph).
    assert got[1, 0, 0] > 0  # attractive in the well: pulled towards 1
    np.testing.assert_array_equal(got[[0, 2, 3, 4], 0, 0], 0.0)
    np.testing.assert_array_equal(got[:-1, 0, 1], 0.0)
    assert got[-1, 0, 1] > 0  # pulled up towards 2 by the far band alone
    np.testing.assert_allclose(got[1, 0, 0] * mass[0], -got[1, 1, 0] * mass[1], rtol=1e-5)  # action = reaction
    np.testing.assert_array_equal(got[:-1, 2], 0.0)  # particle 2 feels only the far band


def test_the_joint_fit_recovers_known_betas_and_what_they_explain(bands):
    rng = np.random.default_rng(3)
    fields = rng.normal(size=(3, 400, 2))
    fields[1] += 0.8 * fields[0]  # correlated bands: single-band projections are biased, the joint fit is not
    true_beta = np.array([0.5, -1.0, 2.0])
    along = -np.tensordot(true_beta, fields, 1)
    noise = rng.normal(size=along.shape)
    flat = fields.reshape(3, -1)
    noise -= (np.linalg.lstsq(flat.T, noise.reshape(-1), rcond=None)[0] @ flat).reshape(noise.shape)  # orthogonal
    got = bands.fit(along + noise, fields)
    np.testing.assert_allclose(got["beta"], true_beta, rtol=1e-9)
    share = (along * along).sum() / ((along + noise) ** 2).sum()
    assert got["explained"] == pytest.approx(share, rel=1e-9)
    assert abs(got["single_band_beta"][1] - true_beta[1]) > 0.1
    assert bands.fit(-fields[2], fields)["explained"] == pytest.approx(1.0)
    # A band empty in a window (no contacts yet) gets beta 0 and leaves the others' fit as it was.
    empty = np.concatenate([fields, np.zeros((1,) + fields.shape[1:])])
    got = bands.fit(along + noise, empty)
    np.testing.assert_allclose(got["beta"], np.r_[true_beta, 0.0], rtol=1e-9, atol=1e-12)
    assert got["single_band_beta"][-1] == 0.0


def test_windows_pool_the_trajectories_and_report_each_ones_spread(bands):
    rng = np.random.default_rng(4)
    per = []
    for k in range(3):
        frames = np.arange(5, 250, 5)
        fields = rng.normal(size=(2, frames.size, 7, 2))
        beta = np.array([1.0 + 0.1 * k, -0.5])[:, None, None, None] * (1 + (frames >= 100))[None, :, None, None]
        # (both double from frame 100)
        per.append((frames, -(beta * fields).sum(0), fields))
    got = bands.windows_fit(per)
    assert list(got) == ["0-100", "100-200", "200-300"]
    np.testing.assert_allclose(got["0-100"]["beta"][1], -0.5, rtol=0.01)  # pooled over unequal band-0 betas
    np.testing.assert_allclose(got["200-300"]["beta"][1], -1.0, rtol=0.01)
    assert 1.0 < got["0-100"]["beta"][0] < 1.2
    np.testing.assert_allclose(got["0-100"]["beta_standard_error"][0], 0.1 / np.sqrt(3), rtol=1e-6)
    # A trajectory whose second band is empty (no pairs there yet) adds no beta of 0 to that band's spread.
    frames, error, fields = per[0]
    empty = fields.copy()
    empty[1] = 0.0
    with_empty = bands.windows_fit(per + [(frames, -(1.05 * empty[0]), empty)])
    np.testing.assert_allclose(with_empty["0-100"]["beta_standard_error"][1], 0.0, atol=1e-12)
    assert with_empty["0-100"]["beta_standard_error"][0] > 0


def test_the_correction_at_zero_betas_is_the_models_own_rollout(bands, far_field, tiny_pair):
    metadata, trajectories = tiny_pair
    config = dataclasses.replace(CONFIG, connectivity_radius=0.4)
    params = init_params(jax.random.key(0), config, NORM)
    short = [dataclasses.replace(t, position=np.asarray(t.position[:16])) for t in trajectories]
    fields = bands.band_fields_fn(metadata, config)
    k = len(bands.EDGES) + 2
    for beta, gain, moved in [(jnp.zeros(k), 0.0, False), (jnp.full(k, 1e3), 0.0, True), (jnp.zeros(k), 0.5, True)]:
        got = far_field.hybrid_rollouts(
            params, config, metadata, short, [0.0, 1.0], 2, gain=gain,
            field=lambda x, rm, m, b=beta: jnp.tensordot(b, fields(x, rm, m), 1),
        )  # fmt: skip
        gap = max(np.abs(a - b).max() for a, b in zip(got[1.0], got[0.0], strict=True))
        assert (gap > 1e-6) == moved, (beta[0], gain)
        if not moved:
            for a, b in zip(got[1.0], got[0.0], strict=True):
                np.testing.assert_array_equal(a, b)


def test_the_own_regressor_is_the_models_predicted_acceleration(bands, tiny_pair):
    metadata, trajectories = tiny_pair
    config = dataclasses.replace(CONFIG, connectivity_radius=0.4)
    params = init_params(jax.random.key(1), config, NORM)
    short = [dataclasses.replace(trajectories[0], position=np.asarray(trajectories[0].position[:30]))]
    [(frames, error, fields)] = bands.band_errors(params, config, metadata, short, 7, 30, bands.EDGES, own=True)
    assert fields.shape[0] == len(bands.EDGES) + 3
    x = short[0].position
    capacity = fit_capacity(x, config, margin=0.1)
    for j, t in enumerate(frames):
        step = predict_step(params, x[t - 5 : t + 1], short[0].radius, model_config=config, capacity=capacity)
        np.testing.assert_allclose(fields[-1, j], np.asarray(step.acceleration), rtol=1e-4, atol=1e-8)
        np.testing.assert_allclose(error[j], np.asarray(step.position) - x[t + 1], atol=1e-6)


def test_the_correction_terms_by_option(bands):
    fit = {"windows": {"all": {"beta": [0.1, 0.2, 2.5, 0.3], "single_band_beta": [0.0, 0.0, 2.4, 0.05]}}}
    beta, gain = bands.correction_terms(fit, 3, own=True)
    np.testing.assert_allclose(beta, [0.1, 0.2, 2.5], rtol=1e-6)
    assert gain == pytest.approx(0.3)
    beta, gain = bands.correction_terms(fit, 3, own=True, without_far=True)
    np.testing.assert_allclose(beta, [0.1, 0.2, 0.0], rtol=1e-6)
    assert gain == pytest.approx(0.3)
    beta, gain = bands.correction_terms(fit, 3, own=True, gain_only=True)
    np.testing.assert_array_equal(beta, np.zeros(3))
    assert gain == pytest.approx(0.05)
    without_own = {"windows": {"all": {"beta": [0.1, 0.2, 2.5], "single_band_beta": [0.0, 0.0, 2.4]}}}
    beta, gain = bands.correction_terms(without_own, 3, own=False)
    np.testing.assert_allclose(beta, [0.1, 0.2, 2.5], rtol=1e-6)
    assert gain == 0.0
