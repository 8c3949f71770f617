"""The graph network: size, invariances, padding, jit, and the edge-update defect."""

import dataclasses
import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dispgns
from dispgns.model import ModelConfig, count_parameters, init_params
from dispgns.simulator import fit_capacity, predict_acceleration, predict_step

DATA = Path(__file__).parent / "data" / "features.npz"
TINY = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2)
N = 48
CAPACITY = 512


@pytest.fixture(scope="module")
def inputs():
    with np.load(DATA) as d:
        x = jnp.asarray(d["positions"][:, :N], jnp.float32)
        a = jnp.asarray(d["radius"][:N], jnp.float32)
    return x, a


@pytest.fixture(scope="module")
def params():
    norm = {
        "velocity_mean": jnp.array([0.01, -0.02]),
        "velocity_std": jnp.array([0.05, 0.08]),
        "acceleration_mean": jnp.array([0.0, -0.001]),
        "acceleration_std": jnp.array([0.01, 0.02]),
    }
    return init_params(jax.random.key(0), TINY, norm)


def acceleration(params, x, a, *, model_config, mask=None, capacity=CAPACITY):
    """The pure one-step acceleration (what jit, vmap and grad see)."""
    return predict_step(params, x, a, model_config=model_config, capacity=capacity, mask=mask).acceleration


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def _acc(params, x, a, mask=None, *, config=TINY, capacity=CAPACITY):
    return acceleration(params, x, a, model_config=config, mask=mask, capacity=capacity)


def test_parameter_count_of_the_paper_model():
    shapes = jax.eval_shape(lambda k: init_params(k, ModelConfig()), jax.random.key(0))
    assert count_parameters(shapes["network"]) == 2_587_010
    first = shapes["network"]["block_0"]["message"]["Dense_0"]["kernel"]
    assert first.shape == (384, 128)


def test_config_round_trip_and_validation():
    c = ModelConfig(latent_size=32, bounds=[[-2, 2], [-1, 1]])
    assert c.bounds == ((-2.0, 2.0), (-1.0, 1.0)) and hash(c)
    assert ModelConfig.from_dict(c.to_dict()) == c
    with pytest.raises(ValueError, match="activation"):
        ModelConfig(activation="swish2")
    with pytest.raises(ValueError, match="unknown ModelConfig"):
        ModelConfig.from_dict({"latnet_size": 3})


def test_public_api_is_reexported():
    for name in ("ModelConfig", "init_params", "predict_acceleration", "predict_position", "rollout"):
        assert hasattr(dispgns, name), name


@pytest.mark.parametrize("kernels", ["plain", "fused"])
def test_jit_equals_eager(params, inputs, kernels):
    x, a = inputs
    config = dataclasses.replace(TINY, kernels=kernels)
    eager = predict_acceleration(params, x, a, model_config=config)
    jitted = _acc(params, x, a, config=config)
    assert eager.shape == (N, 2)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("kernels", ["plain", "fused"])
def test_network_gradient_jit_equals_eager(params, kernels):
    from dispgns.model import apply_network

    config = dataclasses.replace(TINY, kernels=kernels)
    n, slots = 10, 32
    key = jax.random.split(jax.random.key(5), 4)
    nodes = jax.random.normal(key[0], (n, config.node_feature_size))
    edges = jax.random.normal(key[1], (slots, config.edge_feature_size))
    receivers = jnp.sort(jax.random.randint(key[2], (slots,), 0, n + 1))  # some unused slots (index n), last
    senders = jnp.where(receivers < n, jax.random.randint(key[3], (slots,), 0, n), n)

    def loss(net):
        return jnp.sum(jnp.sin(apply_network(net, nodes, edges, senders, receivers, model_config=config)))

    eager, jitted = jax.grad(loss)(params["network"]), jax.jit(jax.grad(loss))(params["network"])
    for g, want in zip(jax.tree_util.tree_leaves(jitted), jax.tree_util.tree_leaves(eager)):
        np.testing.assert_allclose(
            np.asarray(g), np.asarray(want), rtol=1e-5, atol=1e-6 * float(jnp.max(jnp.abs(want)))
        )


def test_permutation_equivariance(params, inputs):
    x, a = inputs
    perm = np.random.default_rng(0).permutation(N)
    base = _acc(params, x, a)
    permuted = _acc(params, x[:, perm], a[perm])
    np.testing.assert_allclose(np.asarray(permuted), np.asarray(base)[perm], rtol=1e-4, atol=1e-7)


def test_translation_invariance(params, inputs):
    x, a = inputs
    shift = jnp.array([0.25, -0.5], jnp.float32)
    shifted = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=2, bounds=((-0.75, 1.25), (-1.5, 0.5)))
    base = _acc(params, x, a)
    moved = _acc(params, x + shift, a, config=shifted)
    np.testing.assert_allclose(np.asarray(moved), np.asarray(base), rtol=1e-4, atol=1e-7)


def test_padding_changes_no_output_nor_gradient(params, inputs):
    x, a = inputs
    pad = 13
    # Padding rows sit on top of real particles and have a zero radius: both must be harmless.
    xp = jnp.concatenate([x, x[:, :pad]], axis=1)
    ap = jnp.concatenate([a, jnp.zeros((pad,))])
    mask = jnp.arange(N + pad) < N

    def loss(p, x, a, mask, capacity):
        acc = acceleration(p, x, a, model_config=TINY, mask=mask, capacity=capacity)
        return jnp.sum(jnp.where(mask[:, None] if mask is not None else True, acc, 0.0) ** 2), acc

    grad = jax.jit(jax.grad(loss, has_aux=True), static_argnums=(4,))
    g0, acc0 = grad(params, x, a, None, CAPACITY)
    g1, acc1 = grad(params, xp, ap, mask, CAPACITY + 200)  # more particle and edge slots
    np.testing.assert_allclose(np.asarray(acc1[:N]), np.asarray(acc0), rtol=1e-5, atol=1e-8)
    np.testing.assert_array_equal(np.asarray(acc1[N:]), 0.0)
    for l0, l1 in zip(jax.tree_util.tree_leaves(g0), jax.tree_util.tree_leaves(g1)):
        assert np.all(np.isfinite(np.asarray(l1)))
        np.testing.assert_allclose(np.asarray(l1), np.asarray(l0), rtol=1e-4, atol=1e-9)


def test_edge_embeddings_are_updated_by_messages(params, inputs):
    # The authors' block returned its input edges, so the edge MLPs had no effect.
    x, a = inputs

    def loss(net):
        p = {"network": net, "normalization": params["normalization"]}
        return jnp.sum(acceleration(p, x, a, model_config=TINY, capacity=CAPACITY) ** 2)

    g = jax.jit(jax.grad(loss))(params["network"])
    edge_grad = g["block_0"]["edge"]["Dense_0"]["kernel"]
    assert float(jnp.max(jnp.abs(edge_grad))) > 0


@pytest.mark.parametrize("kernels", ["plain", "fused"])
def test_bfloat16_matmuls_stay_close(params, inputs, kernels):
    x, a = inputs
    bf16 = dataclasses.replace(TINY, matmul_dtype="bfloat16", kernels=kernels)
    ref = _acc(params, x, a)
    low = _acc(params, x, a, config=bf16)
    assert low.dtype == jnp.float32
    scale = float(jnp.max(jnp.abs(ref)))
    assert float(jnp.max(jnp.abs(low - ref))) < 0.05 * scale


def test_layer_norm_matches_flax():
    import flax.linen as nn

    from dispgns.kernels import LayerNorm

    x = jax.random.normal(jax.random.key(0), (30, 16)) * 3 + 1
    variables = {
        "params": {
            "scale": jax.random.normal(jax.random.key(1), (16,)),
            "bias": jax.random.normal(jax.random.key(2), (16,)),
        }
    }
    w = jax.random.normal(jax.random.key(3), (30, 16))
    ours = lambda v, x: jnp.sum(LayerNorm(1e-5).apply(v, x) * w)
    flax_ln = lambda v, x: jnp.sum(nn.LayerNorm(epsilon=1e-5).apply(v, x) * w)
    np.testing.assert_allclose(float(ours(variables, x)), float(flax_ln(variables, x)), rtol=1e-5)
    for a, b in zip(
        jax.tree_util.tree_leaves(jax.grad(ours, argnums=(0, 1))(variables, x)),
        jax.tree_util.tree_leaves(jax.grad(flax_ln, argnums=(0, 1))(variables, x)),
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


def _reference_network(net, nodes, edges, senders, receivers, n_real_edges, config):
    """The spec's network written out plainly: concatenated message inputs, flax's LayerNorm, real edges only."""
    import flax.linen as nn

    def mlp(p, x, layer_norm=True):
        names = sorted((k for k in p if k.startswith("Dense_")), key=lambda k: int(k.split("_")[1]))
        for k, name in enumerate(names):
            x = x @ p[name]["kernel"] + p[name]["bias"]
            if k < len(names) - 1:
                x = jax.nn.relu(x)
        if layer_norm:
            x = nn.LayerNorm(epsilon=config.layer_norm_epsilon).apply({"params": p["LayerNorm_0"]}, x)
        return x

    s, r = senders[:n_real_edges], receivers[:n_real_edges]
    x, e = mlp(net["node_encoder"], nodes), mlp(net["edge_encoder"], edges[:n_real_edges])
    for k in range(config.message_passing_steps):
        block = net[f"block_{k}"]
        m = mlp(block["message"], jnp.concatenate([x[r], x[s], e], axis=-1))
        summed = jax.ops.segment_sum(m, r, num_segments=x.shape[0])
        x = x + mlp(block["node_2"], mlp(block["node"], jnp.concatenate([summed, x], axis=-1)))
        e = e + mlp(block["edge"], m)
    return mlp(net["decoder"], x, layer_norm=False)


@pytest.mark.parametrize("kernels", ["plain", "fused"])
@pytest.mark.parametrize("hidden_layers", [0, 1, 2])
def test_network_matches_a_plain_reference_implementation(hidden_layers, kernels):
    """The split first layer (both kernels) and the fused kernels' folded LayerNorm centring compute the spec."""
    from dispgns.model import apply_network

    config = ModelConfig(
        latent_size=16, hidden_size=24, hidden_layers=hidden_layers, message_passing_steps=3, kernels=kernels
    )
    net = init_params(jax.random.key(1), config)["network"]
    # Non-trivial biases and LayerNorm parameters, so that folding them is tested too.
    leaves, treedef = jax.tree_util.tree_flatten(net)
    keys = jax.random.split(jax.random.key(2), len(leaves))
    net = jax.tree_util.tree_unflatten(treedef, [v + 0.3 * jax.random.normal(k, v.shape) for v, k in zip(leaves, keys)])
    n, real, slots = 12, 40, 48
    key = jax.random.split(jax.random.key(3), 4)
    nodes = jax.random.normal(key[0], (n, config.node_feature_size))
    edges = jax.random.normal(key[1], (slots, config.edge_feature_size))
    receivers = jnp.sort(jax.random.randint(key[2], (real,), 0, n))
    senders = jax.random.randint(key[3], (real,), 0, n)
    pad = jnp.full((slots - real,), n, jnp.int32)
    senders, receivers = jnp.concatenate([senders, pad]), jnp.concatenate([receivers, pad])
    weights = jax.random.normal(jax.random.key(4), (n, config.dim))

    def ours(net):
        return jnp.sum(apply_network(net, nodes, edges, senders, receivers, model_config=config) * weights)

    def reference(net):
        return jnp.sum(_reference_network(net, nodes, edges, senders, receivers, real, config) * weights)

    out = apply_network(net, nodes, edges, senders, receivers, model_config=config)
    want = _reference_network(net, nodes, edges, senders, receivers, real, config)
    assert float(jnp.max(jnp.abs(want))) > 1e-2
    np.testing.assert_allclose(np.asarray(out), np.asarray(want), rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(want))))
    got_grad, want_grad = jax.grad(ours)(net), jax.grad(reference)(net)
    for (path, g), w in zip(jax.tree_util.tree_leaves_with_path(got_grad), jax.tree_util.tree_leaves(want_grad)):
        scale = float(jnp.max(jnp.abs(w))) + 1e-12
        np.testing.assert_allclose(
            np.asarray(g), np.asarray(w), rtol=1e-3, atol=1e-4 * scale, err_msg=jax.tree_util.keystr(path)
        )


def test_batch_as_one_graph_equals_separate_graphs(params, inputs):
    from dispgns.graph import GraphCapacity, merge_graphs, merged_edge_count
    from dispgns.simulator import build_graph, network_output, network_output_batch, sanitize

    x, a = inputs
    n2 = N - 9
    mask = jnp.stack([jnp.ones(N, bool), jnp.arange(N) < n2])
    xs = jnp.stack([x, x[:, ::-1] * 0.9])
    xs, radii = jax.vmap(lambda x, r, m: sanitize(x, r, m, TINY))(xs, jnp.stack([a, a[::-1]]), mask)
    cap = GraphCapacity(CAPACITY)
    graphs = jax.vmap(lambda x, m: build_graph(x[-1], m, cap, TINY))(xs, mask)

    real = int(merged_edge_count(graphs, N))
    assert real < 2 * graphs.senders.shape[1]

    @functools.partial(jax.jit, static_argnums=4)
    def both(p, xs, radii, graphs, budget):
        merged = network_output_batch(p, xs, radii, graphs, model_config=TINY, edge_budget=budget)
        separate = jnp.stack(
            [
                network_output(
                    p, xs[k], radii[k], jax.tree_util.tree_map(lambda g, k=k: g[k], graphs), model_config=TINY
                )
                for k in range(2)
            ]
        )
        return merged, separate

    # Without compaction, with a budget that just fits the real edges, and with a generous one.
    for budget in (None, real, real + 100):
        merged, separate = both(params, xs, radii, graphs, budget)
        np.testing.assert_allclose(np.asarray(merged[0]), np.asarray(separate[0]), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(merged[1, :n2]), np.asarray(separate[1, :n2]), rtol=1e-5, atol=1e-6)
    senders, receivers = merge_graphs(graphs, N, real)
    assert np.all(np.diff(np.asarray(receivers)) >= 0)
    # A budget one edge short loses the last edge (a padding particle's self-loop here): the count
    # tells the caller, who must not use the result.
    merged, _ = both(params, xs, radii, graphs, real - 1)
    assert not np.allclose(np.asarray(merged[1]), np.asarray(separate[1]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("rows", [24, 13])
def test_bfloat16_matmul_gradient_matches_autodiff(rows):
    from dispgns.kernels import _matmul_bf16

    x = jax.random.normal(jax.random.key(0), (rows, 16))
    kernel = jax.random.normal(jax.random.key(1), (16, 8))
    w = jax.random.normal(jax.random.key(2), (rows, 8))

    def plain(x, k):
        return jnp.dot(x.astype(jnp.bfloat16), k.astype(jnp.bfloat16), preferred_element_type=jnp.float32)

    ours = jax.grad(lambda x, k: jnp.sum(jnp.sin(_matmul_bf16(x, k)) * w), argnums=(0, 1))
    ref = jax.grad(lambda x, k: jnp.sum(jnp.sin(plain(x, k)) * w), argnums=(0, 1))
    for jit in (False, True):
        f = jax.jit(ours) if jit else ours
        for got, want in zip(f(x, kernel), ref(x, kernel)):
            assert got.dtype == jnp.float32
            np.testing.assert_allclose(
                np.asarray(got), np.asarray(want), rtol=2e-2, atol=2e-2 * float(jnp.max(jnp.abs(want)))
            )
    np.testing.assert_array_equal(np.asarray(_matmul_bf16(x, kernel)), np.asarray(plain(x, kernel)))


@pytest.mark.parametrize("kernels", ["plain", "fused"])
def test_bfloat16_network_gradient_close_to_float32(params, inputs, kernels):
    x, a = inputs
    bf16 = dataclasses.replace(TINY, matmul_dtype="bfloat16", kernels=kernels)

    def loss(net, config):
        p = {"network": net, "normalization": params["normalization"]}
        return jnp.sum(acceleration(p, x, a, model_config=config, capacity=CAPACITY) ** 2)

    g32 = jax.jit(jax.grad(loss), static_argnums=1)(params["network"], TINY)
    g16 = jax.jit(jax.grad(loss), static_argnums=1)(params["network"], bf16)
    for leaf32, leaf16 in zip(jax.tree_util.tree_leaves(g32), jax.tree_util.tree_leaves(g16)):
        scale = float(jnp.max(jnp.abs(leaf32)))
        assert float(jnp.max(jnp.abs(leaf16 - leaf32))) <= 0.1 * scale + 1e-6


@pytest.fixture(scope="module")
def shipped():
    """The shipped model (latent 64, 5 blocks) and all 150 particles of the test frames."""
    from dispgns.pretrained import load_pretrained

    params, config, _ = load_pretrained()
    with np.load(DATA) as d:
        x = jnp.asarray(d["positions"], jnp.float32)
        a = jnp.asarray(d["radius"], jnp.float32)
    return params, config, x, a


def test_model_json_without_kernels_loads_as_plain():
    from dispgns.pretrained import load_pretrained, pretrained_path
    from dispgns.tuning import tuned_model_config

    # The paper-data model was exported before ModelConfig.kernels existed.
    stored = json.loads((pretrained_path("paper") / "model.json").read_text())["model"]
    assert "kernels" not in stored
    config = load_pretrained("paper")[1]
    assert config.kernels == "plain" and ModelConfig.from_dict(stored) == config
    fused = tuned_model_config(config)
    assert fused == dataclasses.replace(config, kernels="fused")
    assert fused.to_dict()["kernels"] == "fused" and ModelConfig.from_dict(fused.to_dict()) == fused
    with pytest.raises(ValueError, match="ModelConfig.kernels must be one of"):
        ModelConfig(kernels="gpu")


def test_plain_and_fused_kernels_agree_on_the_shipped_model(shipped):
    """Same outputs and gradients, to float32 rounding.

    The kernels differ in summation order only (LayerNorm centring folded into
    the layer before it, means as dot products, another variance formula than
    flax's): a few ulps (1.2e-7) per operation, grown through 5 residual blocks
    and 25 LayerNorms to ~1e-6 of the outputs' largest value on these frames,
    and ~1e-6 of each gradient leaf's largest value for the median leaf. A few
    leaves carry up to 1.8e-4: the shipped model's weight gradients on these
    frames are ill-conditioned (inputs moved by one ulp move a leaf's gradient
    by up to 17 % with the plain kernels alone). 3e-5 (outputs), 1e-5 (the
    median leaf) and 2e-3 (every leaf) leave a 10x margin, while a wrong term
    (a bias, a centring, a sender) is off by O(1) on the outputs and on most
    leaves.
    """
    params, config, x, a = shipped
    w = jax.random.normal(jax.random.key(0), (x.shape[1], config.dim))
    capacity = fit_capacity(x[-1], config)

    def run(kernels):
        c = dataclasses.replace(config, kernels=kernels)

        def loss(net):
            acc = acceleration(
                {"network": net, "normalization": params["normalization"]}, x, a, model_config=c, capacity=capacity
            )
            return jnp.sum(acc * w), acc

        return jax.jit(jax.grad(loss, has_aux=True))(params["network"])

    (g_plain, plain), (g_fused, fused) = run("plain"), run("fused")
    scale = float(jnp.max(jnp.abs(plain)))
    assert scale > 0 and float(jnp.max(jnp.abs(fused - plain))) <= 3e-5 * scale
    relative = []
    for (path, gp), gf in zip(jax.tree_util.tree_leaves_with_path(g_plain), jax.tree_util.tree_leaves(g_fused)):
        scale, difference = float(jnp.max(jnp.abs(gp))), float(jnp.max(jnp.abs(gf - gp)))
        assert difference <= 2e-3 * scale, jax.tree_util.keystr(path)
        if scale > 0:
            relative.append(difference / scale)
    assert len(relative) > 50 and float(np.median(relative)) <= 1e-5


def test_bfloat16_kernels_agree_on_the_shipped_model(shipped):
    """With bfloat16 matmuls the two kernels differ by less than bfloat16 differs from float32.

    The fused kernels round the centred kernel instead of the kernel (2^-9
    relative each), so they agree to bfloat16 rounding, not float32's: on
    these frames the outputs differ by 4 % of their largest value between the
    kernels and by 13 % between bfloat16 and float32.
    """
    params, config, x, a = shipped
    bf16 = dataclasses.replace(config, matmul_dtype="bfloat16")
    cap = fit_capacity(x[-1], config)
    ref = _acc(params, x, a, config=config, capacity=cap)
    plain = _acc(params, x, a, config=bf16, capacity=cap)
    fused = _acc(params, x, a, config=dataclasses.replace(bf16, kernels="fused"), capacity=cap)
    assert plain.dtype == fused.dtype == jnp.float32
    assert 0 < float(jnp.max(jnp.abs(fused - plain))) <= float(jnp.max(jnp.abs(plain - ref)))


GROWN = dataclasses.replace(TINY, hidden_size=24, message_passing_steps=4)


def _perturbed(network, seed):
    """Every leaf moved by a random amount: biases and LayerNorm scales no longer what a fresh init gives."""
    leaves, treedef = jax.tree_util.tree_flatten(network)
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    return jax.tree_util.tree_unflatten(
        treedef, [x + 0.1 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys, strict=True)]
    )


@pytest.mark.parametrize(
    "source, grown",
    [
        (TINY, GROWN),
        (TINY, dataclasses.replace(TINY, message_passing_steps=3)),
        (TINY, TINY),
        (dataclasses.replace(TINY, kernels="fused"), dataclasses.replace(GROWN, kernels="fused")),
        (dataclasses.replace(TINY, hidden_layers=1), dataclasses.replace(GROWN, hidden_layers=1)),
        (dataclasses.replace(TINY, hidden_layers=0), dataclasses.replace(GROWN, hidden_layers=0)),
    ],
)
def test_grown_network_computes_the_same_function(params, inputs, source, grown):
    from dispgns.model import grow_network

    x, a = inputs
    start = {**params, "network": _perturbed(init_params(jax.random.key(4), source)["network"], 5)}
    bigger = {**params, "network": grow_network(jax.random.key(1), start["network"], source, grown)}
    assert count_parameters(bigger["network"]) >= count_parameters(start["network"])
    expected = _acc(start, x, a, config=source)
    np.testing.assert_allclose(_acc(bigger, x, a, config=grown), expected, rtol=1e-5, atol=1e-6)
    eager = acceleration(bigger, x, a, model_config=grown)
    np.testing.assert_allclose(eager, expected, rtol=1e-5, atol=1e-6)


def test_grown_network_learns_through_every_new_weight(params, inputs):
    # Zero output weights and zero LayerNorm scales would be dead if nothing upstream of them got gradient:
    # after three plain gradient steps every new leaf (but the last block's edge update, which no output sees
    # in any network) has moved; three, as the weights behind a zero start learning one step after it.
    from dispgns.model import grow_network

    x, a = inputs
    network = grow_network(jax.random.key(1), params["network"], TINY, GROWN)
    fresh = init_params(jax.random.key(2), GROWN)["network"]
    target = jax.random.normal(jax.random.key(3), (x.shape[1], 2))

    def loss(net):
        return jnp.sum((_acc({**params, "network": net}, x, a, config=GROWN) - target) ** 2)

    moved = network
    for _ in range(3):
        grads = jax.grad(loss)(moved)
        moved = jax.tree_util.tree_map(lambda p, g: p - 1e-2 * g / (jnp.max(jnp.abs(g)) + 1e-30), moved, grads)
    changed = jax.tree_util.tree_map(lambda p, q: bool(jnp.any(p != q)), moved, network)
    flat = {jax.tree_util.keystr(path): v for path, v in jax.tree_util.tree_leaves_with_path(changed)}
    assert set(flat) == {jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(fresh)}
    dead = sorted(k for k, v in flat.items() if not v and "'block_3']['edge'" not in k)
    assert not dead, dead
    assert loss(moved) < loss(network)


def test_grow_network_refuses_to_shrink_or_change_the_latent_size(params):
    from dispgns.model import grow_network

    for target, message in [
        (dataclasses.replace(TINY, message_passing_steps=1), "message_passing_steps 2 -> 1"),
        (dataclasses.replace(TINY, latent_size=32), "latent_size 16 -> 32"),
        (dataclasses.replace(TINY, hidden_layers=3), "hidden_layers 2 -> 3"),
        (dataclasses.replace(TINY, activation="gelu"), "activation relu -> gelu"),
    ]:
        with pytest.raises(ValueError, match=message):
            grow_network(jax.random.key(1), params["network"], TINY, target)
