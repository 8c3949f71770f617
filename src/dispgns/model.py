"""The encoder-processor-decoder graph network of the paper (Flax Linen inside, pure functions outside).

Shapes: ``N`` nodes, ``E`` edges, ``L`` latent size, ``H`` hidden width.

* Encoders: node and edge MLPs (``hidden_layers`` hidden layers of ``H``,
  output ``L``, LayerNorm).
* ``message_passing_steps`` interaction blocks, weights not shared. For an
  edge ``j -> i``: message ``m_ij = MLP([x_i, x_j, e_ij])`` (LayerNorm); the
  messages are summed at the receiver; node update ``x_i += MLP2(MLP1([sum_j
  m_ij, x_i]))``; edge update ``e_ij += MLP(m_ij)`` (the authors' code keeps
  the old edge embedding instead; dispgns updates it as the paper describes).
* Decoder: MLP (no LayerNorm) to ``D`` values, the standardised acceleration
  divided by the radius.

With the paper's defaults (``L = H = 128``, 2 hidden layers, 10 blocks, ``C =
6``, ``D = 2``) the network has 2,587,010 parameters.

The first layer of each message MLP acts on ``[x_i, x_j, e_ij]``; its kernel
is split by rows so the node parts are multiplied once per node and then
gathered per edge (same parameters, same function, far fewer FLOPs). Each
LayerNorm's centring is folded into the layer before it: that layer runs with
the output-mean of every kernel row and of its bias taken off, so its output
is already centred (same parameters, same function, one reduction and one
pass fewer per LayerNorm). Both are checked against a plain implementation of
the spec in the tests.

The public surface is :class:`ModelConfig`, :func:`init_params` and
:func:`apply_network`; ``params`` is a pytree ``{"network": ...,
"normalization": ...}`` whose normalisation statistics are data, not weights
(the optimiser never sees them).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from dispgns._config import config_from_mapping
from dispgns.features import edge_feature_size, node_feature_size
from dispgns.graph import Bounds, as_bounds

_ACTIVATIONS: dict[str, Callable] = {
    "relu": jax.nn.relu,
    "gelu": jax.nn.gelu,
    "silu": jax.nn.silu,
    "tanh": jnp.tanh,
    "elu": jax.nn.elu,
}

_MATMUL_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Static description of the learned simulator (hashable; saved with checkpoints).

    Attributes:
      latent_size: ``L``, width of node and edge embeddings (128).
      hidden_layers: hidden layers per MLP (2).
      hidden_size: ``H``, width of the hidden layers (128).
      message_passing_steps: ``K`` interaction blocks, weights not shared (10).
      input_sequence_length: ``C`` input frames (6, i.e. 5 velocities).
      dim: ``D`` spatial dimension (2).
      activation: ``"relu"`` (paper), ``"gelu"``, ``"silu"``, ``"tanh"`` or ``"elu"``.
      connectivity_radius: graph radius in normalised box units (0.2 = 4 x
        the largest training radius).
      boundary_clip: wall distances are clipped to ``[-clip, clip]`` radii (4).
      bounds: the box ``((lo, hi),) * D`` in normalised units (``None``:
        ``[-1, 1]^D``).
      layer_norm_epsilon: LayerNorm epsilon (PyTorch's 1e-5).
      matmul_dtype: ``"float32"`` (default, exact) or ``"bfloat16"``: matmul
        inputs rounded to bfloat16 with float32 accumulation (what TPUs do by
        default; about twice as fast on CPUs with AVX512-BF16).
      keep_inside_box: after every predicted step, move a centre that the
        network put beyond its wall contact position (``lo + a_i``,
        ``hi - a_i`` on an axis) back onto it (False: the network's position
        as it is, the paper's method). A hard constraint the walls of the
        data obey; the next velocity then follows from the corrected position.
    """

    latent_size: int = 128
    hidden_layers: int = 2
    hidden_size: int = 128
    message_passing_steps: int = 10
    input_sequence_length: int = 6
    dim: int = 2
    activation: str = "relu"
    connectivity_radius: float = 0.2
    boundary_clip: float = 4.0
    bounds: Bounds | None = None
    layer_norm_epsilon: float = 1e-5
    matmul_dtype: str = "float32"
    keep_inside_box: bool = False

    def __post_init__(self):
        for name in ("latent_size", "hidden_size", "message_passing_steps", "dim"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"ModelConfig.{name} must be an integer >= 1, got {value!r}")
        if int(self.hidden_layers) != self.hidden_layers or self.hidden_layers < 0:
            raise ValueError(f"ModelConfig.hidden_layers must be an integer >= 0, got {self.hidden_layers!r}")
        if int(self.input_sequence_length) != self.input_sequence_length or self.input_sequence_length < 2:
            raise ValueError(f"ModelConfig.input_sequence_length must be >= 2, got {self.input_sequence_length!r}")
        if self.activation not in _ACTIVATIONS:
            raise ValueError(f"ModelConfig.activation must be one of {sorted(_ACTIVATIONS)}, got {self.activation!r}")
        if self.matmul_dtype not in _MATMUL_DTYPES:
            raise ValueError(
                f"ModelConfig.matmul_dtype must be one of {sorted(_MATMUL_DTYPES)}, got {self.matmul_dtype!r}"
            )
        if not (self.connectivity_radius > 0) or not (self.boundary_clip > 0):
            raise ValueError(
                "ModelConfig.connectivity_radius and boundary_clip must be > 0, got "
                f"{self.connectivity_radius!r} and {self.boundary_clip!r}"
            )
        # Normalise lists (e.g. from YAML/JSON) into the hashable tuple form.
        bounds = ((-1.0, 1.0),) * int(self.dim) if self.bounds is None else self.bounds
        object.__setattr__(self, "bounds", as_bounds(bounds, self.dim))

    @property
    def node_feature_size(self) -> int:
        return node_feature_size(self.input_sequence_length, self.dim)

    @property
    def edge_feature_size(self) -> int:
        return edge_feature_size(self.input_sequence_length, self.dim)

    def to_dict(self) -> dict[str, Any]:
        values = dataclasses.asdict(self)
        values["bounds"] = [list(b) for b in self.bounds]
        return values

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> ModelConfig:
        """Build a config from a mapping (numbers may be given as text); unknown keys are an error."""
        values = dict(values)
        if values.get("bounds") is not None:
            values["bounds"] = tuple(tuple(float(v) for v in b) for b in values["bounds"])
        return config_from_mapping(cls, values)


def _row_chunks(rows: int) -> int:
    return next(c for c in (8, 4, 2, 1) if rows % c == 0)


@jax.custom_vjp
def _matmul_bf16(x, kernel):
    """``x @ kernel`` with inputs rounded to bfloat16, float32 accumulation, result in ``x.dtype``."""
    return _matmul_bf16_fwd(x, kernel)[0]


def _matmul_bf16_fwd(x, kernel):
    xb = x.astype(jnp.bfloat16)
    y = jnp.dot(xb, kernel.astype(jnp.bfloat16), preferred_element_type=jnp.float32).astype(x.dtype)
    # x in bfloat16 (what the product used, at half the memory); the kernel as given (small).
    return y, (xb, kernel)


def _matmul_bf16_bwd(residuals, dy):
    xb, kernel = residuals
    gb, kb = dy.astype(jnp.bfloat16), kernel.astype(jnp.bfloat16)
    # XLA:CPU's bfloat16 dot is 3-4x slower with a transposed operand: give it
    # a kernel transposed in memory, and contract over rows in a few chunks.
    kernel_t = lax.optimization_barrier(kb.T.reshape(-1)).reshape(kb.shape[::-1])
    dx = jnp.dot(gb, kernel_t, preferred_element_type=jnp.float32)
    rows = xb.shape[0]
    chunks = _row_chunks(rows)
    dk = jnp.einsum(
        "cri,cro->io",
        xb.reshape(chunks, rows // chunks, -1),
        gb.reshape(chunks, rows // chunks, -1),
        preferred_element_type=jnp.float32,
    )
    # dy has x's dtype (the forward casts its result to it).
    return dx.astype(dy.dtype), dk.astype(kernel.dtype)


_matmul_bf16.defvjp(_matmul_bf16_fwd, _matmul_bf16_bwd)


class Linear(nn.Module):
    """``x @ kernel + bias`` with explicit input width (so that the kernel exists at setup)."""

    in_features: int
    features: int
    matmul_dtype: Any = None

    def setup(self):
        self.kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.in_features, self.features))
        self.bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))

    def dot(self, x, kernel):
        if self.matmul_dtype is None:
            return jnp.dot(x, kernel)
        if x.ndim == 2:
            return _matmul_bf16(x, kernel)
        return jnp.dot(
            x.astype(self.matmul_dtype), kernel.astype(self.matmul_dtype), preferred_element_type=jnp.float32
        ).astype(x.dtype)

    def __call__(self, x):
        return self.dot(x, self.kernel) + self.bias


def _row_mean(x):
    """Mean over the last axis as a matrix-vector product, shape ``(..., 1)``.

    XLA:CPU turns a row reduction into its own reduce-window pass per call;
    as a dot it runs 1.6x faster standalone and one LayerNorm pass shorter in
    the network. ``HIGHEST`` keeps it exact float32 on GPUs (TF32 otherwise).
    """
    ones = jnp.full((x.shape[-1], 1), 1.0 / x.shape[-1], x.dtype)
    return jnp.matmul(x, ones, precision=lax.Precision.HIGHEST)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _layer_norm(x, scale, bias, epsilon, centred):
    """LayerNorm over the last axis; ``centred=True``: the rows of ``x`` already have zero mean."""
    return _layer_norm_fwd(x, scale, bias, epsilon, centred)[0]


def _layer_norm_fwd(x, scale, bias, epsilon, centred):
    if not centred:
        x = x - _row_mean(x)
    inv = lax.rsqrt(_row_mean(x * x) + epsilon)
    normed = x * inv
    return normed * scale + bias, (normed, inv, scale)


def _layer_norm_bwd(epsilon, centred, residuals, dy):
    normed, inv, scale = residuals
    dbias = jnp.sum(dy, axis=tuple(range(dy.ndim - 1)))
    dscale = jnp.sum(dy * normed, axis=tuple(range(dy.ndim - 1)))
    g = dy * scale
    dx = g - normed * _row_mean(g * normed)
    if not centred:
        dx = dx - _row_mean(g)
    # centred: the centring lives in the layer's kernel (see MLP), whose
    # autodiff projects this gradient onto zero-mean rows.
    return inv * dx, dscale, dbias


_layer_norm.defvjp(_layer_norm_fwd, _layer_norm_bwd)


@jax.custom_vjp
def _centre_last(v):
    """``v`` minus its mean over the last axis (a projection, so its backward is itself).

    The backward centres the bias gradient ``(F,)`` behind an optimisation
    barrier: otherwise XLA merges the mean into the row sum that made it and
    sums the whole ``(E, F)`` cotangent once more, with a slow 32 x 32
    reduce-window (0.3 ms per LayerNorm in the training step).
    """
    return v - jnp.mean(v, axis=-1, keepdims=True)


def _centre_last_bwd(_, g):
    g = lax.optimization_barrier(g)
    return (g - jnp.mean(g, axis=-1, keepdims=True),)


_centre_last.defvjp(lambda v: (_centre_last(v), None), _centre_last_bwd)


class LayerNorm(nn.Module):
    """LayerNorm over the last axis (parameters ``scale``, ``bias``) with a hand-written backward pass.

    Same function and parameters as ``flax.linen.LayerNorm``; the explicit
    backward keeps XLA on CPU from materialising broadcasts of ``scale`` per
    edge.
    """

    epsilon: float = 1e-5

    @nn.compact
    def __call__(self, x, *, centred: bool = False):
        """``x (..., F)``; ``centred=True`` promises rows of zero mean (then not subtracted again)."""
        features = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones_init(), (features,))
        bias = self.param("bias", nn.initializers.zeros_init(), (features,))
        return _layer_norm(x, scale.astype(x.dtype), bias.astype(x.dtype), self.epsilon, centred)


class MLP(nn.Module):
    """``in -> hidden x n -> out`` with an activation between layers and an optional LayerNorm."""

    in_features: int
    hidden: tuple[int, ...]
    out_features: int
    activation: str = "relu"
    layer_norm: bool = True
    epsilon: float = 1e-5
    matmul_dtype: Any = None

    def setup(self):
        sizes = (self.in_features,) + tuple(self.hidden) + (self.out_features,)
        self.layers = [
            Linear(sizes[k], sizes[k + 1], self.matmul_dtype, name=f"Dense_{k}") for k in range(len(sizes) - 1)
        ]
        if self.layer_norm:
            self.norm = LayerNorm(epsilon=self.epsilon, name="LayerNorm_0")

    def __call__(self, x):
        return self.after_first(self.layers[0](x))

    def after_first(self, h):
        """The MLP applied to the output ``h`` of its first linear layer."""
        act = _ACTIVATIONS[self.activation]
        if not self.layer_norm:
            for layer in self.layers[1:]:
                h = layer(act(h))
            return h
        if len(self.layers) == 1:
            return self.norm(h)
        for layer in self.layers[1:-1]:
            h = layer(act(h))
        # LayerNorm's centring folded into the last layer: with the mean over
        # outputs taken off each kernel row and off the bias, x W + b - mean
        # is exactly x W' + b'. Saves a reduction and a pass per LayerNorm.
        # With bfloat16 matmuls W' is rounded too, leaving a row mean of order
        # 2^-9 / sqrt(F) of the outputs: below the rounding of the product.
        last = self.layers[-1]
        return self.norm(last.dot(act(h), _centre_last(last.kernel)) + _centre_last(last.bias), centred=True)


class InteractionBlock(nn.Module):
    """One message-passing step with residual node and edge updates."""

    config: ModelConfig

    def setup(self):
        c = self.config
        hidden = (c.hidden_size,) * c.hidden_layers
        width = c.latent_size
        kw = dict(activation=c.activation, epsilon=c.layer_norm_epsilon, matmul_dtype=_MATMUL_DTYPES[c.matmul_dtype])
        self.message = MLP(3 * width, hidden, width, name="message", **kw)
        self.node = MLP(2 * width, hidden, width, name="node", **kw)
        self.node_2 = MLP(width, hidden, width, name="node_2", **kw)
        self.edge = MLP(width, hidden, width, name="edge", **kw)

    def __call__(self, nodes, edges, gather_senders, gather_receivers, scatter_receivers):
        width = self.config.latent_size
        first = self.message.layers[0]
        kernel = first.kernel
        # [x_i, x_j, e_ij] @ W = (x W_i)[i] + (x W_j)[j] + e W_e: node parts once per node.
        at_receiver = first.dot(nodes, kernel[:width])
        at_sender = first.dot(nodes, kernel[width : 2 * width])
        h = (
            at_receiver.at[gather_receivers].get(indices_are_sorted=True, mode="promise_in_bounds")
            + at_sender.at[gather_senders].get(mode="promise_in_bounds")
            + first.dot(edges, kernel[2 * width :])
            + first.bias
        )
        messages = self.message.after_first(h)
        summed = jax.ops.segment_sum(messages, scatter_receivers, num_segments=nodes.shape[0], indices_are_sorted=True)
        nodes = nodes + self.node_2(self.node(jnp.concatenate([summed, nodes], axis=-1)))
        edges = edges + self.edge(messages)
        return nodes, edges


class EncodeProcessDecode(nn.Module):
    """The whole network: features in, standardised acceleration / radius out."""

    config: ModelConfig

    def setup(self):
        c = self.config
        hidden = (c.hidden_size,) * c.hidden_layers
        kw = dict(activation=c.activation, epsilon=c.layer_norm_epsilon, matmul_dtype=_MATMUL_DTYPES[c.matmul_dtype])
        self.node_encoder = MLP(c.node_feature_size, hidden, c.latent_size, name="node_encoder", **kw)
        self.edge_encoder = MLP(c.edge_feature_size, hidden, c.latent_size, name="edge_encoder", **kw)
        self.blocks = [InteractionBlock(c, name=f"block_{k}") for k in range(c.message_passing_steps)]
        self.decoder = MLP(c.latent_size, hidden, c.dim, layer_norm=False, name="decoder", **kw)

    def __call__(self, node_features, edge_features, senders, receivers):
        n = node_features.shape[0]
        # Unused edge slots hold index N: clamp them for gathers (their
        # results are garbage that never reaches a real node) and keep N for
        # the scatter, which drops them.
        gather_senders = jnp.minimum(senders, n - 1)
        gather_receivers = jnp.minimum(receivers, n - 1)
        nodes = self.node_encoder(node_features)
        edges = self.edge_encoder(edge_features)
        for block in self.blocks:
            nodes, edges = block(nodes, edges, gather_senders, gather_receivers, receivers)
        return self.decoder(nodes)


def identity_normalization(dim: int = 2) -> dict[str, jnp.ndarray]:
    """Statistics that leave features and targets unchanged (the authors' recipe)."""
    zeros, ones = jnp.zeros((dim,), jnp.float32), jnp.ones((dim,), jnp.float32)
    return {"velocity_mean": zeros, "velocity_std": ones, "acceleration_mean": zeros, "acceleration_std": ones}


def init_params(key: jax.Array, model_config: ModelConfig, normalization: Mapping[str, Any] | None = None) -> dict:
    """Initial parameters.

    Args:
      key: PRNG key.
      model_config: static :class:`ModelConfig`.
      normalization: statistics of the radius-normalised velocities and
        target accelerations (``{"velocity_mean", "velocity_std",
        "acceleration_mean", "acceleration_std"}``, each ``(D,)``), e.g. from
        :func:`dispgns.training.compute_normalization`; ``None`` = identity
        (no standardisation, the authors' recipe).

    Returns:
      ``{"network": <Flax params>, "normalization": <dict of (D,) float32>}``.
    """
    c = model_config
    variables = _init_network(key, c)
    norm = identity_normalization(c.dim) if normalization is None else normalization
    norm = {
        k: jnp.asarray(norm[k], jnp.float32)
        for k in ("velocity_mean", "velocity_std", "acceleration_mean", "acceleration_std")
    }
    for k, v in norm.items():
        if v.shape != (c.dim,):
            raise ValueError(f"normalization[{k!r}] must have shape ({c.dim},), got {v.shape}")
    return {"network": variables["params"], "normalization": norm}


def _network_shapes(config: ModelConfig):
    nodes = jnp.zeros((2, config.node_feature_size), jnp.float32)
    edges = jnp.zeros((2, config.edge_feature_size), jnp.float32)
    index = jnp.array([0, 1], jnp.int32)
    return jax.eval_shape(EncodeProcessDecode(config).init, jax.random.key(0), nodes, edges, index, index)


@functools.partial(jax.jit, static_argnums=(1,))
def _init_network(key, config: ModelConfig):
    """Initial weights without running the network (compiles in a fraction of Flax's ``init``).

    Kernels: LeCun normal as Flax's default (truncated normal, std
    ``1 / sqrt(fan_in)``), drawn in one call and cut into the kernels in
    tree order; biases: 0; LayerNorm scales: 1.
    """
    shapes = _network_shapes(config)
    paths, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    kernels = [leaf for path, leaf in paths if path[-1].key == "kernel"]
    total = sum(int(np.prod(leaf.shape)) for leaf in kernels)
    # 0.8796... is the std of a unit normal truncated to [-2, 2] (as in Flax's variance_scaling).
    draws = jax.random.truncated_normal(key, -2.0, 2.0, (total,), jnp.float32) / 0.87962566103423978
    leaves, offset = [], 0
    for path, leaf in paths:
        name = path[-1].key
        if name == "kernel":
            size = int(np.prod(leaf.shape))
            leaves.append((draws[offset : offset + size] / np.sqrt(leaf.shape[0])).reshape(leaf.shape))
            offset += size
        elif name == "scale":
            leaves.append(jnp.ones(leaf.shape, leaf.dtype))
        else:
            leaves.append(jnp.zeros(leaf.shape, leaf.dtype))
    return jax.tree_util.tree_unflatten(treedef, leaves)


def apply_network(
    network_params,
    node_features: jnp.ndarray,
    edge_features: jnp.ndarray,
    senders: jnp.ndarray,
    receivers: jnp.ndarray,
    *,
    model_config: ModelConfig,
) -> jnp.ndarray:
    """The raw network on one graph.

    Args:
      network_params: ``params["network"]``.
      node_features: ``(N, (C-1)D + 2D + 1)`` (velocity columns standardised).
      edge_features: ``(E, CD + 2)``.
      senders, receivers: ``(E,)`` int32; receivers non-decreasing; unused
        slots hold ``N`` (and must come last).
      model_config: static.

    Returns:
      ``(N, D)`` standardised acceleration / radius.
    """
    return EncodeProcessDecode(model_config).apply(
        {"params": network_params}, node_features, edge_features, senders, receivers
    )


def count_parameters(tree) -> int:
    """Number of scalars in a pytree (e.g. ``params["network"]``)."""
    return int(sum(np.prod(np.shape(x)) for x in jax.tree_util.tree_leaves(tree)))
