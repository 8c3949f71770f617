"""Neighbour lists and neighbour-list forces of the ground-truth physics against brute force."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import PhysicsConfig, euler_integrator, tuning
from dispgns.physics import interaction_force, neighbor_fn_for

CONFIG = PhysicsConfig(cutoff=0.03, neighbor_skin=2e-3)
L = CONFIG.box_half_size


def parked(position, mask):
    """Positions as the integrator holds them (padding parked far outside the box), in the cell-list frame."""
    init_fn, _ = euler_integrator(CONFIG)
    return init_fn(position, jnp.zeros_like(position), jnp.full(position.shape[:1], 1e-3), mask).position + L


def random_system(dim, n=60, seed=0):
    key_x, key_a = jax.random.split(jax.random.PRNGKey(seed))
    position = jax.random.uniform(key_x, (n, dim), minval=-0.095, maxval=0.095)
    radius = jax.random.uniform(key_a, (n,), minval=2e-3, maxval=5e-3)
    return position, radius


def brute_force_pairs(position, reach):
    x = np.asarray(position, np.float64)
    distance = np.linalg.norm(x[:, None] - x[None], axis=-1)
    return [set(np.flatnonzero((row < reach) & (np.arange(len(x)) != i)).tolist()) for i, row in enumerate(distance)]


@pytest.mark.parametrize("dim", [2, 3])
def test_neighbor_lists_hold_every_pair_within_the_list_radius(dim):
    position, _ = random_system(dim)
    mask = jnp.arange(position.shape[0]) < 50  # the last 10 are padding, parked outside the box
    shifted = parked(position, mask)
    neighbor_fn = neighbor_fn_for(CONFIG, dim)
    nbrs = neighbor_fn.allocate(shifted)
    moved = neighbor_fn.update(shifted + 5e-4, nbrs)
    reach = CONFIG.cutoff + CONFIG.neighbor_skin
    for lists, x in [(nbrs, shifted), (moved, shifted + 5e-4)]:
        assert not bool(lists.did_buffer_overflow)
        got = [set(row[row < len(x)].tolist()) for row in np.asarray(lists.idx)]
        expected = brute_force_pairs(x[:50], reach)
        assert got[:50] == expected and all(not pairs for pairs in got[50:])
    too_small = dataclasses.replace(nbrs, max_occupancy=1)
    assert bool(neighbor_fn.update(shifted, too_small).did_buffer_overflow)


@pytest.mark.parametrize("slot_loop", [True, False])
def test_neighbor_forces_equal_all_pairs_with_the_cutoff(slot_loop):
    # float64: the two paths sum the pair terms differently (a row sum and a
    # matrix product), and in float32 their rounding alone reaches 1e-5 of
    # the force for these overlapping random particles.
    with jax.enable_x64(True), tuning.use_thresholds(slot_loop_max_pairs=2**30 if slot_loop else 1):
        position, radius = random_system(2, seed=1)
        mask = jnp.arange(position.shape[0]) != 7
        nbrs = neighbor_fn_for(CONFIG, 2).allocate(parked(position, mask))
        # Trial positions near each particle, as wall contact points are.
        query = position + 1e-3
        index = jnp.arange(position.shape[0]).at[3].set(position.shape[0])  # row 3 is padding
        with_list = interaction_force(query, index, position, radius, mask, CONFIG, nbrs.idx)
        all_pairs = interaction_force(query, index, position, radius, mask, CONFIG)
    assert with_list.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(with_list), np.asarray(all_pairs), rtol=1e-10, atol=1e-15)
    assert np.all(np.asarray(with_list)[[3, 7]] == 0) and np.any(np.asarray(with_list) != 0)
