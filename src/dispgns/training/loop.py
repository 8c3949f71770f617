"""The training loop: steps, logging, validation and checkpoints around the pure :func:`train_step`.

Determinism and resume. Step ``s`` (counting from 0) trains on batch ``s`` of
the :class:`~dispgns.training.batches.BatchStream` (a pure function of the
data-order seed and ``s``) with the noise key ``fold_in(key, s)``. A run
restored from a checkpoint at step ``s`` therefore continues exactly as the
uninterrupted run would have (on the same machine and software).

The loop does no I/O of its own: it reports through callbacks (``on_step``
for progress bars, ``on_log`` for log records) and saves through a
:class:`~dispgns.training.checkpoint.Checkpointer`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from dispgns.arrays import Params, PRNGKey, stack_padded
from dispgns.capacity import Attempt, drive
from dispgns.data import Trajectory
from dispgns.metrics import per_frame_mse
from dispgns.model import ModelConfig
from dispgns.simulator import fit_capacity, rollout_batch
from dispgns.training.batches import BatchStream
from dispgns.training.distributed import DataParallel
from dispgns.training.step import TrainConfig, TrainState, loss_fn, train_step_checked
from dispgns.tuning import jitted

__all__ = ["LoopResult", "NonFiniteLossError", "Saver", "Validator", "train"]


class NonFiniteLossError(FloatingPointError):
    """Training stopped: a step's loss (or gradient norm) was NaN or infinite.

    Attributes:
      step: the step whose loss was not finite (counting from 1, as the log does).
      value: that loss.
      state: the last finite state (before that step), already checkpointed when the loop had a
        checkpointer.
    """

    def __init__(self, message: str, *, step: int, value: float, state: TrainState):
        super().__init__(message)
        self.step, self.value, self.state = step, value, state


class Validator:
    """Scores parameters on the valid split: one-step loss and a short rollout MSE.

    * one-step loss: the training loss without noise, pushforward or unrolling, on
      ``train_config.validation_examples`` windows spread evenly over the
      split (one padded batch, one compilation);
    * rollout MSE: the first ``validation_trajectories`` trajectories rolled
      out for ``validation_rollout_frames`` frames from their first ``C``
      frames, mean squared position error over those frames (normalised
      units), all padded to one node budget and one graph capacity so that
      they share one compiled rollout.

    Args:
      trajectories: the valid split (objects with ``.position`` ``(T, N, D)``
        and ``.radius`` ``(N,)``, normalised units).
      model_config, train_config: the run's configs.
    """

    def __init__(
        self,
        trajectories: Sequence[Trajectory],
        model_config: ModelConfig,
        train_config: TrainConfig,
        *,
        compiler_options: Mapping[str, Any] | None = None,
    ):
        self.model_config = model_config
        self.compiler_options = compiler_options
        c = model_config.input_sequence_length
        self.clean_config = dataclasses.replace(
            train_config, noise_std=0.0, pushforward_steps=0, unroll_steps=1, unroll_loss="acceleration"
        )
        self.batch = None
        if train_config.validation_examples > 0:
            stream = BatchStream(
                trajectories,
                input_sequence_length=c,
                batch_size=1,
                connectivity_radius=model_config.connectivity_radius,
                shuffle=False,
                bounds=model_config.bounds,
            )
            count = min(train_config.validation_examples, stream.num_examples)
            ids = np.unique(np.linspace(0, stream.num_examples - 1, count).round().astype(np.int64))
            self.batch = stream.make_batch(ids)
        count = min(train_config.validation_trajectories, len(trajectories))
        chosen = [t for t in trajectories[:count] if t.position.shape[0] > c]
        self.frames = 0
        if chosen:
            self.frames = min([train_config.validation_rollout_frames] + [t.position.shape[0] - c for t in chosen])
        self.rollouts = None
        if self.frames > 0:
            # All padded to one node budget and one capacity: one compiled rollout for the lot.
            position, radius, mask = stack_padded(chosen, frames=c + self.frames)
            capacity = fit_capacity(position, model_config, mask=mask[:, None, :], margin=0.25)
            self.rollouts = (position, radius, mask, capacity)

    def __call__(self, params) -> dict[str, float]:
        out: dict[str, float] = {}
        if self.batch is not None:
            out["valid_one_step_loss"] = float(self._clean_loss(params))
        if self.rollouts is not None:
            c = self.model_config.input_sequence_length
            position, radius, mask, capacity = self.rollouts
            predicted = rollout_batch(
                params,
                position[:, :c],
                radius,
                self.frames,
                model_config=self.model_config,
                mask=mask,
                capacity=capacity,
                compiler_options=self.compiler_options,
            )
            errors = [
                float(jnp.mean(per_frame_mse(jnp.concatenate([x[:c], p]), x, input_frames=c, mask=m)))
                for x, p, m in zip(position, predicted, mask)
            ]
            out["valid_rollout_mse"] = float(np.mean(errors))
            out["valid_rollout_frames"] = self.frames
        return out

    def _clean_loss(self, params) -> float:
        """The one-step loss without noise, on a graph grown until it fits (never a truncated one)."""
        loss = jitted(_clean_loss, self.compiler_options, static_argnames=("model_config", "train_config"))

        def attempt(_, sizes, __):
            value, overflow = loss(
                params, self.batch.with_capacity(*sizes), model_config=self.model_config, train_config=self.clean_config
            )
            return Attempt(None, None, 0, True) if bool(overflow) else Attempt(None, float(value), 1, False)

        def grow(sizes, _):
            grown = BatchStream.grow(self.batch.with_capacity(*sizes))
            return grown.capacity, grown.edge_budget

        _, (value,), sizes = drive(attempt, None, (self.batch.capacity, self.batch.edge_budget), grow)
        self.batch = self.batch.with_capacity(*sizes)
        return value


def _clean_loss(params, batch, *, model_config, train_config):
    loss, aux = loss_fn(
        params["network"], params["normalization"], batch, jax.random.key(0), model_config, train_config
    )
    return loss, aux["overflow"]


class Saver(Protocol):
    """What :func:`train` needs of a checkpointer (:class:`~dispgns.training.checkpoint.Checkpointer` is one)."""

    def save(
        self,
        state: TrainState,
        key: PRNGKey,
        *,
        data_position: int,
        validation: Mapping[str, Any] | None = None,
        validation_value: float | None = None,
    ) -> None: ...


@dataclasses.dataclass
class LoopResult:
    """What :func:`train` returns: the final state and why it stopped."""

    state: TrainState
    interrupted: bool
    last_validation: dict[str, Any]


def train(
    state: TrainState,
    stream: BatchStream,
    key: PRNGKey,
    *,
    until_step: int | None = None,
    validator: Callable[[Params], Mapping[str, Any]] | None = None,
    checkpointer: Saver | None = None,
    on_step: Callable[[int, Mapping[str, float]], None] | None = None,
    on_log: Callable[[Mapping[str, Any]], None] | None = None,
    compiler_options: Mapping[str, Any] | None = None,
    parallel: DataParallel | None = None,
) -> LoopResult:
    """Train from ``state.step`` up to ``until_step`` (default ``train_config.num_steps``).

    Every ``log_every`` steps ``on_log`` gets ``{"kind": "train", "step",
    "loss" (mean since the last record), "grad_norm", "learning_rate",
    "steps_per_s", "elapsed_s", "cpu_s"}`` (wall and CPU seconds of this
    process since ``train`` was called: a resumed run starts again from 0,
    so accuracy per CPU-hour sums the segments); every ``validate_every`` steps (and at the
    end) ``validator(params)`` runs and the state is checkpointed and ``on_log`` gets ``{"kind":
    "validation", "step", ...metrics}``; every ``checkpoint_every`` steps, at
    the end and on ``KeyboardInterrupt`` the checkpointer saves (the best
    checkpoint is judged by ``valid_rollout_mse``, else the one-step loss).
    A step whose loss or gradient norm is not finite stops training: the
    state before it (the last finite one) is checkpointed and
    :class:`NonFiniteLossError` is raised, naming the step.

    ``on_log`` is the hook for your own logging (any callable); the command
    line passes the JSONL log and, with ``--logger``, the loggers of
    :mod:`dispgns.training.loggers` (TensorBoard, W&B) through it.

    Args:
      state: where to start (fresh or restored).
      stream: the training batches; its position is set to ``state.step``.
      key: the run's base PRNG key.
      until_step: last step (exclusive bound on steps taken).
      validator: e.g. a :class:`Validator`.
      checkpointer: a :class:`~dispgns.training.checkpoint.Checkpointer` or ``None``.
      on_step: ``(step, {"loss", "learning_rate"})`` after every step.
      on_log: receives every log record.
      compiler_options: XLA options for the training step (e.g.
        :func:`dispgns.tuning.network_compiler_options`).
      parallel: a :class:`dispgns.training.distributed.DataParallel`: every
        batch split over its devices (``state`` replicated on them; the
        stream built with ``shards`` = its device count); each process reads
        only its part of every batch. ``None``: one device.

    Returns:
      :class:`LoopResult`. On ``KeyboardInterrupt`` the state is checkpointed
      and returned with ``interrupted = True`` (the caller decides the exit
      code).
    """
    tc = state.train_config
    until = tc.num_steps if until_step is None else int(until_step)
    log = on_log or (lambda record: None)
    step = int(state.step)
    stream.position = step
    start_time = time.perf_counter()
    start_cpu = time.process_time()
    window_start, window_step = start_time, step
    losses, norms = [], []
    last_validation: dict[str, Any] = {}
    validated_at = checkpointed_at = None

    def validate():
        nonlocal last_validation, validated_at
        if validator is None or validated_at == step:
            return
        params = state.eval_params  # the moving average of the weights, when the run keeps one
        metrics = dict(validator(params if parallel is None else parallel.local(params)))
        last_validation = {
            "kind": "validation",
            "step": step,
            **metrics,
            "elapsed_s": time.perf_counter() - start_time,
            "cpu_s": time.process_time() - start_cpu,
        }
        validated_at = step
        log(last_validation)

    def checkpoint():
        nonlocal checkpointed_at
        if checkpointer is None or checkpointed_at == step:
            return
        value = None
        if validated_at == step:
            value = last_validation.get("valid_rollout_mse", last_validation.get("valid_one_step_loss"))
        checkpointer.save(state, key, data_position=stream.position, validation=last_validation, validation_value=value)
        checkpointed_at = step

    interrupted = False
    try:
        while step < until:
            if parallel is None:
                batch = stream.batch(step)
            else:
                batch = parallel.global_batch(stream.batch(step, parallel.local_examples(stream.batch_size)))
            previous = state
            state, metrics, _ = train_step_checked(
                state, batch, jax.random.fold_in(key, step), compiler_options=compiler_options, parallel=parallel
            )
            loss = float(metrics["loss"])
            if not (math.isfinite(loss) and math.isfinite(float(metrics["grad_norm"]))):
                # Keep the last finite state: checkpoint it, then stop with the step named.
                state = previous
                checkpoint()
                saved = f"a checkpoint of step {step} (the last finite state) is saved" if checkpointer else ""
                raise NonFiniteLossError(
                    f"training stopped: the loss is {loss} (gradient norm {float(metrics['grad_norm'])}) at step "
                    f"{step + 1}; {saved or 'nothing was saved (no checkpointer)'}. Lower the learning rate or "
                    f"check the data, then resume.",
                    step=step + 1,
                    value=loss,
                    state=state,
                )
            step += 1
            stream.position = step
            losses.append(loss)
            norms.append(float(metrics["grad_norm"]))
            if on_step is not None:
                on_step(step, {"loss": loss, "learning_rate": float(metrics["learning_rate"])})
            if step % tc.log_every == 0 or step == until:
                now = time.perf_counter()
                log(
                    {
                        "kind": "train",
                        "step": step,
                        "loss": float(np.mean(losses)),
                        "grad_norm": float(np.mean(norms)),
                        "learning_rate": float(metrics["learning_rate"]),
                        "steps_per_s": (step - window_step) / max(now - window_start, 1e-9),
                        "elapsed_s": now - start_time,
                        "cpu_s": time.process_time() - start_cpu,
                    }
                )
                losses, norms = [], []
                window_start, window_step = now, step
            validating = bool(tc.validate_every) and step % tc.validate_every == 0
            if validating:
                validate()
            # Also after every validation, whatever checkpoint_every says: the best checkpoint is
            # judged (and saved) only when a validation and a save fall on the same step.
            if validating or (tc.checkpoint_every and step % tc.checkpoint_every == 0):
                checkpoint()
        validate()
        checkpoint()
    except KeyboardInterrupt:
        interrupted = True
        checkpoint()
    return LoopResult(state=state, interrupted=interrupted, last_validation=last_validation)
