"""Radius graphs and the paper's features, against the reference file and invariances."""

import functools
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import features as F
from dispgns import graph as G

DATA = Path(__file__).parent / "data" / "features.npz"


@pytest.fixture(scope="module")
def ref():
    with np.load(DATA) as d:
        return {k: d[k] for k in d.files}


def _graph(x, mask=None, *, edges, cell=None):
    return _graph_jit(jnp.asarray(x), None if mask is None else jnp.asarray(mask), G.GraphCapacity(edges, cell))


@functools.partial(jax.jit, static_argnums=(2,))
def _graph_jit(x, mask, capacity):
    return G.radius_graph(x, mask, connectivity_radius=0.2, capacity=capacity)


def _edge_set(g, n):
    s, r = np.asarray(g.senders), np.asarray(g.receivers)
    keep = r < n
    return sorted(zip(r[keep].tolist(), s[keep].tolist()))


def _reference_edges(ref):
    return sorted(zip(ref["receivers"].tolist(), ref["senders"].tolist()))


def test_sizes():
    assert F.node_feature_size(6, 2) == 15 and F.edge_feature_size(6, 2) == 14
    assert F.node_feature_size(4, 3) == 16 and F.edge_feature_size(4, 3) == 14


def test_features_match_reference_float64(ref):
    with jax.enable_x64(True):
        nodes, edges, senders, receivers = F.graph_features(
            jnp.asarray(ref["positions"], jnp.float64),
            jnp.asarray(ref["radius"], jnp.float64),
            connectivity_radius=float(ref["connectivity_radius"]),
            boundary_clip=float(ref["clip"]),
        )
        assert nodes.dtype == jnp.float64 and edges.dtype == jnp.float64
        np.testing.assert_array_equal(np.asarray(senders), ref["senders"])
        np.testing.assert_array_equal(np.asarray(receivers), ref["receivers"])
        np.testing.assert_allclose(np.asarray(nodes), ref["node_features"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(edges), ref["edge_features"], rtol=0, atol=1e-9)


def test_features_match_reference_float32(ref):
    nodes, edges, senders, receivers = F.graph_features(
        jnp.asarray(ref["positions"], jnp.float32), jnp.asarray(ref["radius"], jnp.float32), connectivity_radius=0.2
    )
    assert nodes.dtype == jnp.float32
    assert nodes.shape == (150, 15) and edges.shape == (1562, 14)
    np.testing.assert_array_equal(np.asarray(senders), ref["senders"])
    np.testing.assert_array_equal(np.asarray(receivers), ref["receivers"])
    np.testing.assert_allclose(np.asarray(nodes), ref["node_features"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(edges), ref["edge_features"], rtol=0, atol=1e-5)


@pytest.mark.parametrize("cell", [None, 12])
def test_radius_graph_brute_force_and_cell_list(ref, cell):
    x = jnp.asarray(ref["positions"][-1], jnp.float32)
    g = _graph(x, edges=1500, cell=cell)
    assert g.senders.shape == (1500 + 150,)
    assert not bool(g.overflow)
    r = np.asarray(g.receivers)
    assert np.all(np.diff(r) >= 0), "edges must be sorted by receiver"
    assert _edge_set(g, 150) == _reference_edges(ref)
    small = _graph(x, edges=1000, cell=cell)
    assert bool(small.overflow)


def test_full_capacity_has_no_spurious_edge(ref):
    # With every candidate slot kept, jax-md leaves a rejected candidate in the last slot.
    x = jnp.asarray(ref["positions"][-1, :40], jnp.float32)
    n = 40
    full = _graph(x, edges=n * (n - 1))
    ok = _graph(x, edges=600)
    assert _edge_set(full, n) == _edge_set(ok, n)
    assert not bool(full.overflow)


def test_padding_never_pairs(ref):
    x = np.asarray(ref["positions"][-1], np.float32)
    pad = 70
    # Padding rows placed right on top of real particles: they must be parked away.
    xp = np.concatenate([x, x[:pad]], axis=0)
    mask = np.arange(150 + pad) < 150
    for cell in (None, 16):
        g = _graph(xp, mask, edges=1500, cell=cell)
        assert not bool(g.overflow)
        s, r = np.asarray(g.senders), np.asarray(g.receivers)
        keep = r < 150 + pad
        s, r = s[keep], r[keep]
        real = (s < 150) & (r < 150)
        assert sorted(zip(r[real].tolist(), s[real].tolist())) == _reference_edges(ref)
        # Padding particles only have their self-loop.
        assert np.all(s[~real] == r[~real]) and np.sum(~real) == pad


def test_the_capacity_policy_fits_grows_and_stays_on_the_ladder(ref, monkeypatch):
    x = ref["positions"][-1]
    assert G.host_count_pairs(x, connectivity_radius=0.2) == 1562 - 150
    # The k-d tree path (large N) counts exactly what the dense path counts, per frame and per mask.
    frames = ref["positions"]
    mask = np.arange(x.shape[0]) % 3 != 0
    dense = G.host_count_pairs(frames, mask, connectivity_radius=0.2)
    monkeypatch.setattr(G, "_DENSE_COUNT_MAX_PARTICLES", 1)
    np.testing.assert_array_equal(G.host_count_pairs(frames, mask, connectivity_radius=0.2), dense)
    monkeypatch.undo()
    cap = G.fit_capacity(x, connectivity_radius=0.2, use_cell_list=False)
    assert cap.edges >= 1412 * 1.05 and cap.cell is None and G.on_ladder(cap) == cap
    cap_cells = G.fit_capacity(x, connectivity_radius=0.2, use_cell_list=True)
    assert cap_cells.cell >= G.host_max_cell_occupancy(x, connectivity_radius=0.2) >= 1
    # Growth: at least 25 % more, enough for the positions it is given, on the ladder, capped at all pairs.
    grown = G.grow_capacity(cap_cells, 150)
    assert grown.edges >= 1.25 * cap_cells.edges and grown.cell >= 1.25 * cap_cells.cell and G.on_ladder(grown) == grown
    tight = G.grow_capacity(G.GraphCapacity(64, 4), 150, x, connectivity_radius=0.2)
    assert tight.edges >= 1412 * 1.2 and tight.cell >= G.host_max_cell_occupancy(x, connectivity_radius=0.2)
    assert G.grow_capacity(G.full_capacity(150), 150) == G.full_capacity(150)  # nothing left to grow
    # Sized from counts: head-room, then the ladder; never beyond all pairs.
    assert G.capacity_for_counts(1412, 150).edges == G.on_ladder(G.GraphCapacity(math.ceil(1412 * 1.05) + 32)).edges
    assert G.capacity_for_counts(10_000, 20) == G.GraphCapacity(380)
    assert G.edge_budget_for(1000) == G.on_ladder(G.GraphCapacity(1000)).edges
    assert G.grow_edge_budget(G.edge_budget_for(1000)) >= 1.25 * G.edge_budget_for(1000)


def test_translation_invariance_of_features(ref):
    pos = jnp.asarray(ref["positions"], jnp.float32)
    a = jnp.asarray(ref["radius"], jnp.float32)
    shift = np.array([0.375, -0.625], np.float32)
    bounds = tuple((-1.0 + s, 1.0 + s) for s in shift.tolist())
    n0, e0, s0, r0 = F.graph_features(pos, a, connectivity_radius=0.2)
    n1, e1, s1, r1 = F.graph_features(pos + shift, a, bounds=bounds, connectivity_radius=0.2)
    np.testing.assert_array_equal(np.asarray(s0), np.asarray(s1))
    np.testing.assert_array_equal(np.asarray(r0), np.asarray(r1))
    np.testing.assert_allclose(np.asarray(n0), np.asarray(n1), atol=1e-5)
    np.testing.assert_allclose(np.asarray(e0), np.asarray(e1), atol=1e-5)


def test_feature_gradients_are_finite_on_self_loops(ref):
    pos = jnp.asarray(ref["positions"][:, :20], jnp.float32)
    a = jnp.asarray(ref["radius"][:20], jnp.float32)
    idx = jnp.arange(20)

    def total(pos, a):
        return jnp.sum(F.edge_features(pos, a, idx, idx) ** 2) + jnp.sum(F.node_features(pos, a) ** 2)

    grads = jax.jit(jax.grad(total, argnums=(0, 1)))(pos, a)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)


def test_default_candidate_search_falls_back_to_all_pairs_where_no_cell_list_fits():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (6, 200, 2)).astype(np.float32)
    radius = np.full(200, 0.02, np.float32)
    # A radius so large that the grid has fewer than 3 cells per side, and a 1-D system.
    assert not G.cell_list_possible(2, connectivity_radius=2.5) and not G.cell_list_possible(
        1, connectivity_radius=0.05
    )
    assert G.fit_capacity(x[-1], connectivity_radius=2.5).cell is None
    _, _, senders, receivers = F.graph_features(x, radius, connectivity_radius=2.5)
    d2 = ((x[-1, :, None].astype(np.float64) - x[-1, None, :]) ** 2).sum(-1)
    assert len(senders) == int((d2 < 2.5**2).sum())  # self-loops included
    line = x[..., :1]
    _, _, senders, receivers = F.graph_features(line, radius, bounds=((-1.0, 1.0),), connectivity_radius=0.05)
    close = np.abs(line[-1, :, 0][:, None] - line[-1, :, 0][None, :]) < 0.05
    assert len(senders) == int(close.sum())
    assert G.fit_capacity(x[-1], connectivity_radius=0.2).cell is not None  # the usual case keeps the cell list


def test_capacities_on_the_ladder_are_shared_rungs():
    import math

    rungs = set()
    for edges in range(1, 20_000, 7):
        for cell in (None, 4, 9, 13, 31):
            cap = G.on_ladder(G.GraphCapacity(edges, cell))
            assert cap.edges >= edges and cap.edges % 64 == 0
            assert cap.edges <= max(64 * math.ceil(edges / 64) * 1.19, 64 * math.ceil(edges / 64) + 64)
            assert G.on_ladder(cap) == cap  # a rung maps to itself
            if cell is not None:
                assert cell <= cap.cell <= 1.5 * cell
        rungs.add(G.on_ladder(G.GraphCapacity(edges)).edges)
    assert len(rungs) < 40  # 20,000 capacities on a few dozen rungs
    # Trajectories a few pairs apart land on one capacity (one compilation).
    assert G.on_ladder(G.GraphCapacity(2240, 10)) == G.on_ladder(G.GraphCapacity(2304, 11))
    # With the particle count, never beyond all pairs or n per cell, never below the input.
    assert G.on_ladder(G.GraphCapacity(700, 20), 30) == G.GraphCapacity(768, 24)
    assert G.on_ladder(G.GraphCapacity(800, 20), 30) == G.GraphCapacity(870, 24)
    assert G.on_ladder(G.GraphCapacity(870, 29), 30) == G.GraphCapacity(870, 30)
    assert G.on_ladder(G.GraphCapacity(0), 1) == G.GraphCapacity(0)
