"""One-step predictions and rollouts: loops, vmap, overflow handling, gradients."""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import simulator
from dispgns.graph import GraphCapacity
from dispgns.model import ModelConfig, init_params
from dispgns.simulator import (
    fit_capacity,
    predict_acceleration,
    predict_position,
    predict_step,
    rollout,
    rollout_batch,
    rollout_scan,
    steps_until_overflow,
)

DATA = Path(__file__).parent / "data" / "features.npz"
TINY = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2)
N = 40
STEPS = 12
CAP = GraphCapacity(512)


@pytest.fixture(scope="module")
def inputs():
    with np.load(DATA) as d:
        return jnp.asarray(d["positions"][:, :N], jnp.float32), jnp.asarray(d["radius"][:N], jnp.float32)


@pytest.fixture(scope="module")
def params():
    # Small accelerations keep the untrained rollouts tame (no chaotic amplification).
    norm = {
        "velocity_mean": jnp.zeros(2),
        "velocity_std": jnp.full((2,), 0.05),
        "acceleration_mean": jnp.zeros(2),
        "acceleration_std": jnp.full((2,), 0.002),
    }
    return init_params(jax.random.key(1), TINY, norm)


def test_predict_position_is_the_euler_update(params, inputs):
    x, a = inputs
    acc = predict_acceleration(params, x, a, model_config=TINY, capacity=CAP)
    nxt = predict_position(params, x, a, model_config=TINY, capacity=CAP)
    np.testing.assert_allclose(np.asarray(nxt), np.asarray(x[-1] + (x[-1] - x[-2]) + acc), atol=1e-7)
    assert float(jnp.max(jnp.abs(acc))) > 0


def test_rollout_equals_a_loop_of_predict_position(params, inputs):
    x, a = inputs
    out = rollout(params, x, a, STEPS, model_config=TINY, capacity=CAP, chunk_size=5)
    assert out.shape == (STEPS, N, 2)
    window, expected = x, []
    for _ in range(STEPS):
        nxt = predict_position(params, window, a, model_config=TINY, capacity=CAP)
        expected.append(nxt)
        window = jnp.concatenate([window[1:], nxt[None]])
    np.testing.assert_allclose(np.asarray(out), np.asarray(jnp.stack(expected)), rtol=0, atol=2e-6)


def test_overflow_is_caught_and_recomputed(params, inputs):
    x, a = inputs
    big = rollout(params, x, a, STEPS, model_config=TINY, capacity=CAP, chunk_size=5)
    small = rollout(params, x, a, STEPS, model_config=TINY, capacity=GraphCapacity(16), chunk_size=5)
    assert np.all(np.isfinite(np.asarray(small)))
    np.testing.assert_allclose(np.asarray(small), np.asarray(big), rtol=0, atol=2e-6)
    # One step too: a too-small capacity is grown, never truncated.
    np.testing.assert_allclose(
        np.asarray(predict_position(params, x, a, model_config=TINY, capacity=16)),
        np.asarray(big[0]),
        rtol=0,
        atol=2e-6,
    )


def test_a_chunk_stops_at_its_first_overflowing_step(params, inputs):
    x, a = inputs
    window, expected = x, []
    for _ in range(4):
        expected.append(predict_position(params, window, a, model_config=TINY, capacity=CAP))
        window = jnp.concatenate([window[1:], expected[-1][None]])

    @functools.partial(jax.jit, static_argnums=(1,))
    def run(limit, capacity):
        def step(w):
            out = predict_step(params, w, a, model_config=TINY, capacity=capacity)
            return out.position, out.overflow

        return steps_until_overflow(step, x, jnp.int32(limit), length=6, axis=0)

    window, positions, taken, overflow = run(4, CAP)
    assert int(taken) == 4 and not bool(overflow)
    np.testing.assert_allclose(np.asarray(positions[:4]), np.asarray(jnp.stack(expected)), rtol=0, atol=2e-6)
    np.testing.assert_array_equal(np.asarray(positions[4:]), 0.0)
    np.testing.assert_array_equal(np.asarray(window), np.asarray(jnp.concatenate([x[4:], positions[:4]])))
    _, _, taken, overflow = run(4, GraphCapacity(16))
    assert int(taken) == 1 and bool(overflow)


def _counting_step(window, capacity, axis):
    """Stand-in step: the next frame is the last one + 1; it overflows where the last frame is >= capacity."""
    last = jnp.take(window, window.shape[axis] - 1, axis=axis)
    return last + 1.0, jnp.max(last) >= capacity


@pytest.mark.parametrize("axis", [0, 1])
def test_the_step_loop_stops_mid_chunk_at_an_overflow(axis):
    window = jnp.moveaxis(jnp.broadcast_to(jnp.arange(3.0)[:, None, None, None], (3, 2, 1, 1)), 0, axis)
    if axis == 0:
        window = window[:, 0]
    run = jax.jit(
        lambda w, limit, cap: steps_until_overflow(
            lambda w: _counting_step(w, cap, axis), w, limit, length=8, axis=axis
        )
    )
    new_window, positions, taken, overflow = run(window, jnp.int32(8), 5.0)
    # Frames 3, 4, 5 are fine; the step from frame 5 overflows (and is the last one taken).
    assert int(taken) == 4 and bool(overflow)
    np.testing.assert_array_equal(np.asarray(positions)[:4].reshape(4, -1)[:, 0], [3.0, 4.0, 5.0, 6.0])
    np.testing.assert_array_equal(np.asarray(positions)[4:], 0.0)
    # The window to go on from is the one before the overflowing step: frames 3, 4, 5.
    np.testing.assert_array_equal(np.asarray(jnp.moveaxis(new_window, axis, 0)).reshape(3, -1)[:, 0], [3.0, 4.0, 5.0])
    # A limit above the static length is clamped instead of overwriting the last row.
    _, positions, taken, overflow = run(window, jnp.int32(50), 100.0)
    assert int(taken) == 8 and not bool(overflow)
    np.testing.assert_array_equal(np.asarray(positions).reshape(8, -1)[:, 0], np.arange(3.0, 11.0))


def attempts_of(monkeypatch):
    """Every attempt the simulator's host driver makes: ``(capacity, steps kept, overflow)``."""
    seen = []
    original = simulator.drive

    def spy(run, state, capacity, grow, **kwargs):
        def recorded(state, capacity, remaining):
            attempt = run(state, capacity, remaining)
            seen.append((capacity, attempt.done, attempt.overflow))
            return attempt

        return original(recorded, state, capacity, grow, **kwargs)

    monkeypatch.setattr(simulator, "drive", spy)
    return seen


@pytest.mark.parametrize("batched", [False, True])
def test_the_host_loop_redoes_only_the_overflowing_steps(params, inputs, monkeypatch, batched):
    x, a = inputs
    seen = attempts_of(monkeypatch)
    if batched:
        small = rollout_batch(params, x[None], a[None], STEPS, model_config=TINY, capacity=16, chunk_size=5)[0]
    else:
        small = rollout(params, x, a, STEPS, model_config=TINY, capacity=16, chunk_size=5)
    growths = sum(overflow for _, _, overflow in seen)
    assert growths >= 1, "the capacity never overflowed: the test lost its purpose"
    # No step is kept twice: every overflow costs one recomputed step, not a chunk.
    assert sum(done for _, done, _ in seen) == STEPS
    capacities = [capacity.edges for capacity, _, _ in seen]
    assert capacities == sorted(capacities) and capacities[0] == 16
    big = rollout(params, x, a, STEPS, model_config=TINY, capacity=CAP, chunk_size=5)
    np.testing.assert_allclose(np.asarray(small), np.asarray(big), rtol=0, atol=2e-6)


def test_pure_cores_flag_an_overflow_and_poison_with_nan(params, inputs):
    x, a = inputs
    positions, overflow = jax.jit(lambda p, x: rollout_scan(p, x, a, 3, model_config=TINY, capacity=GraphCapacity(16)))(
        params, x
    )
    assert np.all(np.isnan(np.asarray(positions))) and np.all(np.asarray(overflow))
    step = jax.jit(lambda p, x: predict_step(p, x, a, model_config=TINY, capacity=16))(params, x)
    assert bool(step.overflow) and np.all(np.isnan(np.asarray(step.acceleration)))
    ok = jax.jit(lambda p, x: predict_step(p, x, a, model_config=TINY, capacity=CAP))(params, x)
    assert not bool(ok.overflow) and np.all(np.isfinite(np.asarray(ok.position)))
    with pytest.raises(ValueError, match="needs a graph capacity"):
        rollout_scan(params, x, a, 3, model_config=TINY, capacity=None)


def test_host_conveniences_name_the_pure_core_under_a_transformation(params, inputs):
    x, a = inputs
    with pytest.raises(ValueError, match="rollout_scan"):
        jax.jit(lambda p, x: rollout(p, x, a, 3, model_config=TINY))(params, x)
    with pytest.raises(ValueError, match="predict_step"):
        jax.jit(lambda x: predict_position(params, x, a, model_config=TINY))(x)


def test_vmap_over_padded_trajectories_equals_loop(params, inputs):
    x, a = inputs
    sizes = (N, N - 11)
    second = x[:, 5 : 5 + sizes[1]] * jnp.array([-1.0, 1.0])  # another configuration (mirrored)
    xs = jnp.stack([x, jnp.pad(second, ((0, 0), (0, N - sizes[1]), (0, 0)))])
    radii = jnp.stack([a, jnp.pad(a[5 : 5 + sizes[1]], (0, N - sizes[1]))])
    masks = jnp.stack([jnp.ones(N, bool), jnp.arange(N) < sizes[1]])
    scan = lambda x, r, m: rollout_scan(params, x, r, STEPS, model_config=TINY, mask=m, capacity=CAP)
    batched, overflow = jax.jit(jax.vmap(scan))(xs, radii, masks)
    assert not np.any(np.asarray(overflow))
    for k, n in enumerate(sizes):
        single = rollout(params, xs[k, :, :n], radii[k, :n], STEPS, model_config=TINY, capacity=CAP, chunk_size=5)
        np.testing.assert_allclose(np.asarray(batched[k, :, :n]), np.asarray(single), rtol=0, atol=2e-6)
    # Padding particles stay where they were.
    np.testing.assert_array_equal(
        np.asarray(batched[1, :, sizes[1] :]),
        np.broadcast_to(np.asarray(xs[1, -1, sizes[1] :]), (STEPS, N - sizes[1], 2)),
    )


def test_rollout_batch_equals_single_rollouts_and_survives_overflow(params, inputs):
    x, a = inputs
    sizes = (N, N - 11)
    second = x[:, 5 : 5 + sizes[1]] * jnp.array([-1.0, 1.0])
    xs = jnp.stack([x, jnp.pad(second, ((0, 0), (0, N - sizes[1]), (0, 0)))])
    radii = jnp.stack([a, jnp.pad(a[5 : 5 + sizes[1]], (0, N - sizes[1]), constant_values=1.0)])
    masks = np.stack([np.ones(N, bool), np.arange(N) < sizes[1]])
    done = []
    batched = rollout_batch(params, xs, radii, STEPS, model_config=TINY, mask=masks, chunk_size=5, progress=done.append)
    # Too small a capacity at first: overflow, growth, recomputation, same answer.
    small = rollout_batch(
        params, xs, radii, STEPS, model_config=TINY, mask=masks, capacity=GraphCapacity(16), chunk_size=5
    )
    assert batched.shape == (2, STEPS, N, 2) and done[-1] == STEPS
    np.testing.assert_allclose(np.asarray(small), np.asarray(batched), rtol=0, atol=1e-6)
    for k, n in enumerate(sizes):
        single = rollout(params, xs[k, :, :n], radii[k, :n], STEPS, model_config=TINY, capacity=CAP, chunk_size=5)
        np.testing.assert_allclose(np.asarray(batched[k, :, :n]), np.asarray(single), rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="shape"):
        rollout_batch(params, xs[0], radii[0], 2, model_config=TINY)


def test_rollout_is_differentiable(params, inputs):
    x, a = inputs
    target = x[-1] + 0.01

    def loss(p, radius):
        out, _ = rollout_scan(p, x, radius, 4, model_config=TINY, capacity=CAP)
        return jnp.mean((out[-1] - target) ** 2)

    g_params, g_radius = jax.jit(jax.grad(loss, argnums=(0, 1)))(params, a)
    leaves = jax.tree_util.tree_leaves(g_params["network"])
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)
    assert any(float(jnp.max(jnp.abs(leaf))) > 0 for leaf in leaves)
    assert np.all(np.isfinite(np.asarray(g_radius))) and float(jnp.max(jnp.abs(g_radius))) > 0
    # Normalisation statistics are data, not weights.
    assert all(float(jnp.max(jnp.abs(leaf))) == 0 for leaf in jax.tree_util.tree_leaves(g_params["normalization"]))


def test_bad_shapes_are_rejected(params, inputs):
    x, a = inputs
    with pytest.raises(ValueError, match="positions must have shape"):
        rollout(params, x[1:], a, 2, model_config=TINY)
    with pytest.raises(ValueError, match="radius must have shape"):
        predict_position(params, x, a[1:], model_config=TINY)
    with pytest.raises(ValueError, match="n_steps"):
        rollout(params, x, a, 0, model_config=TINY)


def test_keep_inside_box_projects_onto_the_walls(inputs):
    import dataclasses

    x, a = inputs
    # A model that pushes everything towards +x: without the constraint particles leave the box.
    norm = {
        "velocity_mean": jnp.zeros(2),
        "velocity_std": jnp.full((2,), 0.05),
        "acceleration_mean": jnp.array([0.5, 0.0]),
        "acceleration_std": jnp.full((2,), 1e-4),
    }
    free_config = TINY
    boxed_config = dataclasses.replace(TINY, keep_inside_box=True)
    params = init_params(jax.random.key(1), free_config, norm)
    free = np.asarray(rollout(params, x, a, 8, model_config=free_config, capacity=CAP))
    boxed = np.asarray(rollout(params, x, a, 8, model_config=boxed_config, capacity=CAP))
    limit = 1.0 - np.asarray(a)[None, :]
    assert np.any(free[..., 0] > limit + 1e-3)
    assert np.all(np.abs(boxed) <= limit[..., None] + 1e-6)
    # The first step is the free one, projected.
    np.testing.assert_allclose(boxed[0], np.clip(free[0], -limit[0][:, None], limit[0][:, None]), atol=1e-6)
    assert np.any(np.isclose(boxed[..., 0], limit, atol=1e-6))


def test_a_fitted_capacity_serves_the_pure_rollout_under_jit_also_with_the_cell_list():
    # N above the cell-list threshold: the fitted capacity uses the cell list.
    n = 170
    x0 = np.random.default_rng(0).uniform(-0.9, 0.9, (n, 2)).astype(np.float32)
    frames = np.stack([x0 + 1e-3 * k for k in range(6)])
    radius = np.full((n,), 0.03, np.float32)
    params = init_params(jax.random.key(0), TINY)
    host = rollout(params, frames, radius, 3, model_config=TINY)
    capacity = fit_capacity(frames[-1], TINY, margin=0.5)
    assert capacity.cell is not None and capacity.edges < n * (n - 1)
    run = jax.jit(lambda p: rollout_scan(p, frames, radius, 3, model_config=TINY, capacity=capacity))
    positions, overflow = run(params)
    assert not np.any(np.asarray(overflow))
    np.testing.assert_allclose(np.asarray(positions), np.asarray(host), rtol=0, atol=1e-6)
    assert f"{n * n}" not in run.lower(params).as_text()  # sized from the positions, not all N^2 slots


def test_bad_values_are_rejected(params, inputs):
    x, a = inputs
    with pytest.raises(ValueError, match="n_steps must be an integer"):
        rollout(params, x, a, 2.5, model_config=TINY)
    with pytest.raises(ValueError, match="radius must be finite and > 0"):
        rollout(params, x, a.at[3].set(0.0), 2, model_config=TINY)
    with pytest.raises(ValueError, match="no particles"):
        predict_position(params, x[:, :0], a[:0], model_config=TINY)
    # Padding radii may be anything.
    mask = jnp.arange(N) != 3
    predict_position(params, x, a.at[3].set(0.0), model_config=TINY, mask=mask, capacity=CAP)


def test_rollouts_of_other_trajectories_reuse_the_compiled_capacities(params, monkeypatch):
    """Data-sized capacities go on the ladder, so two trajectories with different pair counts share them."""
    from dispgns.graph import host_count_pairs

    with np.load(DATA) as d:  # all 150 particles: enough pairs for capacities a rung apart
        x, a = jnp.asarray(d["positions"], jnp.float32), jnp.asarray(d["radius"], jnp.float32)
    seen = attempts_of(monkeypatch)
    # The same packing squeezed by 3 %: 1,412 and 1,476 pairs, capacities 1,600 and 1,664 off the ladder.
    windows = [x, x * 0.97]
    pairs = [int(host_count_pairs(w[-1], connectivity_radius=TINY.connectivity_radius)) for w in windows]
    assert pairs[0] != pairs[1]
    capacities = []
    for w, count in zip(windows, pairs):
        seen.clear()
        rollout(params, w, a, 4, model_config=TINY)
        capacities.append(seen[0][0])
        assert seen[0][0].edges >= count * 1.1  # still the head-room asked for
    assert capacities[0] == capacities[1]
