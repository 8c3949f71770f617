"""Evaluation of a learned simulator on whole dataset splits (full rollouts, metrics, references).

:func:`evaluate_trajectories` rolls a model out over every trajectory of a
split, from its first ``C`` ground-truth frames to its last frame, batched
(trajectories padded to one node budget, ``rollout_batch`` in groups of
equal size, so one compilation serves the split), and scores each rollout
with :func:`dispgns.metrics.rollout_metrics` next to two references:

* the constant-velocity baseline (always);
* the chaos floor (where the trajectories carry their exact initial state):
  the ground-truth physics re-run from that state with every centre
  perturbed by ``1e-6 L``, in the precision the dataset was generated in
  (:func:`chaos_floor_rollout` for one trajectory, :func:`chaos_floor_trajectories`
  for a split).

Units: normalised box units for positions and MSEs, as everywhere in the
learned simulator; ``rollout_metrics`` adds millimetres and diameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dispgns.arrays import Frame, Params, ParticleMask, Positions, PRNGKey, Radii, node_budget, stack_padded
from dispgns.data import Trajectory
from dispgns.metrics import rollout_metrics, summarize
from dispgns.model import ModelConfig
from dispgns.physics import PhysicsConfig, simulate, simulate_batch
from dispgns.simulator import rollout_batch

__all__ = [
    "CHAOS_PERTURBATION",
    "chaos_floor_rollout",
    "chaos_floor_trajectories",
    "evaluate_trajectories",
    "perturb_positions",
    "predict_trajectories",
]

CHAOS_PERTURBATION = 1e-6
"""Initial-position perturbation of the chaos floor, in units of ``L``."""


def chaos_floor_rollout(
    initial_position: Frame,
    initial_velocity: Frame,
    radius: Radii,
    config: PhysicsConfig,
    *,
    key: PRNGKey | int,
    n_frames: int,
    save_every: int = 15,
    perturbation: float = 1e-6,
    mask: ParticleMask | None = None,
    x64: bool = True,
    length_scale: float | None = None,
    **simulate_kwargs: Any,
) -> Positions:
    """Re-run the ground truth from a slightly perturbed initial state.

    The suspension is chaotic: two exact simulations whose initial positions
    differ by ``1e-6 L`` separate over the trajectory. The error of the
    perturbed run against the stored truth (computed with the same metrics
    as a model) is a floor that even a perfect model could not beat.

    Every coordinate of every real particle is shifted by an independent
    normal draw of standard deviation ``perturbation * L``, then kept inside
    the wall contact positions ``[-L + a_i, L - a_i]`` (a no-op unless a
    particle starts within the perturbation of a wall). With
    ``perturbation = 0`` the result is exactly ``simulate(...) / L``.

    Args:
      initial_position: ``(N, D)`` stored exact initial centres in m (SI,
        float64, as stored in the dataset, not the normalised frames).
      initial_velocity: ``(N, D)`` in m/s. radius: ``(N,)`` in m.
      config: the :class:`PhysicsConfig` the truth was generated with.
      key: a ``jax.random`` key (or an int seed).
      n_frames: frames to return (frame 0 is the perturbed initial state).
      save_every: Euler steps between frames (15 in the paper).
      perturbation: standard deviation of the shift, in units of ``L``.
      mask: optional ``(N,)`` bool for padded particles.
      x64: run in float64 (inside ``jax.enable_x64(True)``), as the data
        generator does; ``False`` runs in the session's precision.
      **simulate_kwargs: passed to :func:`dispgns.physics.simulate`
        (e.g. ``collision_capacity``, ``chunk_frames``).

    Returns:
      ``(n_frames, N, D)`` numpy array of positions divided by ``L`` (float64
      with ``x64``), directly comparable with the stored normalised truth.
    """
    if isinstance(key, (int, np.integer)):
        key = jax.random.PRNGKey(int(key))
    half = config.height if length_scale is None else length_scale
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        x0 = jnp.asarray(np.asarray(initial_position), dtype)
        v0 = jnp.asarray(np.asarray(initial_velocity), dtype)
        a = jnp.asarray(np.asarray(radius), dtype)
        if x0.ndim != 2 or v0.shape != x0.shape or a.shape != x0.shape[:1]:
            raise ValueError(
                f"expected initial_position (N, D), initial_velocity (N, D) and radius (N,), got "
                f"{x0.shape}, {v0.shape} and {a.shape}"
            )
        shifted = perturb_positions(key, x0, a, config, perturbation=perturbation, mask=mask, length_scale=half)
        frames = simulate(
            shifted, v0, a, config, n_frames=n_frames, save_every=save_every, mask=mask, **simulate_kwargs
        )
        return np.asarray(frames) / half


def perturb_positions(
    key: PRNGKey,
    initial_position: Frame,
    radius: Radii,
    config: PhysicsConfig,
    *,
    perturbation: float = 1e-6,
    mask: ParticleMask | None = None,
    length_scale: float | None = None,
) -> Frame:
    """Initial centres shifted by independent normal draws of std ``perturbation * L`` (the chaos floor's start).

    Shifted centres are kept inside the wall contact positions ``[-L + a_i,
    L - a_i]`` (only where the noise pushed them across), so an unperturbed
    or padding particle keeps its exact position.

    Args:
      key: a ``jax.random`` key.
      initial_position: ``(N, D)`` centres in m. radius: ``(N,)`` in m.
      perturbation: std in units of ``L`` (finite, >= 0).
      mask: optional ``(N,)`` bool; padding particles are not moved.
      length_scale: ``L`` in m (``None``: the box's vertical half-size,
        ``config.height``, the paper's ``L``). The walls are those of
        ``config`` (one half-size per axis in a rectangular box).

    Returns:
      ``(N, D)`` shifted centres in m, in the dtype of ``initial_position``.
    """
    if perturbation < 0 or not math.isfinite(perturbation):
        raise ValueError(f"perturbation must be a finite number >= 0 (units of L), got {perturbation!r}")
    x0 = jnp.asarray(initial_position)
    a = jnp.asarray(radius, x0.dtype)
    scale = config.height if length_scale is None else length_scale
    noise = jax.random.normal(key, x0.shape, x0.dtype) * (perturbation * scale)
    if mask is not None:
        noise = jnp.where(jnp.asarray(mask, bool)[:, None], noise, 0.0)
    shifted = x0 + noise
    half = jnp.asarray(config.half_sizes(x0.shape[-1]), x0.dtype)
    lower, upper = -half + a[:, None], half - a[:, None]
    shifted = jnp.where((shifted > upper) & (x0 <= upper), upper, shifted)
    return jnp.where((shifted < lower) & (x0 >= lower), lower, shifted)


def predict_trajectories(
    params: Params,
    trajectories: Sequence[Trajectory],
    *,
    model_config: ModelConfig,
    n_frames: int | None = None,
    batch_size: int = 6,
    progress: Callable[[int], None] | None = None,
    compiler_options: Mapping[str, Any] | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> list[Positions]:
    """Full rollouts of ``trajectories`` from their first ``C`` frames.

    Args:
      params: the model's parameters.
      trajectories: objects with ``.position`` ``(T, N, D)`` and ``.radius``
        ``(N,)`` (normalised units), all with at least ``n_frames`` frames.
      n_frames: frames of each returned rollout, inputs included (``None``:
        the shortest trajectory's ``T``).
      batch_size: trajectories rolled out together (the last group is padded
        with repeats so every group compiles to the same program).
      progress: ``progress(steps)`` with the number of model steps just done.
      compiler_options: XLA options for the rollouts (e.g.
        :func:`dispgns.tuning.network_compiler_options`).
      mesh: a 1-D mesh of this process's devices to spread each group's
        trajectories over (``batch_size`` is rounded up to a multiple of its
        size); ``None``: one device.

    Returns:
      One ``(n_frames, N, D)`` float32 array per trajectory: frames ``0 ..
      C-1`` are the given inputs, the rest predicted.
    """
    trajectories = list(trajectories)
    if not trajectories:
        return []
    c = model_config.input_sequence_length
    frames = min(t.position.shape[0] for t in trajectories) if n_frames is None else int(n_frames)
    if frames <= c or any(t.position.shape[0] < frames for t in trajectories):
        raise ValueError(f"every trajectory needs more than C = {c} frames and at least n_frames = {frames}")
    budget = node_budget([t.position.shape[1] for t in trajectories])
    batch_size = max(1, min(batch_size, len(trajectories)))
    if mesh is not None:
        batch_size = mesh.devices.size * math.ceil(batch_size / mesh.devices.size)
    out = []
    for start in range(0, len(trajectories), batch_size):
        group = trajectories[start : start + batch_size]
        filled = group + [group[-1]] * (batch_size - len(group))
        position, radius, mask = stack_padded(filled, frames=c, budget=budget)
        last, members = [0], len(group)

        def step_progress(done, last=last, members=members):
            if progress is not None:
                progress(members * (done - last[0]))
            last[0] = done

        predicted = np.asarray(
            rollout_batch(
                params,
                position,
                radius,
                frames - c,
                model_config=model_config,
                mask=mask,
                progress=step_progress,
                compiler_options=compiler_options,
                mesh=mesh,
            )
        )
        for k, traj in enumerate(group):
            n = traj.position.shape[1]
            out.append(np.concatenate([np.asarray(traj.position[:c], np.float32), predicted[k, :, :n]], axis=0))
    return out


def _from_every_process(mine: list[np.ndarray], trajectories: Sequence[Any], frames: int) -> list[np.ndarray]:
    """Every trajectory's array, from the arrays each process computed for its share ``p::P`` (``(T, N_k, D)``)."""
    processes = jax.process_count()
    if processes == 1:
        return mine
    from jax.experimental import multihost_utils

    count = math.ceil(len(trajectories) / processes)
    dim = trajectories[0].position.shape[-1]
    budget = max(t.position.shape[1] for t in trajectories)
    stacked = np.zeros((count, frames, budget, dim), np.float32)
    for k, array in enumerate(mine):
        stacked[k, :, : array.shape[1]] = array
    everyone = np.asarray(multihost_utils.process_allgather(stacked))  # (processes, count, T, budget, D)
    return [everyone[k % processes, k // processes, :, : t.position.shape[1]] for k, t in enumerate(trajectories)]


def chaos_floor_trajectories(
    trajectories: Sequence[Trajectory],
    physics_config: PhysicsConfig,
    *,
    n_frames: int,
    save_every: int,
    seed: int = 0,
    perturbation: float = CHAOS_PERTURBATION,
    x64: bool = False,
    compiler_options: Mapping[str, Any] | None = None,
    length_scale: float | None = None,
) -> list[Positions]:
    """The ground truth re-run from each trajectory's perturbed initial state, in one batched simulation.

    Args:
      trajectories: objects with ``initial_position`` ``(N, D)`` (m),
        ``initial_velocity`` ``(N, D)`` (m/s) and ``initial_radius`` ``(N,)``
        (m), e.g. dataset :class:`~dispgns.data.Trajectory` objects.
      physics_config: the physics the dataset was generated with.
      n_frames, save_every: frames to return and Euler steps between them.
      seed: trajectory ``k`` is perturbed with ``fold_in(PRNGKey(seed), k)``.
      perturbation: std of the shift in units of ``L``.
      x64: simulate in float64 (use the dataset's generation precision).
      compiler_options: XLA options for the physics (e.g.
        :func:`dispgns.tuning.physics_compiler_options`).

    Returns:
      One ``(n_frames, N, D)`` array per trajectory, normalised by ``L``.
    """
    trajectories = list(trajectories)
    if not trajectories:
        return []
    # Positions are returned in units of L (default: the vertical half-size, the paper's L).
    half = physics_config.height if length_scale is None else length_scale
    budget = max(t.initial_position.shape[0] for t in trajectories)
    dim = trajectories[0].initial_position.shape[1]
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        x0 = np.zeros((len(trajectories), budget, dim))
        v0 = np.zeros_like(x0)
        radius = np.full((len(trajectories), budget), float(np.min(trajectories[0].initial_radius)))
        mask = np.zeros((len(trajectories), budget), bool)
        for k, traj in enumerate(trajectories):
            n = traj.initial_position.shape[0]
            key = jax.random.fold_in(jax.random.PRNGKey(seed), k)
            shifted = perturb_positions(
                key,
                jnp.asarray(traj.initial_position, dtype),
                jnp.asarray(traj.initial_radius, dtype),
                physics_config,
                perturbation=perturbation,
                length_scale=half,
            )
            x0[k, :n] = np.asarray(shifted)
            v0[k, :n] = traj.initial_velocity
            radius[k, :n] = traj.initial_radius
            mask[k, :n] = True
            # Padding rows: parked where the physics puts them; they never touch real particles.
        frames = simulate_batch(
            jnp.asarray(x0, dtype),
            jnp.asarray(v0, dtype),
            jnp.asarray(radius, dtype),
            jnp.asarray(mask),
            physics_config,
            n_frames=n_frames,
            save_every=save_every,
            compiler_options=compiler_options,
        )
        frames = np.asarray(frames)
    return [frames[k, :, : t.initial_position.shape[0]] / half for k, t in enumerate(trajectories)]


def evaluate_trajectories(
    params: Params,
    trajectories: Sequence[Trajectory],
    *,
    model_config: ModelConfig,
    box_half_size: float,
    frame_dt: float,
    physics_config: PhysicsConfig | None = None,
    save_every: int = 15,
    chaos_floor: bool = True,
    chaos_x64: bool = False,
    n_frames: int | None = None,
    batch_size: int = 6,
    progress: Callable[[str, int], None] | None = None,
    compiler_options: Mapping[str, Any] | None = None,
    physics_compiler_options: Mapping[str, Any] | None = None,
    mesh: jax.sharding.Mesh | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
    statistics: bool = False,
) -> dict[str, Any]:
    """Roll out and score every trajectory of a split.

    Args:
      params, model_config: the model.
      trajectories: the split (normalised positions; the initial state is
        used for the chaos floor when every trajectory has one).
      box_half_size: the length scale ``L`` in m positions are divided by
        (the dataset's ``length_scale``). frame_dt: s between frames.
      physics_config: the dataset's physics (needed for the chaos floor and
        the kinetic energy; default :class:`PhysicsConfig`).
      save_every: Euler steps between frames of the dataset.
      chaos_floor: compute the chaos-floor reference where possible.
      chaos_x64: re-run the physics in float64.
      n_frames: evaluate the first ``n_frames`` frames only (``None``: all).
      batch_size: trajectories rolled out together.
      progress: ``progress(stage, amount)``; stage ``"rollout"`` (model
        steps) or ``"chaos"`` (trajectories).
      compiler_options, physics_compiler_options: XLA options for the
        rollouts and the chaos floor's physics (:mod:`dispgns.tuning`).
      mesh: a 1-D mesh of this process's devices to spread the rollouts over
        (see :func:`predict_trajectories`). In a multi-process run
        (``jax.distributed``) every process calls this with the same split;
        process ``p`` of ``P`` computes trajectories ``p, p + P, ...`` and the
        results are gathered (``jax.experimental.multihost_utils``), so every
        process returns the whole split.
      bounds: the dataset's box in normalised units, for the wall
        violations (``None``: ``model_config.bounds``).
      statistics: add the suspension statistics of
        :func:`dispgns.metrics.rollout_metrics` (front and settling velocity,
        final bed, g(r), Sinkhorn divergence and MMD) for the model, the
        constant-velocity baseline and the chaos floor side by side.

    Returns:
      ``{"predictions": [(T, N, D), ...], "metrics": [rollout_metrics dict,
      ...], "summary": summarize(metrics), "chaos_floor": bool}``.
    """
    physics_config = PhysicsConfig() if physics_config is None else physics_config
    trajectories = list(trajectories)
    report = progress or (lambda stage, amount: None)
    frames = min(t.position.shape[0] for t in trajectories) if n_frames is None else int(n_frames)
    mine = trajectories[jax.process_index() :: jax.process_count()]
    predictions = predict_trajectories(
        params,
        mine,
        model_config=model_config,
        n_frames=frames,
        batch_size=batch_size,
        progress=lambda steps: report("rollout", steps),
        compiler_options=compiler_options,
        mesh=mesh,
    )
    with_chaos = chaos_floor and all(getattr(t, "initial_position", None) is not None for t in trajectories)
    chaos = [None] * len(mine)
    if with_chaos:
        chaos = chaos_floor_trajectories(
            mine,
            physics_config,
            n_frames=frames,
            save_every=save_every,
            x64=chaos_x64,
            compiler_options=physics_compiler_options,
            length_scale=box_half_size,
        )
        report("chaos", len(mine))
    predictions = _from_every_process(predictions, trajectories, frames)
    chaos = _from_every_process(chaos, trajectories, frames) if with_chaos else [None] * len(trajectories)
    metrics = []
    for traj, predicted, floor in zip(trajectories, predictions, chaos):
        metrics.append(
            rollout_metrics(
                predicted,
                np.asarray(traj.position[:frames], np.float32),
                np.asarray(traj.radius, np.float32),
                box_half_size=box_half_size,
                input_frames=model_config.input_sequence_length,
                frame_dt=frame_dt,
                chaos_floor=None if floor is None else np.asarray(floor, np.float32),
                physics_config=physics_config,
                bounds=model_config.bounds if bounds is None else bounds,
                statistics=statistics,
            )
        )
    return {"predictions": predictions, "metrics": metrics, "summary": summarize(metrics), "chaos_floor": with_chaos}
