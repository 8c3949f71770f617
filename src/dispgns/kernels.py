"""CPU kernels for the network of :mod:`dispgns.model`, chosen with ``ModelConfig(kernels="fused")``.

They keep the parameters and the function of the plain network (equal to
float32 rounding: other summation orders), and are faster with XLA on CPU.
What each one measured when it was added (in-process A/B runs of the paper
network on the 2-core AMD EPYC of ``benchmarks/``, the first on the earlier
2-core Intel machine):

* :func:`_matmul_bf16`: the bfloat16 matmul with a backward that hands
  XLA:CPU operands in the layout its bfloat16 dot is fast with (bfloat16
  training step ~409 -> 278 ms, Intel).
* :class:`MLP` folds its LayerNorm's centring into the kernel and bias of the
  layer before it, and :func:`_row_mean` takes row means as matrix-vector
  products: one reduction and one pass fewer per LayerNorm (rollout step
  20.0 -> 18.5 ms, training step 177 -> 168 ms).
* :func:`_centre_last`'s backward centres the bias gradient behind an
  optimisation barrier (float32 training step 172 -> 165 ms and 159 -> 154
  ms in two runs).
* :class:`LayerNorm`: a hand-written backward that skips the centring terms
  the fold provides and keeps XLA from materialising per-edge broadcasts.

:class:`MLP` extends :class:`dispgns.model.MLP` (the network code uses either
through the same interface: ``layers[k].kernel``, ``layers[k].bias``,
``layers[k].dot(x, kernel)``, ``__call__(x)`` and ``after_first(h)``);
:mod:`dispgns.model` imports this module only when a config asks for it.
``benchmarks/model_kernels.py`` times the network with them and without
(float32, paper size; two runs, medians of per-round ratios): the plain
network takes 1.03-1.08x their time for a rollout-sized forward pass and
1.05x for a training-sized forward + backward pass.
"""

from __future__ import annotations

import functools

# Callable and DTypeLike name the field types of dispgns.model's Dense and MLP: the dataclass ``__init__`` flax
# generates for the subclasses below resolves its annotations in this module's namespace.
from collections.abc import Callable  # noqa: F401

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import lax
from jax.typing import DTypeLike  # noqa: F401
from jaxtyping import ArrayLike, Float

from dispgns.model import MLP as PlainMLP
from dispgns.model import Dense

__all__ = ["LayerNorm", "Linear", "MLP"]

# ``x (..., K) @ kernel (K, H)``; the hidden and output rows of an MLP.
_Inputs = Float[ArrayLike, "*batch K"]
_Kernel = Float[ArrayLike, "K H"]
_Hidden = Float[ArrayLike, "*batch H"]
_Outputs = Float[ArrayLike, "*batch O"]


def _row_chunks(rows: int) -> int:
    return next(c for c in (8, 4, 2, 1) if rows % c == 0)


@jax.custom_vjp
def _matmul_bf16(x, kernel):
    """``x (R, F) @ kernel (F, G)`` with inputs rounded to bfloat16, float32 accumulation, result in ``x.dtype``."""
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


class Linear(Dense):
    """:class:`dispgns.model.Dense` with bfloat16 products of 2-D inputs through :func:`_matmul_bf16`."""

    def dot(self, x: _Inputs, kernel: _Kernel) -> _Outputs:
        if self.matmul_dtype is not None and x.ndim == 2:
            return _matmul_bf16(x, kernel).astype(x.dtype)
        return super().dot(x, kernel)


def _row_mean(x):
    """Mean over the last axis as a matrix-vector product, ``(..., F) -> (..., 1)``.

    XLA:CPU turns a row reduction into its own reduce-window pass per call;
    as a dot it runs 1.6x faster standalone and one LayerNorm pass shorter in
    the network. ``HIGHEST`` keeps it exact float32 on GPUs (TF32 otherwise).
    """
    ones = jnp.full((x.shape[-1], 1), 1.0 / x.shape[-1], x.dtype)
    return jnp.matmul(x, ones, precision=lax.Precision.HIGHEST)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _layer_norm(x, scale, bias, epsilon, centred):
    """LayerNorm of ``x (..., F)`` over the last axis; ``centred=True``: the rows of ``x`` already have zero mean."""
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


class MLP(PlainMLP):
    """:class:`dispgns.model.MLP` (same parameters, same function) with the fused LayerNorm and :class:`Linear`."""

    def dense(self, index: int, fan_in: int, fan_out: int) -> Linear:
        return Linear(fan_in, fan_out, self.matmul_dtype, name=f"Dense_{index}")

    def layer_norm_module(self) -> LayerNorm:
        return LayerNorm(epsilon=self.epsilon, name="LayerNorm_0")

    def after_first(self, h: _Hidden) -> _Outputs:
        """The MLP applied to the output ``h (..., H)`` of its first linear layer."""
        if not self.layer_norm or len(self.layers) == 1:
            return super().after_first(h)
        act = self.activation
        for layer in self.layers[1:-1]:
            h = layer(act(h))
        # LayerNorm's centring folded into the last layer: with the mean over
        # outputs taken off each kernel row and off the bias, x W + b - mean
        # is exactly x W' + b'. Saves a reduction and a pass per LayerNorm.
        # With bfloat16 matmuls W' is rounded too, leaving a row mean of order
        # 2^-9 / sqrt(F) of the outputs: below the rounding of the product.
        last = self.layers[-1]
        return self.norm(last.dot(act(h), _centre_last(last.kernel)) + _centre_last(last.bias), centred=True)
