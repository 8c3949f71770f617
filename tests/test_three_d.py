"""Three dimensions: the paper's features on spheres, the invariances of the 2-D tests, the floor symmetries.

The inputs are frames of the 3-D reference settling run (tests/data/sedimentation_3d.npz, 182
spheres in the 0.1 m cube), divided by L so that the box is [-1, 1]^3.
"""

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import PhysicsConfig, simulate
from dispgns import features as F
from dispgns import graph as G
from dispgns.graph import GraphCapacity
from dispgns.model import ModelConfig, init_params
from dispgns.simulator import predict_position, predict_step, rollout, rollout_scan
from dispgns.training import BatchStream, quarter_turns

DATA = Path(__file__).parent / "data" / "sedimentation_3d.npz"
TINY = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, dim=3)
N = 60
CAP = GraphCapacity(1536)
STEPS = 6


@pytest.fixture(scope="module")
def frames():
    """Frames 14..19 (steps 210..285) of the reference run, normalised; radii normalised."""
    with np.load(DATA) as d:
        scale = float(d["L"])
        return d["frames"][14:20] / scale, d["radius"] / scale


@pytest.fixture(scope="module")
def inputs(frames):
    x, a = frames
    return jnp.asarray(x[:, :N], jnp.float32), jnp.asarray(a[:N], jnp.float32)


@pytest.fixture(scope="module")
def params():
    norm = {
        "velocity_mean": jnp.zeros(3),
        "velocity_std": jnp.full((3,), 0.05),
        "acceleration_mean": jnp.zeros(3),
        "acceleration_std": jnp.full((3,), 0.002),
    }
    return init_params(jax.random.key(3), TINY, norm)


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def _acc(params, x, a, mask=None, *, config=TINY, capacity=CAP):
    return predict_step(params, x, a, model_config=config, capacity=capacity, mask=mask).acceleration


def plain_features(x, a, radius, clip=4.0):
    """The spec's features written out in NumPy for D = 3: all pairs, self-loops included."""
    last = x[-1]
    v = np.diff(x, axis=0)  # (C-1, N, D)
    d = np.linalg.norm(last[:, None] - last[None], axis=-1)
    receivers, senders = np.nonzero(d < radius)  # sorted by (receiver, sender)
    vel = np.transpose(v, (1, 0, 2)).reshape(len(a), -1)
    walls = np.clip(np.concatenate([last + 1, 1 - last], axis=1) / a[:, None], -clip, clip)
    nodes = np.concatenate([vel / a[:, None], walls, a[:, None]], axis=1)
    a_sum = (a[senders] + a[receivers])[:, None]
    rel = (last[senders] - last[receivers]) / a_sum
    rel_vel = (vel[senders] - vel[receivers]) / a_sum
    edges = np.concatenate([rel, np.linalg.norm(rel, axis=1, keepdims=True), rel_vel, a_sum], axis=1)
    return nodes, edges, senders, receivers


def test_3d_feature_sizes_are_the_specs():
    assert F.node_feature_size(6, 3) == 22 and F.edge_feature_size(6, 3) == 20


def test_3d_features_match_the_spec_written_out(frames):
    x, a = frames
    expected = plain_features(x, a, 0.2)
    with jax.enable_x64(True):
        nodes, edges, senders, receivers = F.graph_features(jnp.asarray(x), jnp.asarray(a), connectivity_radius=0.2)
    assert nodes.shape == (182, 22) and edges.shape[1] == 20
    np.testing.assert_array_equal(np.asarray(senders), expected[2])
    np.testing.assert_array_equal(np.asarray(receivers), expected[3])
    np.testing.assert_allclose(np.asarray(nodes), expected[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(edges), expected[1], rtol=0, atol=1e-12)


def test_3d_cell_list_graph_equals_all_pairs_and_grows_on_overflow(frames):
    x, _ = frames
    last = jnp.asarray(x[-1], jnp.float32)
    d = np.linalg.norm(x[-1][:, None] - x[-1][None], axis=-1)
    expected = sorted(zip(*np.nonzero((d < 0.2) & ~np.eye(len(d), dtype=bool))))
    capacity = G.fit_capacity(last, connectivity_radius=0.2, use_cell_list=True)
    assert capacity.cell is not None and G.cell_list_possible(3, connectivity_radius=0.2, bounds=((-1, 1),) * 3)
    for cap in (capacity, GraphCapacity(capacity.edges, 2)):  # the second: cells too small, must overflow
        graph = jax.jit(functools.partial(G.radius_graph, connectivity_radius=0.2, capacity=cap))(last)
        if cap is capacity:
            assert not bool(graph.overflow)
            r, s = np.asarray(graph.receivers), np.asarray(graph.senders)
            keep = (r < 182) & (r != s)
            assert sorted(zip(r[keep].tolist(), s[keep].tolist())) == expected
        else:
            assert bool(graph.overflow)
            grown = G.grow_capacity(cap, 182, last, connectivity_radius=0.2)
            assert grown.cell > cap.cell


def test_3d_translation_invariance(params, inputs):
    x, a = inputs
    shift = jnp.array([0.25, -0.5, 0.125], jnp.float32)
    shifted = ModelConfig(
        latent_size=16,
        hidden_size=16,
        message_passing_steps=2,
        dim=3,
        bounds=((-0.75, 1.25), (-1.5, 0.5), (-0.875, 1.125)),
    )
    np.testing.assert_allclose(
        np.asarray(_acc(params, x + shift, a, config=shifted)), np.asarray(_acc(params, x, a)), rtol=1e-4, atol=1e-7
    )


def test_3d_permutation_equivariance(params, inputs):
    x, a = inputs
    perm = np.random.default_rng(0).permutation(N)
    base = _acc(params, x, a)
    np.testing.assert_allclose(
        np.asarray(_acc(params, x[:, perm], a[perm])), np.asarray(base)[perm], rtol=1e-4, atol=1e-7
    )


def test_3d_padding_changes_nothing_and_jit_equals_eager(params, inputs):
    x, a = inputs
    pad = 9
    xp = jnp.concatenate([x, x[:, :pad]], axis=1)  # padding rows on top of real spheres
    ap = jnp.concatenate([a, jnp.zeros((pad,))])
    mask = jnp.arange(N + pad) < N
    base = _acc(params, x, a)
    padded = _acc(params, xp, ap, mask, capacity=GraphCapacity(CAP.edges + 300))
    np.testing.assert_allclose(np.asarray(padded[:N]), np.asarray(base), rtol=1e-5, atol=1e-8)
    np.testing.assert_array_equal(np.asarray(padded[N:]), 0.0)
    eager = predict_step(params, x, a, model_config=TINY, capacity=CAP).acceleration
    np.testing.assert_allclose(np.asarray(eager), np.asarray(base), rtol=1e-5, atol=1e-7)


def test_3d_rollout_equals_a_loop_and_vmap_equals_the_loop(params, inputs):
    x, a = inputs
    out = rollout(params, x, a, STEPS, model_config=TINY, capacity=CAP, chunk_size=4)
    assert out.shape == (STEPS, N, 3)
    window, expected = x, []
    for _ in range(STEPS):
        nxt = predict_position(params, window, a, model_config=TINY, capacity=CAP)
        expected.append(nxt)
        window = jnp.concatenate([window[1:], nxt[None]])
    np.testing.assert_allclose(np.asarray(out), np.asarray(jnp.stack(expected)), rtol=0, atol=2e-6)
    # vmap over two padded trajectories (the second: 45 spheres, turned a quarter) equals one by one.
    n2 = 45
    second = quarter_turns(x[:, 7 : 7 + n2], 1)
    second = jnp.concatenate([second, x[:, 7 : 7 + n2, 2:]], axis=-1)
    xs = jnp.stack([x, jnp.pad(second, ((0, 0), (0, N - n2), (0, 0)))])
    radii = jnp.stack([a, jnp.pad(a[7 : 7 + n2], (0, N - n2))])
    masks = jnp.stack([jnp.ones(N, bool), jnp.arange(N) < n2])
    scan = lambda x, r, m: rollout_scan(params, x, r, STEPS, model_config=TINY, mask=m, capacity=CAP)
    batched, overflow = jax.jit(jax.vmap(scan))(xs, radii, masks)
    assert not np.any(np.asarray(overflow))
    np.testing.assert_allclose(np.asarray(batched[0]), np.asarray(out), rtol=0, atol=2e-6)
    alone = rollout(params, second, a[7 : 7 + n2], STEPS, model_config=TINY, capacity=CAP, chunk_size=4)
    np.testing.assert_allclose(np.asarray(batched[1, :, :n2]), np.asarray(alone), rtol=0, atol=2e-6)


# ----------------------------------------------------------------------------- floor symmetries


def turn(x, k):
    """``x (..., 3)`` turned ``k`` quarter turns about the vertical axis."""
    return np.concatenate([quarter_turns(np.asarray(x)[..., :2], k), np.asarray(x)[..., 2:]], axis=-1)


def mirror(x, axis):
    out = np.array(x, copy=True)
    out[..., axis] *= -1
    return out


def test_quarter_turns_form_the_rotation_group_exactly():
    xy = np.random.default_rng(0).normal(size=(5, 2)).astype(np.float32)
    np.testing.assert_array_equal(quarter_turns(xy, 1), np.stack([-xy[:, 1], xy[:, 0]], -1))
    np.testing.assert_array_equal(quarter_turns(quarter_turns(xy, 1), 3), xy)
    np.testing.assert_array_equal(quarter_turns(xy, 2), -xy)
    np.testing.assert_array_equal(np.asarray(quarter_turns(jnp.asarray(xy), 5)), quarter_turns(xy, 1))


def test_the_physics_maps_turned_and_mirrored_starts_onto_turned_and_mirrored_runs():
    # What the augmentation relies on: walls, gravity and the pair force are unchanged by
    # the symmetries of the square floor (float64, 300 steps from 80 spheres of the reference start).
    with np.load(DATA) as d:
        x0, v0, a, config = d["x0"][:80], d["v0"][:80], d["radius"][:80], PhysicsConfig()
    with jax.enable_x64(True):
        run = lambda x, v: np.asarray(simulate(x, v, a, config, n_frames=2, save_every=300))
        base = run(x0, v0)
        # One quarter turn and one mirror generate all eight symmetries of the square.
        np.testing.assert_allclose(run(turn(x0, 1), turn(v0, 1)), turn(base, 1), rtol=0, atol=1e-13)
        np.testing.assert_allclose(run(mirror(x0, 0), mirror(v0, 0)), mirror(base, 0), rtol=0, atol=1e-13)


def test_node_and_edge_features_of_a_turned_start_are_the_features_relabelled(frames):
    # A quarter turn (x, y) -> (-y, x) maps every velocity-like column pair the same way and
    # swaps the wall distances (x walls become y walls): the input the network sees under
    # the augmentation is an exact relabelling, no new numbers.
    x, a = frames
    nodes, edges, s, r = F.graph_features(jnp.asarray(x), jnp.asarray(a), connectivity_radius=0.2)
    t_nodes, t_edges, ts, tr = F.graph_features(jnp.asarray(turn(x, 1)), jnp.asarray(a), connectivity_radius=0.2)
    np.testing.assert_array_equal(np.asarray(ts), np.asarray(s))
    np.testing.assert_array_equal(np.asarray(tr), np.asarray(r))
    nodes, t_nodes = np.asarray(nodes), np.asarray(t_nodes)
    for k in range(5):  # velocities
        np.testing.assert_allclose(t_nodes[:, 3 * k : 3 * k + 3], turn(nodes[:, 3 * k : 3 * k + 3], 1), atol=1e-6)
    lower, upper = nodes[:, 15:18], nodes[:, 18:21]  # distances to the lower and upper walls
    np.testing.assert_allclose(t_nodes[:, 15:18], np.stack([upper[:, 1], lower[:, 0], lower[:, 2]], 1), atol=1e-5)
    np.testing.assert_allclose(t_nodes[:, 18:21], np.stack([lower[:, 1], upper[:, 0], upper[:, 2]], 1), atol=1e-5)
    edges, t_edges = np.asarray(edges), np.asarray(t_edges)
    np.testing.assert_allclose(t_edges[:, :3], turn(edges[:, :3], 1), atol=1e-6)
    np.testing.assert_allclose(
        t_edges[:, 3:],
        np.concatenate(
            [edges[:, 3:4]] + [turn(edges[:, 4 + 3 * k : 7 + 3 * k], 1) for k in range(5)] + [edges[:, -1:]], axis=1
        ),
        atol=1e-6,
    )


def test_batch_stream_turns_and_mirrors_examples_by_its_own_draws(frames):
    x, a = frames

    class Trajectory:
        position = np.concatenate([x, x[-1:] + 1e-3 * np.arange(1, 4)[:, None, None]], axis=0).astype(np.float32)
        radius = a.astype(np.float32)

    common = dict(input_sequence_length=6, batch_size=2, connectivity_radius=0.2, bounds=((-1, 1),) * 3)
    plain = BatchStream([Trajectory], **common)
    flipped = BatchStream([Trajectory], mirror=True, **common)
    turned = BatchStream([Trajectory], mirror=True, quarter_turns=True, **common)
    seen = set()
    for i in range(8):
        ids = plain.batch_examples(i)
        assert np.array_equal(turned.batch_examples(i), ids)
        flips = np.random.default_rng([0, 1, i]).integers(0, 2, (2, 2)) == 1
        turns = np.random.default_rng([0, 2, i]).integers(0, 4, 2)
        # Mirror draws do not change when quarter turns are added (old runs replay the same batches).
        np.testing.assert_array_equal(flipped.batch(i).position, plain.make_batch(ids, flips).position)
        batch = turned.batch(i).position
        for k in range(2):
            n = len(a)
            expected = np.array(plain.make_batch(ids).position[k, :, :n])
            expected[..., :2] *= np.where(flips[k], -1.0, 1.0)
            np.testing.assert_array_equal(batch[k, :, :n], turn(expected, turns[k]))
            seen.add(int(turns[k]))
    assert seen == {0, 1, 2, 3}
    with pytest.raises(ValueError, match="3-D"):
        BatchStream([Trajectory], quarter_turns=True, **{**common, "bounds": ((-1, 1), (-2, 2), (-1, 1))})


def test_an_augmented_example_is_the_example_of_the_physically_turned_run():
    # What the model is trained on under augmentation (one mirror in y, then one quarter turn, the
    # BatchStream's order) must be what the physics does from the turned start: the same input
    # frames, so the same node features (velocities and the six wall distances) and targets.
    with np.load(DATA) as d:
        x0, v0, a, config, scale = d["x0"][:80], d["v0"][:80], d["radius"][:80], PhysicsConfig(), float(d["L"])
    g = lambda x: turn(mirror(x, 1), 1)
    with jax.enable_x64(True):
        run = lambda x, v: (np.asarray(simulate(x, v, a, config, n_frames=8, save_every=15)) / scale).astype(np.float32)
        base, moved = run(x0, v0), run(g(x0), g(v0))

    class Trajectory:
        def __init__(self, position):
            self.position, self.radius = position, (a / scale).astype(np.float32)

    common = dict(input_sequence_length=6, batch_size=1, connectivity_radius=0.2, bounds=((-1, 1),) * 3)
    augmented = BatchStream([Trajectory(base)], **common).make_batch([0], np.array([[False, True]]), turns=[1])
    physical = BatchStream([Trajectory(moved)], **common).make_batch([0])
    np.testing.assert_allclose(augmented.position, physical.position, rtol=0, atol=1e-6)
    radius = jnp.asarray(Trajectory(base).radius)
    nodes = [np.asarray(F.node_features(jnp.asarray(b.position[0, :6]), radius)) for b in (augmented, physical)]
    np.testing.assert_allclose(nodes[0], nodes[1], rtol=0, atol=1e-4)
    targets = [np.asarray(b.position[0, 6] - 2 * b.position[0, 5] + b.position[0, 4]) for b in (augmented, physical)]
    np.testing.assert_allclose(targets[0], targets[1], rtol=0, atol=1e-6)
    # and neither is the unaugmented example (the check can fail)
    plain = BatchStream([Trajectory(base)], **common).make_batch([0])
    assert np.abs(plain.position - physical.position).max() > 0.1


def _relative_l2(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def test_symmetrized_prediction_is_equivariant_under_the_floors_eight_symmetries(params, inputs):
    # mean_g g^-1 net(g X) over the 8 symmetries of the square floor: any weights give an exactly
    # equivariant prediction (to float rounding of the mean). The same untrained network without
    # the average is far from equivariant: the test can tell the two apart.
    from dispgns.simulator import floor_symmetries

    x, a = inputs
    symmetric = dataclasses.replace(TINY, symmetrize=True)
    group = floor_symmetries(3)
    assert len(group) == 8 and len(set(group)) == 8 and group[0] == ((0, 1, 2), (1.0, 1.0, 1.0))

    def g(v, k):
        perm, signs = group[k]
        return np.asarray(v)[..., list(perm)] * np.asarray(signs, np.float32)

    base_sym = _acc(params, x, a, config=symmetric)
    base = _acc(params, x, a)
    plain_errors = []
    for k in range(1, 8):
        moved = jnp.asarray(g(x, k))
        assert _relative_l2(_acc(params, moved, a, config=symmetric), g(base_sym, k)) < 1e-5
        plain_errors.append(_relative_l2(_acc(params, moved, a), g(base, k)))
    assert min(plain_errors) > 1e-2, plain_errors
    # The symmetric prediction is the mean of the network's predictions for g X, each mapped back by g^-1.
    turned = [_acc(params, jnp.asarray(g(x, k)), a) for k in range(8)]
    by_hand = np.mean(
        [(np.asarray(turned[k]) * np.asarray(group[k][1]))[..., list(np.argsort(group[k][0]))] for k in range(8)],
        axis=0,
    )
    np.testing.assert_allclose(np.asarray(base_sym), by_hand, rtol=1e-5, atol=1e-7)


@pytest.mark.slow  # two more programs to compile (~30 s of CPU)
def test_symmetrized_rollout_batch_and_2d_mirror(params, inputs):
    # The batched step (what rollout_batch and evaluate use) symmetrises too; in 2-D the group is
    # the mirror image in x.
    from dispgns.simulator import predict_step_batch

    x, a = inputs
    symmetric = dataclasses.replace(TINY, symmetrize=True)
    batch = predict_step_batch(
        params, jnp.stack([x, x]), jnp.stack([a, a]), model_config=symmetric, capacity=CAP
    ).acceleration
    np.testing.assert_allclose(np.asarray(batch[0]), np.asarray(_acc(params, x, a, config=symmetric)), atol=1e-7)
    config2 = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, dim=2, symmetrize=True)
    norm = {k: jnp.full((2,), v) for k, v in (("velocity_mean", 0.0), ("velocity_std", 0.05))}
    norm |= {"acceleration_mean": jnp.full((2,), 1e-4), "acceleration_std": jnp.full((2,), 0.002)}
    params2 = init_params(jax.random.key(5), config2, norm)
    x2 = x[..., 1:]  # the y-z plane of the spheres: a 2-D input with the last axis vertical
    full = G.full_capacity(N)  # all pairs: the projection packs the plane more densely than the cube
    acc = _acc(params2, x2, a, config=config2, capacity=full)
    mirrored = _acc(params2, x2 * jnp.asarray([-1.0, 1.0]), a, config=config2, capacity=full)
    assert np.all(np.isfinite(acc))
    assert _relative_l2(mirrored, np.asarray(acc) * [-1.0, 1.0]) < 1e-5
    with pytest.raises(ValueError, match="square floor"):
        ModelConfig(dim=3, symmetrize=True, bounds=((-1, 1), (-2, 2), (-1, 1)))
    with pytest.raises(ValueError, match="square floor"):
        ModelConfig(dim=2, symmetrize=True, bounds=((0, 2), (-1, 1)))


# A trained model learns the floor's symmetries only approximately (from the augmentation): the
# largest relative L2 difference ||acc(g X) - g acc(X)|| / ||acc(X)|| allowed over the 7 non-trivial
# symmetries, on two windows of a fresh paper3d trajectory. (Checkpoint 11000 of the 3-D run, far from
# trained, gives 0.12-0.16 for the mirror image in y and 1.35-1.93 for the others: its accelerations carry
# an x component that does not turn with the input. A model shipped with ship.py --symmetrize passes exactly.)
TRAINED_EQUIVARIANCE_TOLERANCE = 0.2


def floor_equivariance_errors(params, model_config, window, radius):
    """``{(perm, signs): relative L2}`` of the one-step accelerations under each non-trivial floor symmetry."""
    from dispgns.simulator import floor_symmetries, predict_acceleration

    base = np.asarray(predict_acceleration(params, window, radius, model_config=model_config))
    errors = {}
    for perm, signs in floor_symmetries(3)[1:]:
        moved = np.asarray(window)[..., list(perm)] * np.asarray(signs, np.float32)
        acc = np.asarray(predict_acceleration(params, moved, radius, model_config=model_config))
        errors[(perm, signs)] = _relative_l2(acc, base[..., list(perm)] * np.asarray(signs, np.float32))
    return errors


def paper3d_windows(seed=0, frames=40):
    """Two input windows (frames 10-15 and 34-39) of a fresh trajectory in the paper3d cube, normalised."""
    from dispgns.data.generate import PAPER3D_HALF_SIZE_M, PAPER_TRAIN_RADII_M, paper3d_spec
    from dispgns.physics import sample_initial_state

    spec = paper3d_spec()
    config = spec.physics
    state = sample_initial_state(jax.random.PRNGKey(seed), PAPER_TRAIN_RADII_M, config, dim=3)
    truth = np.asarray(
        simulate(state.position, state.velocity, state.radius, config, n_frames=frames, save_every=spec.save_every)
    )
    truth = (truth / PAPER3D_HALF_SIZE_M).astype(np.float32)
    radius = (np.asarray(state.radius) / PAPER3D_HALF_SIZE_M).astype(np.float32)
    return [truth[10:16], truth[frames - 6 :]], radius


@pytest.mark.slow  # a fresh 3-D trajectory and 16 one-step predictions of the full-size model
def test_shipped_3d_model_maps_turned_and_mirrored_inputs_onto_turned_and_mirrored_predictions():
    from dispgns.pretrained import MODEL_3D, load_pretrained

    params, config, _ = load_pretrained(MODEL_3D)  # it ships with the package
    windows, radius = paper3d_windows()
    for window in windows:
        # Averaged over the eight symmetries the weights are equivariant to float rounding.
        symmetric = floor_equivariance_errors(params, dataclasses.replace(config, symmetrize=True), window, radius)
        assert max(symmetric.values()) < 1e-5, symmetric
        # As shipped: with the average (sedimentation-3d's network alone is off by 0.38-0.90, RESUME.md),
        # or else a network that learned the symmetries from the augmentation.
        if not config.symmetrize:
            errors = floor_equivariance_errors(params, config, window, radius)
            assert max(errors.values()) <= TRAINED_EQUIVARIANCE_TOLERANCE, errors
    assert config.dim == 3 and config.keep_inside_box
