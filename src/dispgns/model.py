"""The encoder-processor-decoder graph network of the paper (Flax Linen inside, pure functions outside).

Shapes: ``N`` nodes, ``E`` edge slots, ``L`` latent size, ``H`` hidden width,
``D`` spatial dimension.

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

``ModelConfig.kernels`` picks what computes the MLPs (in :func:`_mlp` only):
``"plain"`` (:class:`MLP`: flax/jax ops, autodiff backward) or ``"fused"``
(:mod:`dispgns.kernels`: CPU kernels, same parameters and function).
``params`` is a pytree ``{"network": ..., "normalization": ...}`` whose
normalisation statistics are data, not weights (the optimiser never sees them).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import flax
import flax.linen as nn
import flax.traverse_util
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import ArrayLike, Float, Int, PyTree, Shaped

from dispgns._config import check_fields, config_from_mapping
from dispgns.arrays import Frame, Params, PerAxis, PRNGKey
from dispgns.features import edge_feature_size, node_feature_size
from dispgns.graph import Bounds, as_bounds

# Shapes (jaxtyping, no runtime check): F node and G edge features, E edges, K inputs and H outputs of a
# layer, O of an MLP.
_NodeFeatures = Float[ArrayLike, "N F"]
_EdgeFeatures = Float[ArrayLike, "E G"]
_EdgeIndex = Int[ArrayLike, "E"]
_Inputs = Float[ArrayLike, "*batch K"]
_Kernel = Float[ArrayLike, "K H"]
_Hidden = Float[ArrayLike, "*batch H"]
_Outputs = Float[ArrayLike, "*batch O"]
_Tree = PyTree[Shaped[ArrayLike, "..."]]

__all__ = [
    "MLP",
    "Dense",
    "EncodeProcessDecode",
    "InteractionBlock",
    "ModelConfig",
    "apply_network",
    "GROWABLE_FIELDS",
    "count_parameters",
    "grow_network",
    "identity_normalization",
    "init_params",
]

_ACTIVATIONS: dict[str, Callable] = {name: getattr(jax.nn, name) for name in ("relu", "gelu", "silu", "tanh", "elu")}
_MATMUL_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}
_KERNELS = ("plain", "fused")
_NORMALIZATION_KEYS = ("velocity_mean", "velocity_std", "acceleration_mean", "acceleration_std")


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
      kernels: ``"plain"`` (default: flax/jax ops, the spec as written) or
        ``"fused"`` (:mod:`dispgns.kernels`, ~5 % faster on CPUs; same
        parameters, same function to float32 rounding). A speed setting only:
        :func:`dispgns.tuning.tuned_model_config` sets it.
      keep_inside_box: after every predicted step, move a centre that the
        network put beyond its wall contact position (``lo + a_i``,
        ``hi - a_i`` on an axis) back onto it (False: the network's position
        as it is, the paper's method). A hard constraint the walls of the
        data obey; the next velocity then follows from the corrected position.
      symmetrize: average every predicted acceleration over the symmetries of the
        box's floor (:func:`dispgns.simulator.floor_symmetries`: the 8 quarter turns
        about the vertical and mirror images of a square floor in 3-D, the mirror
        image in 2-D): ``acc(X) = mean_g g^-1 net(g X)``, so the prediction is
        equivariant under them whatever the weights (to float rounding of the mean).
        Prediction only (``predict_step`` and everything built on it); training
        targets the network itself. 8 network evaluations per step in 3-D (2 in 2-D,
        as one merged graph); needs a box centred on the vertical axis with a square floor.
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
    kernels: str = "plain"
    keep_inside_box: bool = False
    symmetrize: bool = False

    def __post_init__(self):
        check_fields(
            self,
            integers=dict(
                latent_size=1, hidden_size=1, message_passing_steps=1, dim=1, hidden_layers=0, input_sequence_length=2
            ),
            positive=("connectivity_radius", "boundary_clip", "layer_norm_epsilon"),
            choices={"activation": _ACTIVATIONS, "matmul_dtype": _MATMUL_DTYPES, "kernels": _KERNELS},
        )
        # Normalise lists (e.g. from YAML/JSON) into the hashable tuple form.
        bounds = ((-1.0, 1.0),) * int(self.dim) if self.bounds is None else self.bounds
        object.__setattr__(self, "bounds", as_bounds(bounds, self.dim))
        if self.symmetrize:
            # The floor's symmetries act about the vertical axis through the box's centre: they map the
            # box onto itself only if every horizontal axis spans (-h, h) with one h.
            horizontal = self.bounds[:-1]
            if self.dim < 2 or any(lo != -hi or hi != horizontal[0][1] for lo, hi in horizontal):
                raise ValueError(
                    "ModelConfig.symmetrize needs a box centred on the vertical axis with a square floor "
                    f"(bounds (-h, h) on every horizontal axis, one h), got bounds {self.bounds}"
                )

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
        """Build a config from a mapping (numbers may be text); unknown keys are an error, missing ones default."""
        values = dict(values)
        if values.get("bounds") is not None:
            values["bounds"] = tuple(tuple(float(v) for v in b) for b in values["bounds"])
        return config_from_mapping(cls, values)


class Dense(nn.Module):
    """``x (..., in_features) @ kernel + bias``; ``matmul_dtype=jnp.bfloat16``: inputs rounded, float32 sums.

    The kernel is declared at setup (not at the first call, as in
    ``nn.Dense``): the interaction block multiplies by parts of it.
    """

    in_features: int
    features: int
    matmul_dtype: DTypeLike | None = None

    def setup(self) -> None:
        self.kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.in_features, self.features))
        self.bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))

    def dot(self, x: _Inputs, kernel: _Kernel) -> _Outputs:
        if self.matmul_dtype is None:
            return jnp.dot(x, kernel)
        return jnp.dot(
            x.astype(self.matmul_dtype), kernel.astype(self.matmul_dtype), preferred_element_type=jnp.float32
        )

    def __call__(self, x):
        return self.dot(x, self.kernel) + self.bias


class MLP(nn.Module):
    """``(..., in_features) -> (..., out_features)``: Dense layers of widths ``hidden``, ``activation`` between them."""

    in_features: int
    hidden: tuple[int, ...]
    out_features: int
    activation: Callable = jax.nn.relu
    layer_norm: bool = True
    epsilon: float = 1e-5
    matmul_dtype: DTypeLike | None = None

    def setup(self) -> None:
        sizes = (self.in_features, *self.hidden, self.out_features)
        self.layers = [self.dense(k, sizes[k], sizes[k + 1]) for k in range(len(sizes) - 1)]
        if self.layer_norm:
            self.norm = self.layer_norm_module()

    def dense(self, index: int, fan_in: int, fan_out: int) -> Dense:
        return Dense(fan_in, fan_out, self.matmul_dtype, name=f"Dense_{index}")

    def layer_norm_module(self) -> nn.LayerNorm:
        return nn.LayerNorm(epsilon=self.epsilon, name="LayerNorm_0")

    def __call__(self, x):
        return self.after_first(self.layers[0](x))

    def after_first(self, h: _Hidden) -> _Outputs:
        """The MLP applied to the output ``h (..., H)`` of its first Dense layer."""
        for layer in self.layers[1:]:
            h = layer(self.activation(h))
        return self.norm(h) if self.layer_norm else h


def _mlp(c: ModelConfig, in_features: int, out_features: int, name: str, layer_norm: bool = True):
    """An MLP of the network, computed by the implementation ``c.kernels`` names (chosen here only)."""
    cls = MLP
    if c.kernels == "fused":
        from dispgns.kernels import MLP as cls  # it extends this module's MLP, so it is imported on demand
    hidden, act, dtype = (c.hidden_size,) * c.hidden_layers, _ACTIVATIONS[c.activation], _MATMUL_DTYPES[c.matmul_dtype]
    return cls(in_features, hidden, out_features, act, layer_norm, c.layer_norm_epsilon, dtype, name=name)


class InteractionBlock(nn.Module):
    """One message-passing step with residual node and edge updates."""

    config: ModelConfig

    def setup(self) -> None:
        c, width = self.config, self.config.latent_size
        self.message = _mlp(c, 3 * width, width, "message")
        self.node = _mlp(c, 2 * width, width, "node")
        self.node_2 = _mlp(c, width, width, "node_2")
        self.edge = _mlp(c, width, width, "edge")

    def __call__(self, nodes, edges, gather_senders, gather_receivers, scatter_receivers):
        """``nodes (N, L)``, ``edges (E, L)``, indices ``(E,)`` (gathers: within ``[0, N)``); new nodes and edges."""
        width, first = self.config.latent_size, self.message.layers[0]
        # [x_i, x_j, e_ij] W = (x W_i)[i] + (x W_j)[j] + e_ij W_e exactly, with the node parts multiplied once per
        # node, not per edge: part of the spec path, as it saves FLOPs on every device (L = H: 6 instead of 8
        # L x H products per edge and block, message and edge MLPs together).
        at_receiver = first.dot(nodes, first.kernel[:width])
        at_sender = first.dot(nodes, first.kernel[width : 2 * width])
        h = (
            at_receiver.at[gather_receivers].get(indices_are_sorted=True, mode="promise_in_bounds")
            + at_sender.at[gather_senders].get(mode="promise_in_bounds")
            + first.dot(edges, first.kernel[2 * width :])
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

    def setup(self) -> None:
        c = self.config
        self.node_encoder = _mlp(c, c.node_feature_size, c.latent_size, "node_encoder")
        self.edge_encoder = _mlp(c, c.edge_feature_size, c.latent_size, "edge_encoder")
        self.blocks = [InteractionBlock(c, name=f"block_{k}") for k in range(c.message_passing_steps)]
        self.decoder = _mlp(c, c.latent_size, c.dim, "decoder", layer_norm=False)

    def __call__(self, node_features, edge_features, senders, receivers):
        """As :func:`apply_network`."""
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


def identity_normalization(dim: int = 2) -> dict[str, PerAxis]:
    """Statistics that leave features and targets unchanged (the authors' recipe), each ``(dim,)``."""
    zeros, ones = jnp.zeros((dim,), jnp.float32), jnp.ones((dim,), jnp.float32)
    return {"velocity_mean": zeros, "velocity_std": ones, "acceleration_mean": zeros, "acceleration_std": ones}


def init_params(key: PRNGKey, model_config: ModelConfig, normalization: Mapping[str, PerAxis] | None = None) -> Params:
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
    norm = identity_normalization(model_config.dim) if normalization is None else normalization
    norm = {k: jnp.asarray(norm[k], jnp.float32) for k in _NORMALIZATION_KEYS}
    for k, v in norm.items():
        if v.shape != (model_config.dim,):
            raise ValueError(f"normalization[{k!r}] must have shape ({model_config.dim},), got {v.shape}")
    return {"network": _init_network(key, model_config), "normalization": norm}


@functools.partial(jax.jit, static_argnums=(1,))
def _init_network(key, config: ModelConfig):
    """Initial weights without running the network (compiles in a fraction of Flax's ``init``).

    Kernels: LeCun normal as Flax's default (truncated normal, std
    ``1 / sqrt(fan_in)``), drawn in one call and cut into the kernels in
    tree order; biases: 0; LayerNorm scales: 1.
    """
    nodes, edges = jnp.zeros((2, config.node_feature_size)), jnp.zeros((2, config.edge_feature_size))
    index = jnp.arange(2)
    shapes = jax.eval_shape(EncodeProcessDecode(config).init, jax.random.key(0), nodes, edges, index, index)["params"]
    paths, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    sizes = [leaf.size for path, leaf in paths if path[-1].key == "kernel"]
    # 0.8796... is the std of a unit normal truncated to [-2, 2] (as in Flax's variance_scaling).
    draws = jax.random.truncated_normal(key, -2.0, 2.0, (sum(sizes),), jnp.float32) / 0.87962566103423978
    kernels = iter(jnp.split(draws, np.cumsum(sizes)[:-1]))

    def init(path, leaf):
        name = path[-1].key
        if name == "kernel":
            return (next(kernels) / np.sqrt(leaf.shape[0])).reshape(leaf.shape)
        return (jnp.ones if name == "scale" else jnp.zeros)(leaf.shape, leaf.dtype)

    return jax.tree_util.tree_unflatten(treedef, [init(path, leaf) for path, leaf in paths])


# Fields a grown network may enlarge, and fields it must share with its source (they fix the weights' shapes or what
# the network computes with them; the graph and feature settings are not the network's).
GROWABLE_FIELDS = ("hidden_size", "message_passing_steps")
_FIXED_BY_WEIGHTS = ("latent_size", "hidden_layers", "input_sequence_length", "dim", "activation", "layer_norm_epsilon")


def grow_network(key: PRNGKey, network_params: Params, source: ModelConfig, target: ModelConfig) -> Params:
    """Weights of a larger network that computes exactly what ``network_params`` computes (Net2Net growth).

    ``target`` may have wider hidden layers (``hidden_size``) and more interaction
    blocks (``message_passing_steps``) than ``source``; the fields that shape the
    weights or the network's function (latent size, hidden layers, ``C``, ``D``,
    activation, LayerNorm epsilon) must be equal. The new hidden units get fresh
    weights (:func:`init_params`'s) on their inputs and zero weights on their
    outputs; the new blocks, appended after the source's, get fresh weights and a
    zero LayerNorm scale at the end of their node and edge updates, so each adds
    zero to its residual. :func:`apply_network` is unchanged (up to float rounding
    of the wider sums), and every new weight learns (the zero weights get gradient
    at once, the weights behind them once those have moved): a fine-tune starts
    from the source's accuracy with the capacity of the target.

    Args:
      key: PRNG key of the fresh weights.
      network_params: ``params["network"]`` of a ``source`` network.
      source, target: static :class:`ModelConfig`.

    Returns:
      ``params["network"]`` of a ``target`` network.
    """
    fixed = [f for f in _FIXED_BY_WEIGHTS if getattr(source, f) != getattr(target, f)]
    shrunk = [f for f in GROWABLE_FIELDS if getattr(target, f) < getattr(source, f)]
    if fixed or shrunk:
        raise ValueError(
            "grow_network can only widen hidden_size and add message_passing_steps: "
            + "; ".join(f"{f} {getattr(source, f)} -> {getattr(target, f)}" for f in fixed + shrunk)
        )
    old = flax.traverse_util.flatten_dict(flax.core.unfreeze(network_params))
    blocks = {keys[0] for keys in old}

    def grown(path, leaf):
        keys = tuple(p.key for p in path)
        if keys[0] not in blocks:  # a new block (a leaf missing elsewhere is a KeyError: not this network's weights)
            ends_residual = keys[-3:-1] in (("node_2", "LayerNorm_0"), ("edge", "LayerNorm_0"))
            return jnp.zeros_like(leaf) if ends_residual and keys[-1] == "scale" else leaf
        value = jnp.asarray(old[keys], leaf.dtype)
        if value.shape == leaf.shape:
            return value
        if keys[-1] == "kernel":  # (in, out): the old block, zero from new inputs to old outputs
            rows, cols = value.shape
            return leaf.at[rows:, :cols].set(0.0).at[:rows, :cols].set(value)
        return leaf.at[: value.shape[0]].set(value)  # a bias: new units start at zero

    return jax.tree_util.tree_map_with_path(grown, flax.core.unfreeze(_init_network(key, target)))


def apply_network(
    network_params: Params,
    node_features: _NodeFeatures,
    edge_features: _EdgeFeatures,
    senders: _EdgeIndex,
    receivers: _EdgeIndex,
    *,
    model_config: ModelConfig,
) -> Frame:
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


def count_parameters(tree: _Tree) -> int:
    """Number of scalars in a pytree (e.g. ``params["network"]``)."""
    return int(sum(np.prod(np.shape(x)) for x in jax.tree_util.tree_leaves(tree)))
