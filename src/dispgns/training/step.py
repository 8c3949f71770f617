"""Training configuration, optimiser, loss and the jitted training step.

One step on a :class:`~dispgns.training.batches.Batch` of ``B`` examples:

1. random-walk noise on the ``C`` input frames (:mod:`.noise`);
2. optionally ``k`` pushforward steps: the model advances the inputs ``k``
   frames without gradient, and the loss is taken on the next step(s) from
   its own predictions;
3. graph at the last input frame (capacity ``batch.capacity``), network,
   target acceleration corrected for the input corruption, divided by the
   radius and standardised with ``params["normalization"]``;
4. optionally (``u = unroll_steps > 1``) the model's prediction becomes the
   next input frame and 3. is repeated ``u - 1`` times, with the gradient
   flowing through the predicted frames (backpropagation through the
   rollout: the loss sees how an error grows over ``u`` steps);
5. loss: squared error summed over ``D``, averaged over the real particles of
   the batch and the ``u`` steps (``unroll_loss``: of each step's
   standardised acceleration, or of the predicted position after each step
   divided by the radius and the acceleration std, which compounds over the
   steps: the two forms' logged losses are not comparable); Adam on
   ``params["network"]`` only;
6. optionally (``ema_decay > 0``) the moving average of the network's weights
   follows the updated ones: ``ema <- d * ema + (1 - d) * network``.

:func:`train_step` is pure. If some example's graph needs more than
``batch.capacity`` it does not update anything (``metrics["overflow"]`` is
True, ``state.step`` unchanged): retry the same batch with a larger capacity
(``BatchStream.grow``), as the host convenience :func:`train_step_checked`
does with :func:`dispgns.capacity.drive`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax import lax
from jaxtyping import ArrayLike, PyTree, Shaped

import dispgns
from dispgns._config import check_fields, config_from_mapping
from dispgns.arrays import Count, Flag, Params, PerAxis, PRNGKey, Scalar
from dispgns.capacity import Attempt, drive
from dispgns.graph import merged_edge_count
from dispgns.model import ModelConfig, identity_normalization, init_params
from dispgns.simulator import (
    acceleration_from_output,
    build_graph,
    network_output_batch,
    next_position_batch,
    predict_step_batch,
    sanitize,
)
from dispgns.training.batches import Batch, BatchStream
from dispgns.training.noise import random_walk_noise, target_acceleration
from dispgns.tuning import jitted

# What TrainConfig.unroll_loss may name.
UNROLL_LOSSES = ("acceleration", "position")

# optax's Adam state: a pytree of arrays of any shape and dtype (step counts, moments).
_OptState = PyTree[Shaped[ArrayLike, "..."]]

__all__ = [
    "TrainConfig",
    "TrainState",
    "create_train_state",
    "learning_rate_schedule",
    "loss_fn",
    "make_optimizer",
    "train_step",
    "train_step_checked",
]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (hashable; saved with checkpoints).

    Attributes:
      noise_std: std of the random-walk noise on the last input velocity
        (normalised units per frame), 5e-4 as in the paper.
      batch_size: examples per step (2).
      learning_rate: initial rate (1e-4); the rate is
        ``max(learning_rate * lr_decay ** (step / lr_decay_steps), min_learning_rate)``.
      lr_decay, lr_decay_steps: 0.1 every 2e5 steps, as the authors.
      min_learning_rate: the floor the authors lacked (1e-6).
      standardize: standardise radius-normalised velocities and accelerations
        with dataset statistics (True); False is the authors' recipe.
      pushforward_steps: steps the model advances the inputs without
        gradient before the loss (0).
      unroll_steps: consecutive steps the loss is averaged over, the model's
        own predictions feeding the next with the gradient flowing through
        them (1: the one-step loss); windows then hold ``C +
        pushforward_steps + unroll_steps`` frames. Each step costs about one
        more forward and backward pass of the network, and memory and
        compile time grow with it. The logged training loss is then the mean
        over the steps; the validation's one-step loss stays comparable.
      unroll_loss: what the unrolled loss compares at each of the ``u``
        steps. ``"acceleration"`` (the default): the step's standardised
        acceleration against the true next velocity minus the window's last
        velocity, so a position error carried in from the earlier steps is
        not asked to be undone, only its growth. ``"position"``: the predicted
        position after the step against the true one (shifted by the input
        corruption of the unroll's first window, which is not asked to be
        undone either), in the same standardised units (divided by the
        radius and the acceleration std): an acceleration error at step
        ``i`` then counts again at every later step, with the weight the
        rollout gives it (``j - i + 1`` at step ``j``), so the slowly
        accumulating part of the error weighs more. With ``u = 1`` both are
        the one-step loss (to float rounding of the positions, unless
        ``keep_inside_box`` moves the predicted position).
      mirror_augmentation: reflect each training example on each horizontal
        axis with probability 1/2 (the physics is mirror-symmetric; gravity
        is along the last axis), so that the model sees as many wall
        contacts on one side as on the other (False;
        ``experiments/paper/config.yaml`` turns it on).
      quarter_turn_augmentation: turn each training example by a random
        multiple of 90 degrees about the vertical (last) axis, each of the
        four equally likely (D = 3 only: the cube's walls and gravity are
        unchanged by it). With ``mirror_augmentation`` the model sees all
        eight symmetries of the square floor (False).
      early_windows, early_repeats: the windows starting at the first
        ``early_windows`` frames of each trajectory are drawn
        ``early_repeats`` times per epoch (less the few examples an epoch
        leaves over; 0 and 1, the defaults: every window once). A rollout
        starts from a trajectory's first frames, where its errors have the
        longest to grow, and those windows are few. With ``pushforward_steps = k`` the loss's first target is a
        window's frame ``C + k``: the first ``k`` frames a rollout predicts
        are never targets unless ``k = 0``.
      num_steps: training steps of a full run (2 million in the paper).
      seed: seed of the parameter initialisation, data order and noise.
      log_every: steps between log records (mean loss since the last one).
      validate_every: steps between validations (0: never).
      checkpoint_every: steps between checkpoints (0: only at the end and
        on interruption).
      keep_checkpoints: how many of the latest checkpoints to keep (the best
        by validation is kept apart).
      validation_examples: one-step examples of the valid split scored
        (evenly spaced over it, without noise).
      validation_trajectories: valid trajectories rolled out.
      validation_rollout_frames: frames of each validation rollout.
      ema_decay: decay ``d`` of an exponential moving average of the
        network's weights (Polyak averaging), kept beside them in the state
        and checkpoints: validations, the best checkpoint and the exported
        model use the average (:attr:`TrainState.eval_params`). It spans
        about ``1 / (1 - d)`` steps and starts at the initial weights (the
        ones fine-tuned, or the random ones: then it needs a few spans to
        forget them). 0 (the default) keeps no average.
    """

    noise_std: float = 5e-4
    batch_size: int = 2
    learning_rate: float = 1e-4
    lr_decay: float = 0.1
    lr_decay_steps: float = 2e5
    min_learning_rate: float = 1e-6
    standardize: bool = True
    pushforward_steps: int = 0
    unroll_steps: int = 1
    unroll_loss: str = "acceleration"
    mirror_augmentation: bool = False
    quarter_turn_augmentation: bool = False
    early_windows: int = 0
    early_repeats: int = 1
    num_steps: int = 2_000_000
    seed: int = 0
    log_every: int = 100
    validate_every: int = 2000
    checkpoint_every: int = 2000
    keep_checkpoints: int = 3
    validation_examples: int = 64
    validation_trajectories: int = 3
    validation_rollout_frames: int = 50
    ema_decay: float = 0.0

    def __post_init__(self):
        once = ("batch_size", "num_steps", "log_every", "keep_checkpoints", "unroll_steps", "early_repeats")
        once = dict.fromkeys(once, 1)
        counts = ("validate_every", "checkpoint_every", "validation_examples", "validation_trajectories")
        counts += ("validation_rollout_frames", "pushforward_steps", "early_windows")
        check_fields(
            self,
            integers={**once, **dict.fromkeys(counts, 0)},
            positive=("learning_rate", "lr_decay", "lr_decay_steps"),
            nonnegative=("noise_std", "min_learning_rate", "ema_decay"),
            choices={"unroll_loss": UNROLL_LOSSES},
        )
        if self.ema_decay >= 1.0:
            raise ValueError(f"TrainConfig.ema_decay must lie in [0, 1), got {self.ema_decay!r}")
        if self.min_learning_rate > self.learning_rate:
            raise ValueError(
                f"TrainConfig.min_learning_rate must lie in [0, learning_rate], got {self.min_learning_rate!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> TrainConfig:
        """Build a config from a mapping (numbers may be given as text); unknown keys are an error."""
        return config_from_mapping(cls, values)


def learning_rate_schedule(train_config: TrainConfig) -> Callable[[Count | int], Scalar]:
    """``step -> max(lr * decay ** (step / decay_steps), min_lr)`` (an optax schedule)."""
    c = train_config

    def schedule(step):
        rate = c.learning_rate * c.lr_decay ** (jnp.asarray(step, jnp.float32) / c.lr_decay_steps)
        return jnp.maximum(rate, c.min_learning_rate)

    return schedule


@functools.cache
def make_optimizer(train_config: TrainConfig) -> optax.GradientTransformation:
    """Adam with :func:`learning_rate_schedule` (cached per config, so jit caches stay warm)."""
    return optax.adam(learning_rate_schedule(train_config))


@struct.dataclass
class TrainState:
    """Everything a training run evolves (a pytree; the configs are static).

    Attributes:
      params: ``{"network", "normalization"}`` (see :func:`dispgns.init_params`).
      opt_state: Adam state of ``params["network"]``.
      step: ``()`` int32, optimiser steps taken (= batches consumed).
      model_config, train_config: static.
      ema: ``Params | None``; the moving average of ``params["network"]``
        (the same structure) when ``train_config.ema_decay > 0``, else
        ``None`` (which is then no pytree leaf at all).

    Checkpoint ``params``, ``opt_state``, ``step``, and ``ema`` when it is not
    ``None`` (plus the configs); restore into the structure of
    :func:`create_train_state` for the same ``train_config``.
    """

    params: Params
    opt_state: _OptState
    step: Count
    model_config: ModelConfig = struct.field(pytree_node=False)
    train_config: TrainConfig = struct.field(pytree_node=False)
    ema: Params | None = None

    @property
    def eval_params(self) -> Params:
        """The parameters to validate and export: ``params`` with the moving-average network when there is one."""
        if self.ema is None:
            return self.params
        return {"network": self.ema, "normalization": self.params["normalization"]}

    def with_params(self, params: Params) -> TrainState:
        """This state with new parameters (fine-tuning from a trained model); the moving average restarts at them.

        The optimiser state is kept: Adam's moments start at zero whatever the weights.
        """
        return self.replace(params=params, ema=None if self.ema is None else params["network"])


def create_train_state(
    key: PRNGKey,
    model_config: ModelConfig,
    train_config: TrainConfig,
    normalization: Mapping[str, PerAxis] | None = None,
) -> TrainState:
    """Fresh parameters and optimiser state.

    Args:
      key: PRNG key for the initial weights.
      normalization: statistics from
        :func:`dispgns.training.compute_normalization` (required when
        ``train_config.standardize``; ignored otherwise).
    """
    if train_config.standardize:
        if normalization is None:
            raise ValueError(
                "TrainConfig.standardize is on: pass normalization=compute_normalization(train "
                "trajectories, noise_std=train_config.noise_std), or set standardize=False"
            )
    else:
        normalization = identity_normalization(model_config.dim)
    params = init_params(key, model_config, normalization)
    opt_state = make_optimizer(train_config).init(params["network"])
    return TrainState(
        params=params,
        opt_state=opt_state,
        step=jnp.zeros((), jnp.int32),
        model_config=model_config,
        train_config=train_config,
        ema=params["network"] if train_config.ema_decay > 0 else None,
    )


def _example_keys(key, count: int, axis_name: str | None):
    """The noise keys of this device's ``count`` examples: slices of one split over the whole batch.

    With ``axis_name`` (the batch split over a mesh axis) the whole batch has
    ``count x devices`` examples and this device holds the slice at its index,
    so every example gets the key it would get on one device.
    """
    if axis_name is None:
        return jax.random.split(key, count)
    devices = lax.psum(1, axis_name)
    keys = jax.random.split(key, count * devices)
    return lax.dynamic_slice_in_dim(keys, lax.axis_index(axis_name) * count, count)


def _any(flag, axis_name: str | None):
    """``flag`` or'ed over the devices of ``axis_name`` (all of them skip a step together)."""
    return flag if axis_name is None else lax.psum(flag.astype(jnp.int32), axis_name) > 0


def _noisy_inputs(
    params, batch: Batch, key, model_config: ModelConfig, train_config: TrainConfig, axis_name: str | None = None
):
    """The noisy input windows, advanced ``pushforward_steps`` frames by the model (call with frozen ``params``).

    Returns ``(windows (B, C, N, D), overflow ())``.
    """
    c = model_config.input_sequence_length
    k = train_config.pushforward_steps
    position, radius, mask = batch.position, batch.radius, batch.mask
    keys = _example_keys(key, position.shape[0], axis_name)
    inputs = position[:, :c]
    windows = inputs + jax.vmap(lambda key, x, m: random_walk_noise(key, x, train_config.noise_std, m))(
        keys, inputs, mask
    )
    overflow = jnp.zeros((), bool)
    if k:

        def advance(carry, _):
            windows, overflow = carry
            step = predict_step_batch(
                params,
                windows,
                radius,
                model_config=model_config,
                capacity=batch.capacity,
                mask=mask,
                edge_budget=batch.edge_budget,
            )
            nxt, step_overflow = step.position, step.overflow
            windows = jnp.concatenate([windows[:, 1:], nxt[:, None]], axis=1)
            return (windows, overflow | jnp.any(step_overflow)), None

        (windows, overflow), _ = lax.scan(advance, (windows, overflow), None, length=k)
    return windows, overflow


def _graphs_and_target(params, batch: Batch, windows, frame: int, model_config: ModelConfig):
    """Sanitised inputs, graphs and the standardised target of the step from ``windows`` to batch frame ``frame``.

    Returns ``(inputs (B, C, N, D) sanitised, radius (B, N) sanitised,
    graphs, target (B, N, D), overflow ())``.
    """
    position, radius, mask = batch.position, batch.radius, batch.mask
    x, a = jax.vmap(lambda w, r, m: sanitize(w, r, m, model_config))(windows, radius, mask)
    graphs = jax.vmap(lambda p, m: build_graph(p, m, batch.capacity, model_config))(x[:, -1], mask)
    overflow = jnp.any(graphs.overflow)
    if batch.edge_budget is not None:
        overflow = overflow | (merged_edge_count(graphs, x.shape[2]) > batch.edge_budget)
    target = jax.vmap(target_acceleration)(position[:, frame], position[:, frame - 1], windows) / a[..., None]
    norm = params["normalization"]
    target = (target - norm["acceleration_mean"]) / norm["acceleration_std"]
    # The loss masks padding rows out, but a NaN target there would still come
    # back through the gradient of that masked select (0 * NaN): zero it.
    target = jnp.where(mask[..., None], target, 0.0)
    return x, a, graphs, target, overflow


def loss_fn(
    network: Params,
    normalization: Mapping[str, PerAxis],
    batch: Batch,
    key: PRNGKey,
    model_config: ModelConfig,
    train_config: TrainConfig,
    axis_name: str | None = None,
) -> tuple[Scalar, dict[str, Flag]]:
    """Mean over the real particles of the batch (and the unrolled steps) of the squared error summed over D.

    The ``B`` examples are evaluated as one disjoint graph
    (:func:`dispgns.simulator.network_output_batch`), compacted to
    ``batch.edge_budget`` edge slots when the batch has one. With
    ``train_config.unroll_steps = u > 1`` the loss is the mean of ``u``
    consecutive steps' losses, each step's input window ending with the
    previous steps' predictions, differentiated through them. With
    ``unroll_loss = "acceleration"`` the target of each step is the true next
    velocity minus the window's last velocity
    (:func:`~dispgns.training.noise.target_acceleration`), so a position
    error carried in is not asked to be undone, but its growth is; with
    ``"position"`` each step's predicted position is compared with the true
    one (see :class:`TrainConfig`).

    With ``axis_name`` (inside ``shard_map`` over a mesh axis that splits the
    batch) ``batch`` is this device's part and the value is its share of the
    whole batch's loss (its error sum over the whole batch's particle count):
    the shares and their gradients sum to those of the whole batch.

    Returns ``(loss, {"overflow": bool})``.
    """
    mc, tc = model_config, train_config
    expected = mc.input_sequence_length + tc.pushforward_steps + tc.unroll_steps
    if batch.position.shape[1] != expected:
        raise ValueError(
            f"batch windows have {batch.position.shape[1]} frames, expected C + pushforward_steps + unroll_steps = "
            f"{expected}"
        )
    frozen = lax.stop_gradient({"network": network, "normalization": normalization})
    windows, overflow = _noisy_inputs(frozen, batch, key, mc, tc, axis_name)
    params = {"network": network, "normalization": normalization}
    first = mc.input_sequence_length + tc.pushforward_steps
    by_position = tc.unroll_loss == "position"
    # The corruption the unroll starts from (the noise and pushforward error of its last input frame): the
    # position targets carry it, as the acceleration targets do, so it is not asked to be undone.
    offset = windows[:, -1] - batch.position[:, first - 1] if by_position else None
    error_sum = 0.0
    # u is static and small: a Python loop (the u = 1 case is exactly the one-step loss).
    for step in range(tc.unroll_steps):
        x, a, graphs, target, step_overflow = _graphs_and_target(frozen, batch, windows, first + step, mc)
        overflow = overflow | step_overflow
        output = network_output_batch(params, x, a, graphs, model_config=mc, edge_budget=batch.edge_budget)
        last = step + 1 == tc.unroll_steps
        nxt = None if last and not by_position else _next_frame(params, windows, output, a, batch, mc)
        if by_position:
            # In the output's units: the position error of one step is its acceleration error (to float rounding).
            scale = a[..., None] * frozen["normalization"]["acceleration_std"]
            error = (nxt - (batch.position[:, first + step] + offset)) / scale
        else:
            error = output - target
        error_sum = error_sum + jnp.sum(jnp.where(batch.mask, jnp.sum(error**2, axis=-1), 0.0))
        if not last:
            windows = jnp.concatenate([windows[:, 1:], nxt[:, None]], axis=1)
    count = jnp.sum(batch.mask, dtype=jnp.float32)
    if axis_name is not None:
        count = lax.psum(count, axis_name)
    loss = error_sum / (jnp.maximum(count, 1.0) * tc.unroll_steps)
    return loss, {"overflow": _any(overflow, axis_name)}


def _next_frame(params, windows, output, a, batch: Batch, model_config: ModelConfig):
    """The frame ``(B, N, D)`` after ``windows`` that the standardised ``output`` predicts (differentiable).

    The position update of :func:`dispgns.simulator.predict_step_batch`
    (``a``: the sanitised radii), from the network output the loss has
    already computed, so from the network alone even where the pushforward
    frames are symmetry-averaged (``model_config.symmetrize``; fine-tuning
    turns it off). No overflow poisoning: the caller has the step's flag.
    """
    acc = jax.vmap(lambda y, r: acceleration_from_output(params, y, r))(output, a)
    return next_position_batch(windows, acc, batch.radius, batch.mask, model_config=model_config)


@functools.partial(jax.jit, static_argnames=("axis_name",))
def train_step(
    state: TrainState, batch: Batch, key: PRNGKey, *, axis_name: str | None = None
) -> tuple[TrainState, dict[str, Scalar | Flag]]:
    """One optimiser step (pure and jitted; compiles once per batch shape and capacity).

    Args:
      state: :class:`TrainState`.
      batch: :class:`~dispgns.training.batches.Batch` with ``W = C +
        pushforward_steps + unroll_steps`` frames.
      key: PRNG key of this step's noise; use ``jax.random.fold_in(key0,
        state.step)`` for runs that resume exactly.
      axis_name: static; the mesh axis the batch is split over when the step
        runs inside ``shard_map`` (data parallelism, see
        :mod:`dispgns.training.distributed`): losses, gradients and overflow
        flags are summed over it, so every device makes the same update, that
        of the whole batch. ``None``: the whole batch is here.

    Returns:
      ``(new_state, metrics)``; metrics: ``loss`` (before the update),
      ``grad_norm``, ``learning_rate``, ``overflow`` (True: nothing was
      updated, retry with a larger ``batch.capacity``).
    """
    mc, tc = state.model_config, state.train_config
    normalization = state.params["normalization"]
    (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(
        state.params["network"], normalization, batch, key, mc, tc, axis_name
    )
    if axis_name is not None:
        loss, grads = lax.psum((loss, grads), axis_name)
    tx = make_optimizer(tc)
    updates, opt_state = tx.update(grads, state.opt_state, state.params["network"])
    network = optax.apply_updates(state.params["network"], updates)
    ok = ~aux["overflow"]
    keep = lambda new, old: jax.tree_util.tree_map(lambda n, o: jnp.where(ok, n, o), new, old)
    ema = state.ema
    if ema is not None:
        # optax.incremental_update(new, old, s) = s * new + (1 - s) * old.
        ema = keep(optax.incremental_update(network, ema, 1.0 - tc.ema_decay), ema)
    new_state = state.replace(
        params={"network": keep(network, state.params["network"]), "normalization": normalization},
        opt_state=keep(opt_state, state.opt_state),
        step=state.step + ok.astype(jnp.int32),
        ema=ema,
    )
    metrics = {
        "loss": loss,
        "grad_norm": optax.tree.norm(grads),
        "learning_rate": learning_rate_schedule(tc)(state.step),
        "overflow": aux["overflow"],
    }
    return new_state, metrics


def train_step_checked(
    state: TrainState,
    batch: Batch,
    key: PRNGKey,
    *,
    compiler_options: Mapping[str, Any] | None = None,
    # distributed.py imports this module, so DataParallel is named through the package (resolved when read).
    parallel: dispgns.training.distributed.DataParallel | None = None,
) -> tuple[TrainState, dict[str, Scalar | Flag], Batch]:
    """:func:`train_step` with the graph capacity grown until no graph overflows (host).

    Args:
      state, batch, key: as :func:`train_step`.
      compiler_options: XLA options for the step (e.g.
        :func:`dispgns.tuning.network_compiler_options`).
      parallel: a :class:`dispgns.training.distributed.DataParallel` to split
        the batch over its devices (``state`` replicated on them), or ``None``.

    Returns:
      ``(new_state, metrics, batch)``: the batch actually used (with the
      capacity that fitted).
    """
    step = jitted(train_step, compiler_options) if parallel is None else parallel.step(compiler_options)

    def attempt(state, sizes, _):
        new_state, metrics = step(state, batch.with_capacity(*sizes), key)
        if bool(metrics["overflow"]):
            return Attempt(state, None, 0, True)
        return Attempt(new_state, metrics, 1, False)

    def grow(sizes, _):
        grown = BatchStream.grow(batch.with_capacity(*sizes))
        return grown.capacity, grown.edge_budget

    new_state, (metrics,), sizes = drive(attempt, state, (batch.capacity, batch.edge_budget), grow)
    return new_state, metrics, batch.with_capacity(*sizes)
