"""experiments/accuracy/far_probe.py: the shell descriptors by hand, padding, and the least-squares head."""

import jax.numpy as jnp
import numpy as np
import pytest
from experiment_scripts import experiment_fixture

probe = experiment_fixture("far_probe", "probe")


def test_the_shell_descriptors_by_hand(probe):
    centres, width, a_ref = (0.1, 0.3), 0.05, 0.02
    features = probe.shell_features_fn(centres, width, sigma_powers=(0, 2), self_powers=(0, -1), a_ref=a_ref)
    x = jnp.array([[0.0, 0.0], [0.3, 0.0], [0.0, -0.1]], jnp.float32)
    radius = jnp.array([0.02, 0.04, 0.01], jnp.float32)
    got = np.asarray(features(x, radius, jnp.ones(3, bool)))
    assert got.shape == (3, 2 * 2 * 2, 2)  # (N, shells x sigma powers x self powers, D)

    def phi(r):
        return np.exp(-0.5 * ((r - np.asarray(centres)) / width) ** 2)

    want = np.zeros((3, 8, 2))
    xs, a = np.asarray(x, np.float64), np.asarray(radius, np.float64)
    for i in range(3):
        for j in range(3):
            if i == j:
                continue
            d = xs[j] - xs[i]
            r = np.linalg.norm(d)
            sigma = (a[i] + a[j]) / (2 * a_ref)
            for qi, q in enumerate((0, 2)):
                for pi, p in enumerate((0, -1)):
                    for k in range(2):
                        want[i, k + 2 * (pi + 2 * qi)] += (a[i] / a_ref) ** p * sigma**q * phi(r)[k] * d / r
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    # Particle 1 is 0.3 right of particle 0: its shell at 0.3 holds it with weight 1 along the first axis; particle 2,
    # straight below, adds nothing along that axis.
    assert got[0, 1, 0] == pytest.approx(1.0, rel=1e-6)


def test_padding_neither_has_nor_adds_descriptors(probe):
    features = probe.shell_features_fn()
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.uniform(-0.5, 0.5, (6, 2)), jnp.float32)
    radius = jnp.full(6, 0.03, jnp.float32)
    real = np.asarray(features(x, radius, jnp.ones(6, bool)))
    x_pad = jnp.concatenate([x, jnp.array([[0.01, 0.02], [0.2, 0.2]], jnp.float32)])
    mask = jnp.array([True] * 6 + [False] * 2)
    padded = np.asarray(features(x_pad, jnp.append(radius, jnp.array([0.03, 0.05], jnp.float32)), mask))
    np.testing.assert_allclose(padded[:6], real, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(padded[6:], 0.0)


def test_the_head_is_the_least_squares_fit(probe):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2000, 5)) * np.array([1e-3, 1.0, 10.0, 1e2, 1e-1])  # badly scaled columns
    c = rng.normal(size=5)
    y = x @ c
    np.testing.assert_allclose(probe.fit_head(x, y, ridge=0.0), c, rtol=1e-8)
    assert probe.explained(x, y, c) == pytest.approx(1.0)
    noise = rng.normal(size=2000)
    fitted = probe.fit_head(x, y + noise, ridge=0.0)
    assert probe.explained(x, y + noise, fitted) == pytest.approx(
        1 - ((y + noise - x @ fitted) ** 2).sum() / ((y + noise) ** 2).sum()
    )
    assert probe.explained(x, noise, np.zeros(5)) == 0.0
