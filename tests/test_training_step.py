"""Noise, targets, normalisation, batches, the jitted step, and overfitting a tiny dataset."""

import dataclasses
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax
from jax.flatten_util import ravel_pytree

from dispgns.graph import GraphCapacity
from dispgns.model import ModelConfig
from dispgns.training import (
    TrainConfig,
    compute_normalization,
    create_train_state,
    learning_rate_schedule,
    loss_fn,
    random_walk_noise,
    target_acceleration,
    train_step,
)
from dispgns.training.batches import BatchStream, example_index
from dispgns.training.step import train_step_checked

TINY = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2)
# One training configuration and graph capacity for the tests that run steps (one compilation).
FIT = TrainConfig(noise_std=0.0, learning_rate=3e-3, min_learning_rate=3e-4, lr_decay_steps=400)
CAPACITY = GraphCapacity(192)


def _trajectory(seed, n=10, frames=14):
    """Smooth deterministic motion of ``n`` particles on a jittered grid (normalised units)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * 0.13 - 0.3
    x0 = grid + rng.uniform(-0.02, 0.02, (n, 2))
    v0 = rng.uniform(-2e-3, 2e-3, (n, 2))
    phase = rng.uniform(0, 2 * np.pi, (n, 2))
    t = np.arange(frames)[:, None, None]
    position = x0 + v0 * t + 4e-3 * np.sin(0.4 * t + phase)
    radius = rng.choice([0.03, 0.04, 0.05], n)
    return SimpleNamespace(position=position.astype(np.float32), radius=radius.astype(np.float32))


@pytest.fixture(scope="module")
def trajectories():
    return [_trajectory(0), _trajectory(1, n=8)]


def test_random_walk_noise_statistics():
    x = jnp.zeros((6, 4000, 2))
    noise = random_walk_noise(jax.random.key(0), x, 5e-4, mask=jnp.arange(4000) < 3000)
    np.testing.assert_array_equal(np.asarray(noise[0]), 0.0)
    np.testing.assert_array_equal(np.asarray(noise[:, 3000:]), 0.0)
    velocity_noise = np.diff(np.asarray(noise[:, :3000]), axis=0)
    # Each velocity step adds noise_std / sqrt(C - 1): the last velocity carries noise_std.
    assert abs(velocity_noise[-1].std() / 5e-4 - 1) < 0.05
    assert abs(velocity_noise[0].std() / (5e-4 / np.sqrt(5)) - 1) < 0.05


def test_target_is_the_noise_corrected_acceleration():
    rng = np.random.default_rng(0)
    clean = rng.normal(size=(7, 5, 2))
    with jax.enable_x64(True):
        noise = np.asarray(random_walk_noise(jax.random.key(1), jnp.asarray(clean[:6]), 0.1))
        noisy = clean[:6] + noise
        got = np.asarray(target_acceleration(jnp.asarray(clean[6]), jnp.asarray(clean[5]), jnp.asarray(noisy)))
    assert noise.dtype == np.float64
    paper = ((clean[6] + noise[-1]) - noisy[-1]) - (noisy[-1] - noisy[-2])
    np.testing.assert_allclose(got, paper, atol=1e-12)


def test_normalization_statistics(trajectories):
    stats = compute_normalization(trajectories, noise_std=0.0)
    v = np.concatenate([(np.diff(t.position, axis=0) / t.radius[None, :, None]).reshape(-1, 2) for t in trajectories])
    acc = np.concatenate(
        [(np.diff(t.position, 2, axis=0) / t.radius[None, :, None]).reshape(-1, 2) for t in trajectories]
    )
    np.testing.assert_allclose(stats["velocity_mean"], v.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(stats["velocity_std"], v.std(0), rtol=1e-4)
    np.testing.assert_allclose(stats["acceleration_std"], acc.std(0), rtol=1e-4)
    noisy = compute_normalization(trajectories, noise_std=1e-3)
    inv_a2 = np.mean(np.concatenate([1 / t.radius**2 for t in trajectories for _ in range(t.position.shape[0])]))
    np.testing.assert_allclose(
        noisy["acceleration_std"] ** 2, stats["acceleration_std"] ** 2 + 1e-6 * inv_a2, rtol=1e-4
    )


def test_learning_rate_schedule_has_a_floor():
    lr = learning_rate_schedule(TrainConfig())
    np.testing.assert_allclose(float(lr(0)), 1e-4, rtol=1e-6)
    np.testing.assert_allclose(float(lr(200_000)), 1e-5, rtol=1e-5)
    np.testing.assert_allclose(float(lr(2_000_000)), 1e-6, rtol=1e-6)
    assert TrainConfig.from_dict(TrainConfig(noise_std=1e-3).to_dict()) == TrainConfig(noise_std=1e-3)
    with pytest.raises(ValueError):
        TrainConfig(min_learning_rate=1.0)


def test_batches_are_deterministic_resumable_and_padded(trajectories):
    assert len(example_index([14, 9], 7)) == 8 + 3
    make = lambda seed: BatchStream(
        trajectories, input_sequence_length=6, batch_size=3, connectivity_radius=0.2, seed=seed
    )
    stream = make(0)
    assert stream.num_examples == 2 * 8 and stream.batches_per_epoch == 5
    first = [next(stream) for _ in range(7)]
    state = stream.state_dict()
    later = [next(stream) for _ in range(3)]
    resumed = make(0)
    resumed.load_state_dict(state)
    for a, b in zip(later, [next(resumed) for _ in range(3)]):
        np.testing.assert_array_equal(a.example, b.example)
        np.testing.assert_array_equal(a.position, b.position)
    # One epoch draws distinct examples; another seed gives another order.
    ids = np.concatenate([stream.batch_examples(i) for i in range(stream.batches_per_epoch)])
    assert len(set(ids.tolist())) == len(ids)
    assert not np.array_equal(make(1).batch_examples(0), stream.batch_examples(0))
    b = first[0]
    assert b.position.shape == (3, 7, 16, 2) and b.mask.shape == (3, 16)
    for k, (t, s) in enumerate(b.example):
        n = trajectories[t].position.shape[1]
        np.testing.assert_array_equal(b.position[k, :, :n], trajectories[t].position[s : s + 7])
        assert b.mask[k].sum() == n and np.all(b.position[k, :, n:] == 0)
        assert b.capacity.edges >= stream.pairs[stream.batch_examples(0)].max()


def test_early_windows_are_drawn_early_repeats_times_per_epoch(trajectories):
    index = example_index([14, 9], 7, early_windows=2, early_repeats=3)
    assert len(index) == (8 + 2 * 2) + (3 + 2 * 2)
    for k, m in [(0, 8), (1, 3)]:
        starts = np.sort(index.start[index.trajectory == k])
        np.testing.assert_array_equal(starts, np.sort(np.r_[np.arange(m), [0, 0, 1, 1]]))
    # More early windows than a trajectory has: each of its windows is repeated, no more.
    assert len(example_index([9], 7, early_windows=10, early_repeats=2)) == 3 * 2
    for got, want in zip(example_index([14], 7, early_windows=5, early_repeats=1), example_index([14], 7)):
        np.testing.assert_array_equal(got, want)
    for bad in [dict(early_windows=-1), dict(early_repeats=0), dict(early_windows=1.5)]:
        with pytest.raises(ValueError, match="early"):
            example_index([14], 7, **bad)
    config = TrainConfig(batch_size=3, early_windows=2, early_repeats=4, seed=5)
    stream = BatchStream.for_training(trajectories, TINY, config)
    plain = BatchStream.for_training(trajectories, TINY, dataclasses.replace(config, early_windows=0))
    assert stream.num_examples == plain.num_examples + 2 * 2 * 3
    # An epoch draws every copy but the num_examples % B it leaves over: the windows starting at frames 0 and 1
    # four times each per trajectory, frame 2 once.
    epoch = np.concatenate([stream.batch_examples(i) for i in range(stream.batches_per_epoch)])
    left_over = stream.epoch_order(0)[len(epoch) :]
    assert len(left_over) == stream.num_examples % 3
    for frame, copies in [(0, 4), (1, 4), (2, 1)]:
        drawn = (stream.index.start[epoch] == frame).sum()
        assert copies * 2 - (stream.index.start[left_over] == frame).sum() == drawn
    # A copy is a window like any other: a batch of the early ids (originals and copies) holds the trajectory's frames
    # at their starts.
    early = np.flatnonzero(stream.index.start < 2)
    assert len(early) == 2 * 2 * 4
    for part in np.array_split(early, 6):
        b = stream.make_batch(part)
        for k, (t, s) in enumerate(b.example):
            n = trajectories[t].position.shape[1]
            np.testing.assert_array_equal(b.position[k, :, :n], trajectories[t].position[s : s + 7])
    with pytest.raises(ValueError, match="early_repeats"):
        TrainConfig(early_repeats=0)
    with pytest.raises(ValueError, match="early_windows"):
        TrainConfig(early_windows=-1)


def test_train_step_skips_on_overflow_and_checked_step_grows(trajectories):
    stream = BatchStream(trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2)
    first = stream.batch(0)
    assert first.capacity.edges >= stream.pairs.max() and stream.grow(first).capacity.edges > first.capacity.edges
    state = create_train_state(jax.random.key(0), TINY, FIT, compute_normalization(trajectories))
    batch = stream.batch(0).with_capacity(GraphCapacity(8))
    new, metrics = train_step(state, batch, jax.random.key(3))
    assert bool(metrics["overflow"]) and int(new.step) == 0
    assert all(
        np.array_equal(x, y)
        for x, y in zip(jax.tree_util.tree_leaves(new.params), jax.tree_util.tree_leaves(state.params))
    )
    new, metrics, used = train_step_checked(state, batch, jax.random.key(3))
    assert not bool(metrics["overflow"]) and int(new.step) == 1 and used.capacity.edges > 8
    assert np.isfinite(float(metrics["loss"])) and np.isfinite(float(metrics["grad_norm"]))


def test_tiny_model_overfits_a_tiny_dataset(trajectories):
    tc = FIT
    stream = BatchStream(trajectories[:1], input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=1)
    assert stream.pairs.max() < CAPACITY.edges
    state = create_train_state(jax.random.key(0), TINY, tc, compute_normalization(trajectories[:1]))
    everything = stream.make_batch(np.arange(stream.num_examples)).with_capacity(CAPACITY)
    evaluate = jax.jit(lambda p, b: loss_fn(p["network"], p["normalization"], b, jax.random.key(0), TINY, tc)[0])
    before = float(evaluate(state.params, everything))
    for i in range(600):
        batch = stream.batch(i).with_capacity(CAPACITY)
        state, metrics = train_step(state, batch, jax.random.fold_in(jax.random.key(1), i))
    after = float(evaluate(state.params, everything))
    assert int(state.step) == 600 and not bool(metrics["overflow"])
    assert after < before / 100, (before, after)


def test_pushforward_and_unstandardised_recipe(trajectories):
    tc = TrainConfig(pushforward_steps=2, standardize=False)
    state = create_train_state(jax.random.key(0), TINY, tc)
    np.testing.assert_array_equal(np.asarray(state.params["normalization"]["velocity_std"]), 1.0)
    stream = BatchStream(
        trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, pushforward_steps=2
    )
    batch = stream.batch(0)
    assert batch.position.shape[1] == 9
    new, metrics = train_step(state, batch, jax.random.key(0))
    assert int(new.step) == 1 and np.isfinite(float(metrics["loss"]))
    with pytest.raises(ValueError, match="frames"):
        train_step(
            create_train_state(jax.random.key(0), TINY, TrainConfig(standardize=False)), batch, jax.random.key(0)
        )
    with pytest.raises(ValueError, match="standardize"):
        create_train_state(jax.random.key(0), TINY, TrainConfig())


def test_compacted_batches_train_exactly_like_padded_ones(trajectories):
    kwargs = dict(input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=3, pushforward_steps=1)
    compact = BatchStream(trajectories, **kwargs)
    padded = BatchStream(trajectories, compact_edges=False, **kwargs)
    tc = TrainConfig(pushforward_steps=1, learning_rate=1e-3)
    state = create_train_state(jax.random.key(0), TINY, tc, compute_normalization(trajectories))
    a, b = compact.batch(4), padded.batch(4)
    np.testing.assert_array_equal(a.example, b.example)
    real = sum(int(compact.pairs[i]) for i in compact.batch_examples(4)) + 2 * a.node_budget
    assert a.edge_budget is not None and b.edge_budget is None
    assert real <= a.edge_budget < 2 * (a.capacity.edges + a.node_budget)
    new_a, metrics_a = train_step(state, a, jax.random.key(5))
    new_b, metrics_b = train_step(state, b, jax.random.key(5))
    assert not bool(metrics_a["overflow"]) and not bool(metrics_b["overflow"])
    np.testing.assert_allclose(float(metrics_a["loss"]), float(metrics_b["loss"]), rtol=1e-5)
    for x, y in zip(jax.tree_util.tree_leaves(new_a.params), jax.tree_util.tree_leaves(new_b.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-6)
    # Too small a budget: the step refuses, the checked step grows the budget and gets the same result.
    tight = a.with_capacity(a.capacity, 64)
    _, metrics = train_step(state, tight, jax.random.key(5))
    assert bool(metrics["overflow"])
    grown, metrics, used = train_step_checked(state, tight, jax.random.key(5))
    assert used.edge_budget > 64 and not bool(metrics["overflow"])
    np.testing.assert_allclose(float(metrics["loss"]), float(metrics_a["loss"]), rtol=1e-5)


@pytest.mark.parametrize("batch_size", [2, 4])
def test_a_process_part_keeps_the_whole_batch_budgets(trajectories, batch_size):
    # Two processes of one device each: each holds half of every global batch, split over 2 devices in all. With a
    # batch of 2 a process's own examples leave one device's shard empty. Two node budgets (the fixture's
    # trajectories hold 8 and 10 particles) make a part's own budgets differ from the whole batch's.
    kwargs = dict(input_sequence_length=6, batch_size=batch_size, connectivity_radius=0.2, seed=3, shards=2)
    stream = BatchStream(trajectories, mirror=True, node_budgets=(8, 16), **kwargs)
    half = batch_size // 2
    own_budgets_differ = False
    for i in range(4):
        whole = stream.batch(i)
        ids = stream.batch_examples(i)
        for k in range(2):
            part = stream.batch(i, slice(k * half, (k + 1) * half))
            budgets = (part.capacity, part.edge_budget, part.node_budget)
            assert budgets == (whole.capacity, whole.edge_budget, whole.node_budget)
            own = stream.make_batch(ids[k * half : (k + 1) * half])
            own_budgets_differ |= (own.capacity, own.edge_budget, own.node_budget) != budgets
            n = own.node_budget
            np.testing.assert_array_equal(
                part.position[..., :n, :], whole.position[k * half : (k + 1) * half, ..., :n, :]
            )
            np.testing.assert_array_equal(part.example, whole.example[k * half : (k + 1) * half])
    assert own_budgets_differ  # the parts are made to the whole batch's budgets, not to their own


def test_mirror_augmentation_reflects_horizontal_axes_deterministically(trajectories):
    kwargs = dict(input_sequence_length=6, batch_size=4, connectivity_radius=0.2, seed=2)
    plain = BatchStream(trajectories, **kwargs)
    mirrored = BatchStream(trajectories, mirror=True, **kwargs)
    flipped_any = False
    for i in range(6):
        a, b = plain.batch(i), mirrored.batch(i)
        np.testing.assert_array_equal(a.example, b.example)
        np.testing.assert_array_equal(a.position[..., 1], b.position[..., 1])  # gravity axis untouched
        same = np.all(a.position[..., 0] == b.position[..., 0], axis=(1, 2))
        negated = np.all(a.position[..., 0] == -b.position[..., 0], axis=(1, 2))
        assert np.all(same | negated)
        flipped_any |= bool(np.any(negated & ~same))
        np.testing.assert_array_equal(b.position, BatchStream(trajectories, mirror=True, **kwargs).batch(i).position)
    assert flipped_any
    assert TrainConfig().mirror_augmentation is False
    with pytest.raises(ValueError, match="symmetric"):
        BatchStream(trajectories, mirror=True, bounds=((0.0, 1.0), (-1.0, 1.0)), **kwargs)


def test_non_finite_padding_rows_change_nothing(trajectories):
    stream = BatchStream(trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, shuffle=False)
    batch = next(stream.batch(i) for i in range(stream.batches_per_epoch) if not np.all(stream.batch(i).mask))
    batch = batch.with_capacity(CAPACITY)
    pad = ~np.asarray(batch.mask)[:, None, :, None]
    poisoned = batch.replace(position=jnp.where(pad, jnp.nan, batch.position))
    state = create_train_state(jax.random.key(0), TINY, FIT, compute_normalization(trajectories))
    clean, clean_metrics = train_step(state, batch, jax.random.key(3))
    dirty, dirty_metrics = train_step(state, poisoned, jax.random.key(3))
    assert float(dirty_metrics["loss"]) == float(clean_metrics["loss"])
    assert float(dirty_metrics["grad_norm"]) == float(clean_metrics["grad_norm"])
    for x, y in zip(jax.tree_util.tree_leaves(dirty.params), jax.tree_util.tree_leaves(clean.params)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_train_step_with_network_compiler_options_equals_it_nested_in_a_plain_jit(trajectories):
    # At top level the step compiles with dispgns.network_compiler_options; nested in
    # the caller's jit, with that jit's (none): another matmul kernel, the same step.
    stream = BatchStream(trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2)
    state = create_train_state(jax.random.key(0), TINY, FIT, compute_normalization(trajectories))
    batch = stream.batch(0).with_capacity(CAPACITY)
    tuned, tuned_metrics = train_step(state=state, batch=batch, key=jax.random.key(4))
    plain, plain_metrics = jax.jit(train_step)(state, batch, jax.random.key(4))
    np.testing.assert_allclose(float(tuned_metrics["loss"]), float(plain_metrics["loss"]), rtol=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(tuned.params), jax.tree_util.tree_leaves(plain.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


def test_weight_moving_average_follows_the_recursion_and_skips_overflowed_steps(trajectories):
    import dataclasses

    decay = 0.8
    tc = dataclasses.replace(FIT, ema_decay=decay)
    stream = BatchStream(trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=2)
    state = create_train_state(jax.random.key(0), TINY, tc, compute_normalization(trajectories))
    assert create_train_state(jax.random.key(0), TINY, FIT, compute_normalization(trajectories)).ema is None
    leaves = lambda tree: [np.asarray(x, np.float64) for x in jax.tree_util.tree_leaves(tree)]
    expected = leaves(state.params["network"])  # the average starts at the initial weights
    initial = state
    for i in range(4):
        state, _ = train_step(state, stream.batch(i).with_capacity(CAPACITY), jax.random.fold_in(jax.random.key(1), i))
        expected = [decay * e + (1 - decay) * p for e, p in zip(expected, leaves(state.params["network"]), strict=True)]
    for e, a in zip(expected, leaves(state.ema), strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-5, atol=1e-7)
    # It is what validation and export see, and it differs from the raw weights after training.
    assert state.eval_params["network"] is state.ema
    assert state.eval_params["normalization"] is state.params["normalization"]
    assert not all(np.allclose(a, b) for a, b in zip(leaves(state.ema), leaves(state.params["network"])))
    # A step that overflows changes neither the weights nor their average.
    skipped, metrics = train_step(state, stream.batch(4).with_capacity(GraphCapacity(8)), jax.random.key(3))
    assert bool(metrics["overflow"])
    for a, b in zip(leaves(skipped.ema), leaves(state.ema), strict=True):
        np.testing.assert_array_equal(a, b)
    # Fine-tuning: new weights restart the average at them; without an average there is none to restart.
    restarted = state.with_params(skipped.params)
    assert restarted.ema is not None
    for a, b in zip(leaves(restarted.ema), leaves(skipped.params["network"]), strict=True):
        np.testing.assert_array_equal(a, b)
    assert state.replace(ema=None).with_params(skipped.params).ema is None
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="ema_decay"):
            TrainConfig(ema_decay=bad)
    # The step with an average, jitted (as shipped) and traced op by op: the same weights and average.
    batch, key = stream.batch(0).with_capacity(CAPACITY), jax.random.key(5)
    jitted, _ = train_step(initial, batch, key)
    with jax.disable_jit():
        eager, _ = train_step(initial, batch, key)
    for a, b in zip(leaves((jitted.params, jitted.ema)), leaves((eager.params, eager.ema)), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def _manual_unrolled_loss(params, batch, pushforward, steps, frozen_windows=False):
    """The unrolled loss composed from the simulator's public steps (noise-free inputs).

    The window first moves on ``pushforward`` frames without gradient; then each of ``steps`` steps: the
    standardised network output against the noise-corrected target, and the window moves on by
    :func:`dispgns.simulator.predict_step_batch` (which evaluates the network again, independently of the loss).
    """
    from dispgns.simulator import build_graph, network_output_batch, predict_step_batch, sanitize

    c = TINY.input_sequence_length
    norm = params["normalization"]
    windows = jnp.asarray(batch.position[:, :c])
    advance = lambda w: (
        predict_step_batch(
            params, w, batch.radius, model_config=TINY, capacity=batch.capacity, mask=batch.mask
        ).position
    )
    for _ in range(pushforward):
        windows = jnp.concatenate([windows[:, 1:], lax.stop_gradient(advance(windows))[:, None]], axis=1)
    c += pushforward  # the first target frame
    total = 0.0
    for j in range(steps):
        x, a = jax.vmap(lambda w, r, m: sanitize(w, r, m, TINY))(windows, batch.radius, batch.mask)
        graphs = jax.vmap(lambda p, m: build_graph(p, m, batch.capacity, TINY))(x[:, -1], batch.mask)
        out = network_output_batch(params, x, a, graphs, model_config=TINY)
        target = jax.vmap(target_acceleration)(batch.position[:, c + j], batch.position[:, c + j - 1], windows)
        target = (target / a[..., None] - norm["acceleration_mean"]) / norm["acceleration_std"]
        total += jnp.sum(jnp.where(batch.mask, jnp.sum((out - target) ** 2, -1), 0.0))
        nxt = lax.stop_gradient(advance(windows)) if frozen_windows else advance(windows)
        windows = jnp.concatenate([windows[:, 1:], nxt[:, None]], axis=1)
    return total / (jnp.sum(batch.mask) * steps)


@pytest.fixture(scope="module")
def unrolled(trajectories):
    """A config unrolled over 3 steps after 1 pushforward step, its state after a few training steps (so the network
    is not near zero), a batch and the same batch padded to more particle slots."""
    tc = dataclasses.replace(FIT, pushforward_steps=1, unroll_steps=3)
    kwargs = dict(input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=4)
    kwargs.update(pushforward_steps=1, unroll_steps=3)
    stream = BatchStream(trajectories, node_budgets=(16,), **kwargs)
    state = create_train_state(jax.random.key(0), TINY, tc, compute_normalization(trajectories))
    for i in range(3):
        state, _ = train_step(state, stream.batch(i).with_capacity(CAPACITY), jax.random.key(i))
    padded = BatchStream(trajectories, node_budgets=(40,), **kwargs)
    return tc, state, stream.batch(7).with_capacity(CAPACITY), padded.batch(7).with_capacity(CAPACITY)


def test_unrolled_loss_backpropagates_through_the_models_own_rollout(unrolled):
    tc, state, batch, _ = unrolled
    assert batch.position.shape[1] == 6 + 1 + 3 and not np.all(batch.mask)
    params = state.params
    loss = lambda net: loss_fn(net, params["normalization"], batch, jax.random.key(0), TINY, tc)[0]
    manual = lambda net, frozen=False: _manual_unrolled_loss(
        {"network": net, "normalization": params["normalization"]}, batch, 1, 3, frozen
    )
    value, grads = jax.value_and_grad(loss)(params["network"])
    want, want_grads = jax.value_and_grad(manual)(params["network"])
    np.testing.assert_allclose(float(value), float(want), rtol=1e-5)
    flat, want_flat = ravel_pytree(grads)[0], ravel_pytree(want_grads)[0]
    np.testing.assert_allclose(
        np.asarray(flat), np.asarray(want_flat), rtol=1e-3, atol=1e-6 * float(jnp.abs(want_flat).max())
    )
    # The gradient through the predicted frames is part of it: stopping it there gives another gradient.
    stopped = ravel_pytree(jax.grad(lambda net: manual(net, True))(params["network"]))[0]
    gap = float(jnp.linalg.norm(stopped - want_flat) / jnp.linalg.norm(want_flat))
    assert gap > 0.05, gap
    # The step checks that the batch's windows hold the frames of the config's steps.
    with pytest.raises(ValueError, match=r"pushforward_steps \+ unroll_steps"):
        train_step(state.replace(train_config=FIT), batch, jax.random.key(0))


def test_unrolled_loss_jit_padding_and_configuration(trajectories, unrolled):
    tc, state, batch, padded = unrolled
    assert padded.position.shape[2] == 40 and batch.position.shape[2] == 16
    grad = lambda b, noise: jax.value_and_grad(loss_fn, has_aux=True)(
        state.params["network"],
        state.params["normalization"],
        b,
        jax.random.key(2),
        TINY,
        dataclasses.replace(tc, noise_std=noise),
    )
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-6 * np.abs(b).max())
    # Jitted and not, with training noise.
    (value, aux), grads = grad(batch, 3e-3)
    (jit_value, _), jit_grads = jax.jit(grad, static_argnums=1)(batch, 3e-3)
    flat = np.asarray(ravel_pytree(grads)[0])
    assert not bool(aux["overflow"]) and np.all(np.isfinite(flat))
    np.testing.assert_allclose(float(jit_value), float(value), rtol=1e-5)
    close(np.asarray(ravel_pytree(jit_grads)[0]), flat)
    # Padding to more particle slots changes nothing real (without noise: its draws follow the slot count).
    (value, _), grads = grad(batch, 0.0)
    (pad_value, pad_aux), pad_grads = grad(padded, 0.0)
    assert not bool(pad_aux["overflow"])
    np.testing.assert_allclose(float(pad_value), float(value), rtol=1e-5)
    close(np.asarray(ravel_pytree(pad_grads)[0]), np.asarray(ravel_pytree(grads)[0]))
    # A training step with it updates.
    new, metrics = train_step(state, batch, jax.random.key(2))
    assert int(new.step) == int(state.step) + 1 and np.isfinite(float(metrics["loss"]))
    with pytest.raises(ValueError, match="unroll_steps must be an integer >= 1"):
        TrainConfig(unroll_steps=0)
    with pytest.raises(ValueError, match="unroll_steps"):
        BatchStream(trajectories, input_sequence_length=6, batch_size=2, connectivity_radius=0.2, unroll_steps=0)


def _manual_position_loss(params, batch, pushforward, steps, noise_std=0.0, key=None):
    """The position form of the unrolled loss composed from the simulator's public steps.

    The inputs get the training noise as the loss draws it (one key per example, split from ``key``); the window
    then moves on ``pushforward`` frames without gradient; then each of ``steps`` frames of
    :func:`dispgns.simulator.predict_step_batch` (gradient through them) is compared with the true frame shifted
    by the pushforward's error of the unroll's first window, over the radius and the acceleration std.
    """
    from dispgns.simulator import predict_step_batch

    c = TINY.input_sequence_length
    std = params["normalization"]["acceleration_std"]
    advance = lambda w: (
        predict_step_batch(
            params, w, batch.radius, model_config=TINY, capacity=batch.capacity, mask=batch.mask
        ).position
    )
    windows = jnp.asarray(batch.position[:, :c])
    if noise_std:
        keys = jax.random.split(key, windows.shape[0])
        windows += jax.vmap(lambda k, w, m: random_walk_noise(k, w, noise_std, m))(keys, windows, batch.mask)
    for _ in range(pushforward):
        windows = jnp.concatenate([windows[:, 1:], lax.stop_gradient(advance(windows))[:, None]], axis=1)
    c += pushforward
    offset = windows[:, -1] - batch.position[:, c - 1]
    total = 0.0
    for j in range(steps):
        nxt = advance(windows)
        error = (nxt - batch.position[:, c + j] - offset) / (batch.radius[..., None] * std)
        total += jnp.sum(jnp.where(batch.mask, jnp.sum(error**2, -1), 0.0))
        windows = jnp.concatenate([windows[:, 1:], nxt[:, None]], axis=1)
    return total / (jnp.sum(batch.mask) * steps)


def test_unrolled_position_loss(trajectories, unrolled):
    tc, state, batch, padded = unrolled
    tc = dataclasses.replace(tc, unroll_loss="position")
    params = state.params
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-6 * np.abs(b).max())
    flat = lambda tree: np.asarray(ravel_pytree(tree)[0])

    def grad(b, config, noise=0.0):
        config = dataclasses.replace(config, noise_std=noise)
        return jax.value_and_grad(loss_fn, has_aux=True)(
            params["network"], params["normalization"], b, jax.random.key(2), TINY, config
        )

    # The unrolled positions against the true ones, composed from the public steps, with the training noise (its
    # corruption of the inputs is kept in the targets): value and gradient.
    (value, aux), grads = grad(batch, tc)
    (noisy, noisy_aux), noisy_grads = grad(batch, tc, 3e-3)
    want, want_grads = jax.value_and_grad(
        lambda net: _manual_position_loss(
            {"network": net, "normalization": params["normalization"]}, batch, 1, 3, 3e-3, jax.random.key(2)
        )
    )(params["network"])
    assert not bool(aux["overflow"]) and not bool(noisy_aux["overflow"])
    np.testing.assert_allclose(float(noisy), float(want), rtol=1e-5)
    close(flat(noisy_grads), flat(want_grads))
    # The reference itself: with another noise draw it differs (the comparison above sees the noise).
    other = _manual_position_loss(params, batch, 1, 3, 3e-3, jax.random.key(3))
    assert abs(float(other) - float(want)) > 1e-3 * float(want), (float(other), float(want))
    # It is another loss than the acceleration form: the errors carried in count again.
    (accel, _), accel_grads = grad(batch, dataclasses.replace(tc, unroll_loss="acceleration"))
    assert float(value) > 1.2 * float(accel), (float(value), float(accel))
    gap = np.linalg.norm(flat(grads) - flat(accel_grads)) / np.linalg.norm(flat(accel_grads))
    assert gap > 0.05, gap
    # Jitted and not, with training noise; padding to more particle slots changes nothing real.
    (jit_noisy, _), jit_grads = jax.jit(grad, static_argnums=(1, 2))(batch, tc, 3e-3)
    assert np.all(np.isfinite(flat(noisy_grads)))
    np.testing.assert_allclose(float(jit_noisy), float(noisy), rtol=1e-5)
    close(flat(jit_grads), flat(noisy_grads))
    (pad_value, pad_aux), pad_grads = grad(padded, tc)
    assert not bool(pad_aux["overflow"])
    np.testing.assert_allclose(float(pad_value), float(value), rtol=1e-5)
    close(flat(pad_grads), flat(grads))
    # One unrolled step: both forms are the one-step loss, with noise and a pushforward frame in the inputs.
    one = dict(input_sequence_length=6, batch_size=2, connectivity_radius=0.2, seed=4, pushforward_steps=1)
    single = BatchStream(trajectories, node_budgets=(16,), **one).batch(3).with_capacity(CAPACITY)
    one_step = dataclasses.replace(tc, unroll_steps=1)
    (by_position, _), position_grads = grad(single, one_step, 3e-3)
    (by_acceleration, _), acceleration_grads = grad(
        single, dataclasses.replace(one_step, unroll_loss="acceleration"), 3e-3
    )
    np.testing.assert_allclose(float(by_position), float(by_acceleration), rtol=1e-4)
    close(flat(position_grads), flat(acceleration_grads))
    # A training step with it (tc's noise is 0) reports this loss and updates; an unknown form is refused.
    new, metrics = train_step(state.replace(train_config=tc), batch, jax.random.key(2))
    assert int(new.step) == int(state.step) + 1
    np.testing.assert_allclose(float(metrics["loss"]), float(value), rtol=1e-5)
    with pytest.raises(ValueError, match=r"TrainConfig.unroll_loss must be one of \[.acceleration., .position.\]"):
        TrainConfig(unroll_loss="velocity")
