"""Training noise (random walk on the input positions) and the noise-corrected targets.

Units: normalised box units, frames as time (dt = 1 per frame).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from dispgns.arrays import Frame, ParticleMask, PositionWindow, PRNGKey

__all__ = [
    "random_walk_noise",
    "target_acceleration",
]


def random_walk_noise(
    key: PRNGKey, position_seq: PositionWindow, noise_std: float, mask: ParticleMask | None = None
) -> PositionWindow:
    """Random-walk noise for a sequence of input positions (DeepMind's GNS recipe).

    Each of the ``C - 1`` velocities gets i.i.d. Gaussian increments of std
    ``noise_std / sqrt(C - 1)``, cumulated over time, so the last velocity is
    perturbed by ``noise_std``; the position noise is the cumulative sum of
    the velocity noise, zero at the first frame.

    Args:
      key: PRNG key.
      position_seq: ``(C, N, D)`` positions (only shape and dtype are used).
      noise_std: std of the noise on the last input velocity (normalised
        units per frame; 5e-4 in the paper).
      mask: optional ``(N,)`` bool; padding particles get no noise.

    Returns:
      ``(C, N, D)`` noise to add to ``position_seq``.
    """
    c = position_seq.shape[0]
    shape = (c - 1,) + position_seq.shape[1:]
    step_std = noise_std / jnp.sqrt(jnp.asarray(c - 1, position_seq.dtype))
    velocity_noise = jnp.cumsum(jax.random.normal(key, shape, position_seq.dtype) * step_std, axis=0)
    position_noise = jnp.concatenate([jnp.zeros_like(velocity_noise[:1]), jnp.cumsum(velocity_noise, axis=0)], axis=0)
    if mask is not None:
        position_noise = jnp.where(jnp.asarray(mask)[None, :, None], position_noise, 0.0)
    return position_noise


def target_acceleration(next_position: Frame, last_position: Frame, input_seq: PositionWindow) -> Frame:
    """Acceleration the model must predict from (possibly corrupted) inputs, per frame^2.

    ``(x_next - x_last) - (x~_last - x~_prev)``: the true next velocity
    minus the last input velocity. With noisy inputs ``x~ = x + n`` this is
    the paper's ``((x_next + n_last) - x~_last) - (x~_last - x~_prev)``: the
    next position is shifted by the last input's noise, so the model learns to
    correct the velocity but not the position error. The same formula serves
    inputs that come from the model's own predictions (pushforward).

    Args:
      next_position: ``(N, D)`` ground-truth position after the last input.
      last_position: ``(N, D)`` ground-truth (clean) last input position.
      input_seq: ``(C, N, D)`` inputs the model sees.

    Returns:
      ``(N, D)`` acceleration (not divided by the radius).
    """
    return (next_position - last_position) - (input_seq[-1] - input_seq[-2])
