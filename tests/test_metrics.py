"""Evaluation metrics: analytic cases, masks, jit, baselines and the chaos floor."""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import metrics as M
from dispgns.evaluation import chaos_floor_rollout
from dispgns.physics import PhysicsConfig, simulate

DATA = Path(__file__).parent / "data"
L = 0.1
C = 6


def _random_walk(t=40, n=12, seed=0):
    """A trajectory well inside the box, with distinct radii; normalised units."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-0.6, 0.6, (1, n, 2))
    steps = rng.normal(0.0, 2e-3, (t - 1, n, 2))
    traj = np.concatenate([start, start + np.cumsum(steps, axis=0)], axis=0)
    radius = rng.choice([0.02, 0.03, 0.04, 0.05], n)
    return traj.astype(np.float32), radius.astype(np.float32)


def _offset_after_inputs(traj, offset):
    out = np.array(traj, copy=True)
    out[C:] += np.asarray(offset, np.float32)
    return out


# ---------------------------------------------------------------------------
# position errors
# ---------------------------------------------------------------------------


def test_identical_trajectories_give_zero_errors():
    truth, radius = _random_walk()
    m = M.rollout_metrics(truth, truth, radius, box_half_size=L, input_frames=C)
    for key in (
        "mse",
        "rmse_mm",
        "rmse_diameters",
        "mse_times_L_mm",
        "mse_h1",
        "mse_h10",
        "mse_hfull",
        "kinetic_energy_mean_abs_relative_error",
        "kinetic_energy_total_relative_error",
        "mean_height_mean_abs_error",
        "mean_height_final_error",
    ):
        assert m[key] == 0.0, key
    assert m["per_frame_mse"] == [0.0] * (truth.shape[0] - C)
    assert m["wall_violations_total"] == 0
    assert m["overlaps_total"] == m["overlaps_truth_total"]
    assert m["finite"] is True


def test_constant_offset_gives_delta_squared_and_unit_conversions():
    truth, radius = _random_walk()
    delta = 0.01
    m = M.rollout_metrics(_offset_after_inputs(truth, [delta, delta]), truth, radius, box_half_size=L, input_frames=C)
    assert m["mse"] == pytest.approx(delta**2, rel=1e-5)
    assert m["per_frame_mse"] == pytest.approx([delta**2] * (truth.shape[0] - C), rel=1e-5)
    assert m["rmse_mm"] == pytest.approx(delta * L * 1e3, rel=1e-5)  # 1 mm
    assert m["rmse_diameters"] == pytest.approx(delta / np.mean(2 * radius), rel=1e-5)
    # The paper's "mm" number multiplies the MSE by L: 1e-4 * 0.1 m = 1e-5 m = 0.01 mm.
    assert m["mse_times_L_mm"] == pytest.approx(delta**2 * L * 1e3, rel=1e-5)
    # An offset on one axis only: the mean runs over both axes.
    m_x = M.rollout_metrics(_offset_after_inputs(truth, [delta, 0.0]), truth, radius, box_half_size=L, input_frames=C)
    assert m_x["mse"] == pytest.approx(delta**2 / 2, rel=1e-5)
    # The paper's example: MSE 6.6e-4 is an RMSE of 2.6 mm.
    assert float(M.rmse_mm(6.6e-4, 0.1)) == pytest.approx(2.569, abs=1e-3)
    assert float(M.mse_times_L_mm(6.6e-4, 0.1)) == pytest.approx(0.066)


def test_horizons_slice_the_first_predicted_frames():
    truth, radius = _random_walk(t=C + 60)
    k = np.arange(60, dtype=np.float32)
    # Per-frame MSE of predicted frame k is exactly (k + 1) * 1e-6.
    offset = np.sqrt((k + 1) * 1e-6)[:, None, None]
    prediction = np.array(truth, copy=True)
    prediction[C:] += offset
    curve = np.asarray(M.per_frame_mse(prediction, truth, input_frames=C))
    np.testing.assert_allclose(curve, (k + 1) * 1e-6, rtol=2e-4)
    m = M.rollout_metrics(prediction, truth, radius, box_half_size=L, input_frames=C)
    assert m["mse_h1"] == pytest.approx(1e-6, rel=2e-4)
    assert m["mse_h10"] == pytest.approx(5.5e-6, rel=2e-4)
    assert m["mse_h50"] == pytest.approx(25.5e-6, rel=2e-4)
    assert m["mse_h100"] is None  # longer than the 60 predicted frames
    assert m["mse_hfull"] == pytest.approx(30.5e-6, rel=2e-4)
    assert m["mse"] == pytest.approx(30.5e-6, rel=2e-4)
    assert float(M.rollout_mse(prediction, truth, input_frames=C, horizon=10)) == pytest.approx(5.5e-6, rel=2e-4)
    with pytest.raises(ValueError, match="horizon"):
        M.rollout_mse(prediction, truth, input_frames=C, horizon=61)
    assert M.horizon_mse([1.0, 2.0, 3.0], horizons=(1, 2, 3, 4)) == {
        "1": 1.0,
        "2": 1.5,
        "3": 2.0,
        "4": None,
        "full": 2.0,
    }


def test_padding_never_counts():
    truth, radius = _random_walk(n=8)
    prediction = _offset_after_inputs(truth, [0.003, -0.001])
    prediction[-1, 2] = [0.99, 0.0]  # a real wall poke
    pad = 3

    def padded(traj, fill):
        extra = np.full((traj.shape[0], pad, 2), fill, np.float32)
        return np.concatenate([traj, extra], axis=1)

    radius_padded = np.concatenate([radius, np.full(pad, np.nan, np.float32)])
    mask = np.arange(8 + pad) < 8
    reference = M.rollout_metrics(prediction, truth, radius, box_half_size=L, input_frames=C)
    for fill in (np.nan, 5.0, 0.0):
        got = M.rollout_metrics(
            padded(prediction, fill), padded(truth, -fill), radius_padded, box_half_size=L, input_frames=C, mask=mask
        )
        assert got.keys() == reference.keys()
        for key, value in reference.items():
            if value is None or isinstance(value, bool):
                assert got[key] is value, key
            else:
                assert got[key] == pytest.approx(value, rel=1e-5, abs=1e-12), key
    assert reference["wall_violations_total"] == 1


def test_shape_errors_are_clear():
    truth, radius = _random_walk()
    with pytest.raises(ValueError, match="same shape"):
        M.rollout_metrics(truth[:-1], truth, radius, box_half_size=L)
    with pytest.raises(ValueError, match="radius"):
        M.rollout_metrics(truth, truth, radius[:-1], box_half_size=L)
    with pytest.raises(ValueError, match="mask"):
        M.rollout_metrics(truth, truth, radius, box_half_size=L, mask=np.ones(3, bool))
    with pytest.raises(ValueError, match="input_frames"):
        M.rollout_metrics(truth, truth, radius, box_half_size=L, input_frames=truth.shape[0])


# ---------------------------------------------------------------------------
# physical plausibility
# ---------------------------------------------------------------------------


def test_wall_pokes_counted_exactly():
    radius = np.array([0.05, 0.05, 0.05, 0.04, 0.05], np.float32)
    contact = 1.0 - 0.05
    frame0 = np.array(
        [
            [contact + 0.2 * 0.05, 0.0],  # 20 % of its radius through the right wall: counted
            [0.0, -contact - 0.05 * 0.05],  # 5 % through the bottom: within tolerance
            [contact + 0.5 * 0.05, contact + 0.5 * 0.05],  # through a corner: counted once
            [0.0, 0.0],
            [-2.0, 0.0],  # padding, far outside
        ],
        np.float32,
    )
    frame1 = np.zeros_like(frame0)
    frame1[:, 0] = np.linspace(-0.5, 0.5, 5)
    positions = np.stack([frame0, frame1])
    mask = np.array([True, True, True, True, False])
    np.testing.assert_array_equal(M.wall_violations(positions, radius, mask=mask), [2, 0])
    np.testing.assert_array_equal(M.wall_violations(positions, radius, tolerance=0.0, mask=mask), [3, 0])
    np.testing.assert_array_equal(M.wall_violations(positions, radius), [3, 0])


def test_overlaps_counted_exactly():
    radius = np.array([0.02, 0.04, 0.02, 0.03, 0.05], np.float32)
    # r_m = 1.75 min(a_i, a_j): 0.035 for pairs (0, 1), (2, 3).
    frame0 = np.array(
        [
            [0.0, 0.0],
            [0.033, 0.0],  # 0.033 < 0.035: overlap
            [0.5, 0.5],
            [0.5, 0.537],  # 0.037 > 0.035, though closer than a_2 + a_3: no overlap
            [0.01, 0.0],  # padding on top of particle 0: ignored
        ],
        np.float32,
    )
    frame1 = np.array([[0.0, 0.0], [0.0, 0.02], [0.0, -0.02], [-0.6, -0.6], [0.9, 0.9]], np.float32)
    positions = np.stack([frame0, frame1])
    mask = np.array([True, True, True, True, False])
    # Frame 1: (0, 1) at 0.02 < 0.035, (0, 2) at 0.02 < 0.035, (1, 2) at 0.04 > 0.035.
    np.testing.assert_array_equal(M.overlap_counts(positions, radius, mask=mask), [1, 2])
    np.testing.assert_array_equal(M.overlap_counts(positions, radius, coeff=2.0, mask=mask), [2, 2])
    # Unmasked, the padding particle overlaps particles 0 and 1 too.
    np.testing.assert_array_equal(M.overlap_counts(positions, radius), [3, 2])


def test_kinetic_energy_of_uniform_motion():
    config = PhysicsConfig()
    frame_dt = 1.5e-3
    truth, radius = _random_walk(t=20, n=5)
    velocity = np.array([0.004, -0.002], np.float32)  # normalised units per frame
    uniform = truth[:1] + np.arange(20, dtype=np.float32)[:, None, None] * velocity
    energy = np.asarray(M.kinetic_energy(uniform, radius, box_half_size=L, frame_dt=frame_dt, config=config))
    mass = math.pi * (radius.astype(np.float64) * L) ** 2 * config.thickness * config.density
    speed2 = float(np.sum(velocity.astype(np.float64) ** 2)) * (L / frame_dt) ** 2
    np.testing.assert_allclose(energy, 0.5 * np.sum(mass) * speed2, rtol=1e-4)
    assert energy.shape == (19,)
    # Twice the speed after the inputs: four times the energy of every predicted frame.
    faster = truth[:1] + np.arange(20, dtype=np.float32)[:, None, None] * velocity
    faster[C:] = faster[C - 1] + np.arange(1, 20 - C + 1, dtype=np.float32)[:, None, None] * 2 * velocity
    m = M.rollout_metrics(faster, uniform, radius, box_half_size=L, input_frames=C, frame_dt=frame_dt)
    assert m["kinetic_energy_total_relative_error"] == pytest.approx(3.0, rel=1e-4)
    assert m["kinetic_energy_relative_error"] == pytest.approx([3.0] * (20 - C), rel=1e-4)
    assert len(m["kinetic_energy_truth"]) == 20 - C


def test_mean_height_error():
    truth, radius = _random_walk()
    m = M.rollout_metrics(_offset_after_inputs(truth, [0.0, -0.02]), truth, radius, box_half_size=L, input_frames=C)
    assert m["mean_height_error"] == pytest.approx([-0.02] * (truth.shape[0] - C), abs=1e-6)
    assert m["mean_height_final_error"] == pytest.approx(-0.02, abs=1e-6)
    assert m["mean_height_mean_abs_error_mm"] == pytest.approx(2.0, rel=1e-4)
    np.testing.assert_allclose(m["mean_height_truth"], truth[C:, :, 1].mean(axis=1), atol=1e-6)


# ---------------------------------------------------------------------------
# baselines
# ---------------------------------------------------------------------------


def test_constant_velocity_is_exact_on_uniform_motion():
    truth, radius = _random_walk(t=30)
    velocity = np.random.default_rng(1).normal(0, 1e-3, truth.shape[1:]).astype(np.float32)
    uniform = truth[:1] + np.arange(30, dtype=np.float32)[:, None, None] * velocity
    baseline = np.asarray(M.constant_velocity_rollout(uniform, input_frames=C))
    np.testing.assert_array_equal(baseline[:C], uniform[:C])
    np.testing.assert_allclose(baseline, uniform, atol=1e-6)
    m = M.rollout_metrics(uniform, uniform, radius, box_half_size=L, input_frames=C)
    assert m["constant_velocity_mse"] < 1e-12
    # Only the last two inputs are used, and the output can be longer than the input.
    longer = np.asarray(M.constant_velocity_rollout(uniform[:C], input_frames=C, n_frames=30))
    np.testing.assert_allclose(longer, uniform, atol=1e-6)
    # On the random walk the baseline is not exact.
    m = M.rollout_metrics(truth, truth, radius, box_half_size=L, input_frames=C)
    assert m["constant_velocity_mse"] > 0 and m["mse_over_constant_velocity"] == 0.0


def test_array_functions_jit_and_vmap():
    truth, radius = _random_walk(t=25, n=9)
    prediction = _offset_after_inputs(truth, [0.01, 0.0])
    mask = np.arange(9) < 7
    cases = {
        "per_frame_mse": lambda p, t: M.per_frame_mse(p, t, input_frames=C, mask=mask),
        "overlaps": lambda p, t: M.overlap_counts(p, radius, mask=mask),
        "walls": lambda p, t: M.wall_violations(p, radius, mask=mask),
        "energy": lambda p, t: M.kinetic_energy(p, radius, box_half_size=L, frame_dt=1.5e-3, mask=mask),
        "height": lambda p, t: M.mean_height(p, mask),
        "baseline": lambda p, t: M.constant_velocity_rollout(t, input_frames=C),
    }
    for name, fn in cases.items():
        eager = np.asarray(fn(prediction, truth))
        np.testing.assert_allclose(np.asarray(jax.jit(fn)(prediction, truth)), eager, rtol=1e-6, err_msg=name)
    batch_p, batch_t = np.stack([prediction, truth]), np.stack([truth, prediction])
    fn = cases["per_frame_mse"]
    vmapped = np.asarray(jax.vmap(fn)(batch_p, batch_t))
    looped = np.stack([np.asarray(fn(p, t)) for p, t in zip(batch_p, batch_t)])
    np.testing.assert_allclose(vmapped, looped, rtol=1e-6)


# ---------------------------------------------------------------------------
# reports
# ---------------------------------------------------------------------------


def test_rollout_metrics_is_json_ready_and_summarize_gives_mean_std():
    truth, radius = _random_walk(t=20)
    metrics = [
        M.rollout_metrics(_offset_after_inputs(truth, [d, d]), truth, radius, box_half_size=L, input_frames=C)
        for d in (0.01, 0.03)
    ]
    text = json.dumps(metrics, allow_nan=False)
    assert json.loads(text) == metrics
    assert metrics[0]["mse_h50"] is None
    summary = M.summarize(metrics)
    assert summary["n_trajectories"] == 2
    assert summary["mse"]["mean"] == pytest.approx((1e-4 + 9e-4) / 2, rel=1e-5)
    assert summary["mse"]["std"] == pytest.approx(4e-4, rel=1e-4)  # population std
    assert summary["mse"]["n"] == 2
    assert "mse_h50" not in summary  # only None values
    assert summary["finite"]["mean"] == 1.0
    assert summary["per_frame_mse"]["mean"] == pytest.approx([5e-4] * (20 - C), rel=1e-5)
    json.dumps(summary, allow_nan=False)
    # Ragged curves: the common prefix; missing keys: counted out.
    short = {"mse": 1.0, "per_frame_mse": [1.0]}
    summary = M.summarize([{"mse": 3.0, "per_frame_mse": [3.0, 5.0], "extra": 2.0, "name": "x"}, short])
    assert summary["mse"] == {"mean": 2.0, "std": 1.0, "n": 2}
    assert summary["per_frame_mse"] == {"mean": [2.0], "std": [1.0], "n": 2}
    assert summary["extra"] == {"mean": 2.0, "std": 0.0, "n": 1}
    assert "name" not in summary


def test_non_finite_prediction_is_reported_not_hidden():
    truth, radius = _random_walk(t=15)
    prediction = np.array(truth, copy=True)
    prediction[-1, 0] = np.nan
    m = M.rollout_metrics(prediction, truth, radius, box_half_size=L, input_frames=C)
    assert m["finite"] is False
    assert math.isnan(m["mse"])
    assert math.isnan(M.summarize([m, m])["mse"]["mean"])


# ---------------------------------------------------------------------------
# chaos floor
# ---------------------------------------------------------------------------


def _small_system():
    data = np.load(DATA / "sedimentation.npz")
    return data["x0"][:10], data["v0"][:10], data["radius"][:10]


def test_chaos_floor_without_perturbation_is_the_simulation():
    x0, v0, radius = _small_system()
    config = PhysicsConfig()
    floor = chaos_floor_rollout(x0, v0, radius, config, key=jax.random.PRNGKey(0), n_frames=20, perturbation=0.0)
    with jax.enable_x64(True):
        exact = np.asarray(simulate(jnp.asarray(x0), jnp.asarray(v0), jnp.asarray(radius), config, n_frames=20))
    assert floor.dtype == np.float64 and floor.shape == (20, 10, 2)
    np.testing.assert_array_equal(floor, exact / config.box_half_size)


def test_chaos_floor_stays_close_for_a_few_frames():
    x0, v0, radius = _small_system()
    config = PhysicsConfig()
    truth = chaos_floor_rollout(x0, v0, radius, config, key=0, n_frames=20, perturbation=0.0)
    floor = chaos_floor_rollout(x0, v0, radius, config, key=jax.random.PRNGKey(1), n_frames=20)
    again = chaos_floor_rollout(x0, v0, radius, config, key=jax.random.PRNGKey(1), n_frames=20)
    np.testing.assert_array_equal(floor, again)  # seeded
    start = np.abs(floor[0] - truth[0])
    assert 0 < start.max() < 5e-6  # a 1e-6 L normal shift per coordinate
    drift = np.abs(floor - truth).max(axis=(1, 2))
    assert np.all(drift[:5] < 1e-4), drift
    m = M.rollout_metrics(
        truth,
        truth,
        radius / config.box_half_size,
        box_half_size=config.box_half_size,
        input_frames=C,
        chaos_floor=floor,
    )
    assert 0 < m["chaos_floor_mse"] < 1e-8
    assert len(m["chaos_floor_per_frame_mse"]) == 20 - C
    # Padding particles are not perturbed (the physics tests show they never touch real ones).
    mask = np.arange(10) < 8
    masked = chaos_floor_rollout(x0, v0, radius, config, key=jax.random.PRNGKey(1), n_frames=20, mask=mask)
    np.testing.assert_array_equal(masked[0, 8:], truth[0, 8:])
    assert np.all(masked[0, :8] != truth[0, :8])


def test_rollout_metrics_needs_two_input_frames():
    truth = np.zeros((10, 3, 2))
    with pytest.raises(ValueError, match="input_frames must be an integer >= 2"):
        M.rollout_metrics(truth, truth, np.full(3, 0.03), box_half_size=0.1, input_frames=1)


# ---------------------------------------------------------------------------
# statistics: front, settling, bed, g(r), distribution distances
# ---------------------------------------------------------------------------


def test_front_height_is_numpys_quantile_and_ignores_padding():
    rng = np.random.default_rng(3)
    heights = rng.normal(size=(4, 30, 2)).astype(np.float32)
    expected = np.quantile(heights[..., -1], 0.9, axis=1)
    np.testing.assert_allclose(M.front_height(heights, quantile=0.9), expected, rtol=1e-5, atol=1e-6)
    padded = np.concatenate([heights, np.full((4, 5, 2), 1e6, np.float32)], axis=1)
    mask = np.arange(35) < 30
    np.testing.assert_allclose(
        jax.jit(M.front_height, static_argnames="quantile")(padded, mask, quantile=0.9), expected, rtol=1e-5, atol=1e-6
    )


def test_settling_velocity_of_a_linear_fall():
    # Heights falling 2e-3 L per frame of 1.5 ms, L = 0.1 m: -2e-4 m / 1.5e-3 s = -0.1333 m/s.
    heights = 0.5 - 2e-3 * np.arange(50)
    velocity = M.settling_velocity(heights, frame_dt=1.5e-3, box_half_size=L)
    assert float(velocity) == pytest.approx(-2e-3 * L / 1.5e-3, rel=1e-5)


def test_height_profile_and_bed_fraction_by_hand():
    # Four disks of radius 0.1 at heights -0.95, -0.9 (slab 0 of [-1, -0.5)), -0.4 (slab 1) and 0.6 (slab 3);
    # a fifth, padding, must not count.
    frame = np.array([[0.0, -0.95], [0.5, -0.9], [-0.5, -0.4], [0.2, 0.6], [0.0, -0.99]], np.float32)
    radius = np.full(5, 0.1, np.float32)
    mask = np.array([True, True, True, True, False])
    counts, fraction = M.height_profile(frame, radius, mask, bins=4)
    np.testing.assert_allclose(counts, [2, 1, 0, 1])
    disk = math.pi * 0.01
    np.testing.assert_allclose(fraction, np.array([2, 1, 0, 1]) * disk / (0.5 * 2.0), rtol=1e-6)
    # Front at the top quantile (1.0): the highest disk, 0.6; bed = 4 disks over 2 x 1.6.
    value = M.bed_area_fraction(frame, radius, mask, quantile=1.0)
    assert float(value) == pytest.approx(4 * disk / (2.0 * 1.6), rel=1e-6)


def test_radial_distribution_of_a_square_lattice_by_hand():
    # n x n lattice of spacing s: ordered pairs at each distance counted by hand; the shells (width
    # 0.0145) put every lattice distance well inside one shell, and 3 s lies beyond r_max.
    n, s, bins, r_max, volume = 6, 0.1, 20, 0.29, 4.0
    grid = np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2) * s
    r, g = jax.jit(M.radial_distribution, static_argnames=("r_max", "bins", "volume"))(
        grid.astype(np.float32) + 0.013, r_max=r_max, bins=bins, volume=volume
    )
    width = r_max / bins
    density = n * n / volume
    expected = np.zeros(bins)
    pairs = {
        s: 4 * n * (n - 1),
        s * math.sqrt(2): 4 * (n - 1) ** 2,
        2 * s: 4 * n * (n - 2),
        s * math.sqrt(5): 8 * (n - 1) * (n - 2),
        s * math.sqrt(8): 4 * (n - 2) ** 2,
    }
    for distance, count in pairs.items():
        k = int(distance / width)
        expected[k] = count / (n * n * density * math.pi * ((k + 1) ** 2 - k**2) * width**2)
    np.testing.assert_allclose(r, (np.arange(bins) + 0.5) * width, rtol=1e-6)
    np.testing.assert_allclose(g, expected, rtol=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_radial_distribution_matches_freud_overall_and_per_size_pair(dim):
    # In 3-D the ideal-gas count uses the spherical shell 4/3 pi (r_hi^3 - r_lo^3) and the box volume.
    freud = pytest.importorskip("freud")
    rng = np.random.default_rng(7)
    n = 150 if dim == 2 else 400
    points = rng.uniform(-1, 1, (n, dim)).astype(np.float32)
    large = rng.random(n) < 0.4
    side = 10.0  # a box with no periodic image within r_max: freud's g(r) of the open system
    box = freud.box.Box.square(side) if dim == 2 else freud.box.Box.cube(side)
    flat = np.concatenate([points, np.zeros((n, 1), np.float32)], axis=1) if dim == 2 else points
    for neighbours, queries in ((None, None), (large, ~large), (large, large)):
        rdf = freud.density.RDF(bins=20, r_max=0.4, normalization_mode="exact")
        system = flat if neighbours is None else flat[neighbours]
        # freud drops a particle's pair with itself only when the query points are the points themselves.
        same = queries is None or queries is neighbours
        rdf.compute(system=(box, system), query_points=None if same else flat[queries], reset=True)
        r, g = M.radial_distribution(points, r_max=0.4, bins=20, volume=side**dim, mask=neighbours, query_mask=queries)
        np.testing.assert_allclose(r, rdf.bin_centers, rtol=1e-5)
        assert np.count_nonzero(rdf.rdf) > 15  # shells with pairs in them: the comparison is not of zeros
        np.testing.assert_allclose(g, rdf.rdf, rtol=1e-4, atol=1e-4)


def test_sinkhorn_divergence_zero_for_identical_and_shift_squared_for_translate():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(60, 2)).astype(np.float32)
    shift = np.array([0.3, -0.2], np.float32)
    divergence = jax.jit(M.sinkhorn_divergence, static_argnames="epsilon")
    assert abs(float(divergence(x, x, epsilon=1e-2))) < 1e-5
    # Squared Euclidean cost: the debiased divergence of a translate is |t|^2.
    assert float(divergence(x, x + shift, epsilon=1e-2)) == pytest.approx(float(shift @ shift), rel=2e-2)
    # Padding points (masked out, placed far away) change nothing.
    padded = np.concatenate([x, np.full((4, 2), 50.0, np.float32)])
    mask = np.arange(64) < 60
    value = M.sinkhorn_divergence(padded, x + shift, epsilon=1e-2, mask_x=mask)
    assert float(value) == pytest.approx(float(shift @ shift), rel=2e-2)


def test_maximum_mean_discrepancy_is_symmetric_zero_on_equal_sets_and_by_hand():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(40, 2)).astype(np.float32)
    y = rng.normal(size=(30, 2)).astype(np.float32) + 0.5
    bandwidths = (0.3, 1.0)
    xy = M.maximum_mean_discrepancy(x, y, bandwidths=bandwidths)
    assert float(xy) > 0
    assert float(M.maximum_mean_discrepancy(y, x, bandwidths=bandwidths)) == pytest.approx(float(xy), rel=1e-5)
    assert abs(float(M.maximum_mean_discrepancy(x, x[::-1], bandwidths=bandwidths))) < 1e-6
    # One point each, distance d: 2 sum_s (1 - exp(-d^2 / 2 s^2)).
    d2 = 0.5**2 + 0.2**2
    one = M.maximum_mean_discrepancy(np.zeros((1, 2)), np.array([[0.5, 0.2]]), bandwidths=bandwidths)
    expected = 2 * sum(1 - math.exp(-d2 / (2 * s * s)) for s in bandwidths)
    assert float(one) == pytest.approx(expected, rel=1e-5)
    # Masked padding changes nothing.
    padded = np.concatenate([y, np.full((3, 2), 9.0, np.float32)])
    masked = M.maximum_mean_discrepancy(x, padded, bandwidths=bandwidths, mask_y=np.arange(33) < 30)
    assert float(masked) == pytest.approx(float(xy), rel=1e-5)


def test_rollout_statistics_of_a_translate_and_of_the_truth_itself_with_padding(tmp_path):
    truth, radius = _random_walk(t=30, n=12)
    shift = np.array([0.01, -0.02], np.float32)
    prediction = _offset_after_inputs(truth, shift)
    kw = dict(box_half_size=L, input_frames=C, statistics=True)
    m = M.rollout_metrics(prediction, truth, radius, chaos_floor=truth, **kw)
    # The chaos floor here is the truth: every statistic agrees, every distance is 0.
    for key in (
        "chaos_floor_rdf_l1",
        "chaos_floor_height_profile_distance",
        "chaos_floor_mmd_position_final",
        "chaos_floor_mmd_velocity_mean",
        "chaos_floor_front_height_mean_abs_error_mm",
        "chaos_floor_settling_velocity_error_mm_s",
        "chaos_floor_bed_area_fraction_error",
    ):
        assert abs(m[key]) < 1e-6, key
    assert abs(m["chaos_floor_sinkhorn_position_final"]) < 1e-5
    # A translate by t: Sinkhorn divergence |t|^2, heights off by t_y (2 mm down), same final velocities.
    assert m["sinkhorn_position_final"] == pytest.approx(float(shift @ shift), rel=0.05)
    assert m["front_height_final_error_mm"] == pytest.approx(-2.0, abs=1e-3)
    assert m["mean_height_final_error_mm"] == pytest.approx(-2.0, abs=1e-3)
    assert m["settling_velocity_error_mm_s"] == pytest.approx(0.0, abs=1e-3)
    assert abs(m["mmd_velocity_final"]) < 1e-6 and abs(m["sinkhorn_velocity_final"]) < 1e-5
    assert len(m["sinkhorn_position"]) == len(m["distribution_frames"]) and m["distribution_frames"][-1] == 30 - C - 1
    assert "constant_velocity_sinkhorn_position_final" not in m and m["constant_velocity_mmd_position_final"] > 0
    # Padding particles (far away, masked) change nothing.
    pad = lambda x: np.concatenate([x, np.full((x.shape[0], 3, 2), 0.9, np.float32)], axis=1)  # noqa: E731
    mask = np.arange(15) < 12
    padded = M.rollout_metrics(
        pad(prediction),
        pad(truth),
        np.concatenate([radius, np.full(3, 0.04, np.float32)]),
        chaos_floor=pad(truth),
        mask=mask,
        **kw,
    )
    for key in (
        "rdf_l1",
        "sinkhorn_position_final",
        "mmd_position_final",
        "bed_area_fraction_error",
        "front_height_final_error_mm",
    ):
        assert padded[key] == pytest.approx(m[key], rel=1e-4, abs=1e-6), key
    from dispgns.render import plot_statistics

    plot_statistics(M.summarize([m, m]), path=tmp_path / "statistics.png")
    assert (tmp_path / "statistics.png").stat().st_size > 0
