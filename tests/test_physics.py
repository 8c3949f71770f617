"""Properties of the ground-truth physics: analytic limits, invariants, transformations, padding, capacities."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dispgns.physics.integrate as integrate
from dispgns import PhysicsConfig, sample_initial_state, simulate, simulate_batch, simulate_scan
from dispgns.physics import PlacementError, interaction_force, particle_count_range, particle_mass

CONFIG = PhysicsConfig()
L = CONFIG.box_half_size


@pytest.fixture(scope="module")
def small_state():
    """About 20 particles of 8-10 mm: a dense, wall-touching system that runs fast."""
    return sample_initial_state(jax.random.PRNGKey(3), [8e-3, 10e-3], CONFIG)


def test_isolated_particle_follows_the_euler_recurrence():
    config = dataclasses.replace(CONFIG, gravity=0.0)
    radius = np.array([3e-3])
    v0 = np.array([[0.05, -0.02]])
    with jax.enable_x64(True):
        x, v = simulate(np.zeros((1, 2)), v0, radius, config, n_frames=11, save_every=10, return_velocity=True)
        mass = float(particle_mass(jnp.asarray(radius), config, 2)[0])
    factor = 1.0 - config.dt * config.drag * radius[0] / mass
    steps = np.arange(11) * 10
    np.testing.assert_allclose(np.asarray(v)[:, 0], v0[0] * factor ** steps[:, None], rtol=1e-12)
    # x_n = x_0 + dt v_0 (1 - f^n) / (1 - f): positions use the old velocity.
    expected_x = config.dt * v0[0] * ((1 - factor**steps) / (1 - factor))[:, None]
    np.testing.assert_allclose(np.asarray(x)[:, 0], expected_x, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize("dim", [2, 3])
def test_isolated_particle_reaches_terminal_settling_speed(dim):
    # A disk (2-D, relaxes in m / (k a) = 460 steps) or a 2.5 mm sphere (3-D, 370 steps): 3300
    # steps leave a transient below 1e-3, and neither reaches the floor of the 0.1 m box.
    radius = 4e-3 if dim == 2 else 2.5e-3
    start = np.zeros((1, dim)) + np.eye(dim)[-1] * 0.09
    x = simulate(start, np.zeros((1, dim)), np.array([radius]), CONFIG, n_frames=12, save_every=300)
    speed = (x[11, 0, -1] - x[10, 0, -1]) / (300 * CONFIG.dt)
    np.testing.assert_allclose(-float(speed), CONFIG.settling_speed(radius, dim), rtol=3e-3)


def test_pair_force_is_minus_gradient_of_the_potential_above_r_m_and_frozen_below():
    config = CONFIG
    a = np.array([3e-3, 4.5e-3])
    sigma = a.sum()
    r_m = config.min_distance_coeff * a.min()

    def potential(r):
        u0 = config.well_depth_coeff * sigma**2
        s = sigma / r
        return 4 * u0 * (s ** (2 * config.lj_exponent) - s**config.lj_exponent)

    with jax.enable_x64(True):
        for r in [r_m * 1.01, sigma * 0.95, sigma * 1.3, 0.15]:
            position = jnp.array([[0.0, 0.0], [r, 0.0]])
            force = interaction_force(position, jnp.arange(2), position, jnp.asarray(a), jnp.ones(2, bool), config)
            expected = -jax.grad(potential)(r)  # force on particle 1 along +x
            np.testing.assert_allclose(float(force[1, 0]), float(expected), rtol=1e-10)
            np.testing.assert_allclose(np.asarray(force[0]), -np.asarray(force[1]), rtol=1e-12)
        below = []
        for r in [0.3 * r_m, 0.7 * r_m, r_m]:
            position = jnp.array([[0.0, 0.0], [0.0, r]])
            force = interaction_force(position, jnp.arange(2), position, jnp.asarray(a), jnp.ones(2, bool), config)
            below.append(float(force[1, 1]))
        np.testing.assert_allclose(below, below[-1], rtol=1e-12)
        assert below[-1] > 0  # repulsive


def all_pair_forces_float32_and_float64(position, radius):
    """Dense all-pairs forces on every particle (N), computed in float32 and in float64."""
    n = len(radius)

    def force(dtype):
        x, a = jnp.asarray(position, dtype), jnp.asarray(radius, dtype)
        return np.asarray(interaction_force(x, jnp.arange(n), x, a, jnp.ones(n, bool), CONFIG), np.float64)

    with jax.enable_x64(True):
        exact = force(jnp.float64)
    return force(jnp.float32), exact


def buoyant_weight(radius):
    return (CONFIG.density - CONFIG.fluid_density) * np.pi * radius**2 * CONFIG.thickness * CONFIG.gravity


def test_float32_all_pair_forces_in_a_settled_bed_match_float64():
    # The dense path sums pair terms as a matrix product over coordinates,
    # which cancels; in the reference's settled bed (150 particles in contact)
    # its float32 error stays that of the pair coefficients themselves.
    data = np.load(Path(__file__).parent / "data" / "sedimentation.npz")
    radius = data["radius"]
    approx, exact = all_pair_forces_float32_and_float64(data["frames"][-1], radius)
    weight = buoyant_weight(radius)
    assert np.abs(exact).max() > 5 * weight.max()  # contacts carry the weight of the bed above
    assert np.max(np.abs(approx - exact).max(axis=1) / weight) < 1e-3


def test_float32_all_pair_forces_across_a_wide_packed_bed_stay_within_the_documented_error():
    # The worst case the README quotes: 1 mm disks compressed (spacing 1.98 a)
    # across the whole 0.2 m box, where the matrix product's cancellation
    # costs ~13x the direct sum's error (measured here: 1.3e-3 of the weight,
    # 3.6e-5 of the largest force).
    a, rows = 1e-3, 8
    spacing = 1.98 * a
    cols = int(2 * L / spacing) - 2
    points = [
        (-L + a + i * spacing + (j % 2) * spacing / 2, -L + a + j * spacing * np.sqrt(3) / 2)
        for j in range(rows)
        for i in range(cols)
    ]
    jitter = np.random.default_rng(0).uniform(-0.01, 0.01, (len(points), 2)) * a
    position = (np.array(points) + jitter).astype(np.float32).astype(np.float64)
    approx, exact = all_pair_forces_float32_and_float64(position, np.full(len(position), a))
    error = np.abs(approx - exact).max(axis=1)
    weight = buoyant_weight(a)
    assert error.max() < 3e-3 * weight
    assert error.max() < 1e-4 * np.abs(exact).max()


def test_no_particle_ever_ends_a_step_outside_the_box(small_state):
    # Fast particles thrown at every wall and corner, recorded after every step.
    key = jax.random.PRNGKey(0)
    v0 = jax.random.uniform(key, small_state.position.shape, minval=-0.6, maxval=0.6)
    x = np.asarray(simulate(small_state.position, v0, small_state.radius, CONFIG, n_frames=400, save_every=1))
    limit = L - np.asarray(small_state.radius)[None, :, None]
    assert np.all(np.abs(x) <= limit * (1 + 1e-6))


def test_kinetic_energy_decays_without_gravity_or_walls():
    config = dataclasses.replace(CONFIG, gravity=0.0)
    grid = np.stack(np.meshgrid(np.linspace(-0.05, 0.05, 4), np.linspace(-0.05, 0.05, 4)), -1).reshape(-1, 2)
    radius = np.full(16, 3e-3)
    v0 = np.asarray(jax.random.uniform(jax.random.PRNGKey(1), grid.shape, minval=-0.02, maxval=0.02))
    x, v = simulate(grid, v0, radius, config, n_frames=40, save_every=10, return_velocity=True)
    assert np.all(np.abs(np.asarray(x)) < L - 3e-3)  # no wall was touched
    energy = 0.5 * np.sum(
        np.asarray(particle_mass(jnp.asarray(radius), config, 2))[None, :, None] * np.asarray(v) ** 2, axis=(1, 2)
    )
    assert np.all(np.diff(energy) < 0)
    assert energy[-1] < 0.5 * energy[0]


def test_jit_equals_no_jit(small_state):
    args = (small_state.position, small_state.velocity, small_state.radius)
    eager = simulate(*args, CONFIG, n_frames=30)
    jitted = jax.jit(lambda x, v, a: simulate_scan(x, v, a, CONFIG, n_frames=30).position)(*args)
    assert not np.any(np.asarray(simulate_scan(*args, CONFIG, n_frames=30).overflow))
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=0, atol=1e-6)


def test_vmap_and_batch_equal_a_loop():
    states = [sample_initial_state(jax.random.PRNGKey(k), [8e-3, 10e-3], CONFIG, n_particles=15) for k in range(3)]
    xs = jnp.stack([s.position for s in states])
    vs = jnp.stack([s.velocity for s in states])
    rs = jnp.stack([s.radius for s in states])
    loop = np.stack([np.asarray(simulate(s.position, s.velocity, s.radius, CONFIG, n_frames=20)) for s in states])
    vmapped = jax.vmap(lambda x, v, a: simulate_scan(x, v, a, CONFIG, n_frames=20).position)(xs, vs, rs)
    batched = simulate_batch(xs, vs, rs, jnp.ones(rs.shape, bool), CONFIG, n_frames=20)
    np.testing.assert_allclose(np.asarray(vmapped), loop, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(batched), loop, rtol=0, atol=1e-6)


@pytest.mark.parametrize("cutoff", [None, 0.03])
def test_padding_never_changes_real_particles(cutoff):
    config = dataclasses.replace(CONFIG, cutoff=cutoff)
    a = sample_initial_state(jax.random.PRNGKey(5), [8e-3, 10e-3], CONFIG, n_particles=12)
    b = sample_initial_state(jax.random.PRNGKey(6), [8e-3, 10e-3], CONFIG, n_particles=18)
    pad = lambda arr, n: jnp.concatenate([arr, jnp.full((n - arr.shape[0],) + arr.shape[1:], 0.5, arr.dtype)])
    xs = jnp.stack([pad(a.position, 18), b.position])
    vs = jnp.stack([pad(a.velocity, 18), b.velocity])
    rs = jnp.stack([pad(a.radius, 18), b.radius])
    mask = jnp.stack([jnp.arange(18) < 12, jnp.ones(18, bool)])
    batched = np.asarray(simulate_batch(xs, vs, rs, mask, config, n_frames=25))
    alone_a = np.asarray(simulate(a.position, a.velocity, a.radius, config, n_frames=25))
    alone_b = np.asarray(simulate(b.position, b.velocity, b.radius, config, n_frames=25))
    np.testing.assert_allclose(batched[0, :, :12], alone_a, rtol=0, atol=1e-6)
    np.testing.assert_allclose(batched[1], alone_b, rtol=0, atol=1e-6)


def test_cutoff_beyond_the_box_equals_all_pairs(small_state):
    args = (small_state.position, small_state.velocity, small_state.radius)
    exact = simulate(*args, CONFIG, n_frames=40)
    with_cutoff = simulate(*args, dataclasses.replace(CONFIG, cutoff=3 * L), n_frames=40)
    np.testing.assert_allclose(np.asarray(with_cutoff), np.asarray(exact), rtol=0, atol=1e-6)


def converging_ring(n=40, ring=0.08, speed=1.0, radius=3e-3, dim=2):
    """Particles on a ring (a sphere in 3-D) flying to its centre: sparse at first, a dense cluster later."""
    if dim == 2:
        angle = 2 * np.pi * np.arange(n) / n
        direction = np.stack([np.cos(angle), np.sin(angle)], -1)
    else:  # a Fibonacci sphere: near-uniform directions
        z = 1 - (2 * np.arange(n) + 1) / n
        angle = np.pi * (3 - np.sqrt(5)) * np.arange(n)
        direction = np.stack([np.sqrt(1 - z**2) * np.cos(angle), np.sqrt(1 - z**2) * np.sin(angle), z], -1)
    return ring * direction, -speed * direction, np.full(n, radius)


def capacities_tried(monkeypatch):
    """The capacities the physics' host driver runs its attempts with (a spy on ``dispgns.capacity.drive``)."""
    tried = []
    original = integrate.drive

    def spy(run, state, capacity, grow, **kwargs):
        def recorded(state, capacity, remaining):
            tried.append(capacity)
            return run(state, capacity, remaining)

        return original(recorded, state, capacity, grow, **kwargs)

    monkeypatch.setattr(integrate, "drive", spy)
    return tried


@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_neighbor_list_overflow_is_detected_and_recomputed(monkeypatch, dim):
    config = dataclasses.replace(CONFIG, cutoff=0.02, neighbor_skin=1e-3)
    x0, v0, radius = converging_ring(n=40 if dim == 2 else 60, dim=dim)
    tried = capacities_tried(monkeypatch)
    run = simulate(x0, v0, radius, config, n_frames=60, chunk_frames=10)
    sizes = [(c.cell, c.neighbors) for c in tried]
    assert len(set(sizes)) >= 2, "the neighbour list never overflowed; the test lost its purpose"
    assert sizes == sorted(sizes)  # only ever grown
    # Same cutoff on the pure all-pairs path, which has no neighbour list to overflow.
    exact = jax.jit(lambda x, v, a: simulate_scan(x, v, a, config, n_frames=60).position)(x0, v0, radius)
    np.testing.assert_allclose(np.asarray(run), np.asarray(exact), rtol=0, atol=1e-5)


def test_3d_cell_lists_equal_all_pairs_with_the_cutoff():
    # The 3-D reference start (182 spheres, 27 neighbour cells each), cut off at 2 cm, in float64.
    data = np.load(Path(__file__).parent / "data" / "sedimentation_3d.npz")
    config = dataclasses.replace(CONFIG, cutoff=0.02, neighbor_skin=1e-3)
    with jax.enable_x64(True):
        args = (data["x0"], data["v0"], data["radius"])
        cells = simulate(*args, config, n_frames=4, save_every=5)
        exact = simulate_scan(*args, config, n_frames=4, save_every=5).position
        assert cells.shape == (4, 182, 3)
        np.testing.assert_allclose(np.asarray(cells), np.asarray(exact), rtol=0, atol=1e-13)
        # The cut-off matters here: without it the spheres move differently.
        assert np.max(np.abs(np.asarray(simulate(*args, CONFIG, n_frames=4, save_every=5)) - np.asarray(cells))) > 1e-9


def row_hitting_the_floor(n=6, radius=5e-3):
    """A row of particles just above the floor, falling together: all collide in one step."""
    x0 = np.stack([np.linspace(-0.08, 0.08, n), np.full(n, -L + radius + 1e-4)], -1)
    v0 = np.tile([0.0, -0.8], (n, 1))
    return x0, v0, np.full(n, radius)


def test_collision_capacity_overflow_is_detected_and_recomputed(monkeypatch):
    x0, v0, radius = row_hitting_the_floor()
    assert np.asarray(simulate_scan(x0, v0, radius, CONFIG, n_frames=30, collision_capacity=1).overflow).any()
    tried = capacities_tried(monkeypatch)
    small = simulate(x0, v0, radius, CONFIG, n_frames=30, collision_capacity=1, chunk_frames=10)
    capacities = [c.collisions for c in tried]
    assert capacities[0] == 1 and max(capacities) > 1
    exact = simulate(x0, v0, radius, CONFIG, n_frames=30, collision_capacity=None)
    np.testing.assert_allclose(np.asarray(small), np.asarray(exact), rtol=0, atol=1e-6)


def test_overflow_under_jit_poisons_instead_of_lying():
    x0, v0, radius = row_hitting_the_floor()
    run = jax.jit(lambda x, v, a: simulate_scan(x, v, a, CONFIG, n_frames=30, collision_capacity=1))(x0, v0, radius)
    assert np.isnan(np.asarray(run.position)[-1]).all() and bool(run.overflow[-1])


def test_host_drivers_name_the_pure_core_under_a_transformation(small_state):
    args = (small_state.position, small_state.velocity, small_state.radius)
    with pytest.raises(ValueError, match="simulate_scan"):
        jax.jit(lambda x, v, a: simulate(x, v, a, CONFIG, n_frames=3))(*args)


def test_gradient_through_simulate_is_finite(small_state):
    def final_height(radius):
        x = simulate_scan(small_state.position, small_state.velocity, radius, CONFIG, n_frames=10).position
        return jnp.mean(x[-1, :, 1])

    grad = jax.grad(final_height)(small_state.radius)
    assert np.all(np.isfinite(np.asarray(grad))) and np.any(np.asarray(grad) != 0)


def test_three_dimensional_spheres_stay_in_the_box():
    key = jax.random.PRNGKey(8)
    state = sample_initial_state(key, [10e-3, 12e-3], CONFIG, dim=3, n_particles=20)
    assert state.position.shape == (20, 3)
    v0 = jax.random.uniform(key, (20, 3), minval=-0.5, maxval=0.5)
    x = np.asarray(simulate(state.position, v0, state.radius, CONFIG, n_frames=100, save_every=2))
    assert np.all(np.abs(x) <= (L - np.asarray(state.radius))[None, :, None] * (1 + 1e-6))
    assert np.mean(x[-1, :, 2]) < np.mean(x[0, :, 2])  # gravity acts along the last axis


def test_initial_state_follows_the_protocol():
    radii = [2.0e-3, 3.5e-3, 5.0e-3]
    state = sample_initial_state(jax.random.PRNGKey(11), radii, CONFIG)
    again = sample_initial_state(jax.random.PRNGKey(11), radii, CONFIG)
    np.testing.assert_array_equal(np.asarray(state.position), np.asarray(again.position))
    x, a, v = np.asarray(state.position), np.asarray(state.radius), np.asarray(state.velocity)
    low, high = particle_count_range(state.start_height, max(radii), CONFIG)
    assert low <= len(a) <= high and -0.25 * L <= state.start_height <= 0
    assert set(np.round(a * 1e4).astype(int)) <= {20, 35, 50}
    assert np.all(x[:, 0] >= -L + a - 1e-7) and np.all(x[:, 0] <= L - a + 1e-7)
    assert np.all(x[:, 1] >= state.start_height + a - 1e-7) and np.all(x[:, 1] <= L - a + 1e-7)
    gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) - (a[:, None] + a[None]) + 2 * np.eye(len(a))
    assert gaps.min() >= -1e-7
    assert np.all(v == v[0])
    vs = CONFIG.settling_speed(min(radii))
    assert abs(v[0, 0]) <= vs and abs(v[0, 1]) <= vs / 4


def test_impossible_packing_raises_a_clear_error():
    with pytest.raises(PlacementError, match="too dense"):
        sample_initial_state(jax.random.PRNGKey(0), [9e-3], CONFIG, n_particles=200, max_rounds=4)


def test_non_finite_padding_rows_never_reach_real_particles():
    state = sample_initial_state(jax.random.PRNGKey(5), [8e-3, 10e-3], CONFIG, n_particles=12)
    mask = jnp.arange(14) < 12
    pad = lambda arr, value: jnp.concatenate([arr, jnp.full((2,) + arr.shape[1:], value, arr.dtype)])
    alone = np.asarray(simulate(state.position, state.velocity, state.radius, CONFIG, n_frames=10))
    padded = simulate(
        pad(state.position, jnp.nan),
        pad(state.velocity, jnp.inf),
        pad(state.radius, jnp.nan),
        CONFIG,
        n_frames=10,
        mask=mask,
    )
    np.testing.assert_array_equal(np.asarray(padded)[:, :12], alone)


def test_collision_capacity_must_be_positive():
    x0, v0, radius = row_hitting_the_floor()
    for bad in (0, -3, 1.5, "many"):
        with pytest.raises(ValueError, match="collision_capacity"):
            simulate(x0, v0, radius, CONFIG, n_frames=3, collision_capacity=bad)


def test_traced_overflow_poisons_only_frames_from_the_overflow_on():
    # Two particles falling side by side reach the floor in the same step, a few frames in.
    x0 = np.array([[-0.05, -L + 0.02], [0.05, -L + 0.02]])
    v0 = np.tile([0.0, -1.0], (2, 1))
    radius = np.full(2, 5e-3)
    run = np.asarray(
        jax.jit(lambda x, v, a: simulate_scan(x, v, a, CONFIG, n_frames=30, collision_capacity=1).position)(
            x0, v0, radius
        )
    )
    exact = np.asarray(simulate(x0, v0, radius, CONFIG, n_frames=30, collision_capacity=None))
    finite = np.isfinite(run).all(axis=(1, 2))
    first_bad = int(np.argmin(finite))
    assert 1 < first_bad < 30 and not finite[first_bad:].any()
    np.testing.assert_allclose(run[:first_bad], exact[:first_bad], rtol=0, atol=1e-9)


def test_numpy_scalars_are_accepted_as_plain_floats():
    config = PhysicsConfig(dt=np.float32(1e-4), cutoff=np.float64(0.02), drag=np.int64(2))
    assert type(config.dt) is float and type(config.cutoff) is float and type(config.drag) is float
    assert PhysicsConfig.from_dict(config.to_dict()) == config
