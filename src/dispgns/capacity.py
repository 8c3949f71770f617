"""Static capacities: the ladder they are sized on, and the one host loop that grows them.

Compiled code has static shapes: a graph has slots for so many edges, a cell
list for so many particles per cell, the wall step for so many colliding
particles. dispgns follows jax-md: a pure function takes its capacities as
static arguments and returns an ``overflow`` flag instead of dropping work;
growing is the caller's job. This module holds the two pieces every caller
shares.

* :func:`ladder` rounds a size up to a fixed geometric ladder (rungs
  ``ceil(2^(k/4))`` times a quantum, at most ~19 % apart), so that sizes
  fitted to different data repeat and reuse compiled programs.
* :func:`drive` is the host loop: it calls a compiled *attempt* with the
  current capacity, keeps what the attempt computed before it overflowed,
  grows the capacity and goes on from there. The physics, one-step
  predictions, rollouts, training steps and graph features all run through
  it.

The loop, written out for a chunked computation (what :func:`drive` does)::

    state, capacity, outputs, done = start, fitted_capacity, [], 0
    while done < total:
        attempt = run(state, capacity, total - done)   # compiled, static capacity
        outputs.append(attempt.output); done += attempt.done
        state = attempt.state                          # last good state
        if attempt.overflow:
            capacity = grow(capacity, state)           # outside jit, then redo
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from typing import Any, NamedTuple

from jaxtyping import ArrayLike, PyTree, Shaped

__all__ = ["Attempt", "CapacityError", "coarse_ladder", "drive", "ladder"]

# A caller's state or output: any pytree of arrays (positions and velocities, a rollout's frames, ...).
_Tree = PyTree[Shaped[ArrayLike, "..."]]


class CapacityError(RuntimeError):
    """An overflowing capacity that cannot grow (every pair or particle already fits)."""


def ladder(need: int, *, quantum: int = 1) -> int:
    """The smallest ``quantum * ceil(2^(k/4))``, ``k = 0, 1, ...``, that is ``>= need``.

    Rungs are at most ~19 % apart: a size rounded up to them wastes at most
    that, and sizes from different data land on the same few rungs.
    """
    if quantum < 1:
        raise ValueError(f"quantum must be >= 1, got {quantum}")
    units = max(math.ceil(int(need) / quantum), 1)
    k = 4 * (units.bit_length() - 1)
    while math.ceil(2.0 ** (k / 4)) < units:
        k += 1
    return quantum * math.ceil(2.0 ** (k / 4))


def coarse_ladder(need: int) -> int:
    """The smallest ``2^k`` or ``3 x 2^(k-1)`` that is ``>= need`` (rungs up to 50 % apart).

    For small counts whose head-room is cheap (particles per cell), fewer
    rungs mean fewer compilations.
    """
    power = 1 << max(int(need) - 1, 0).bit_length()
    return power * 3 // 4 if power >= 4 and power * 3 // 4 >= need else power


class Attempt(NamedTuple):
    """What one compiled attempt returns to :func:`drive` (host values, not tracers).

    Attributes:
      state: where to go on from: after the last unit of work that fitted
        (the input state when nothing fitted).
      output: what the kept units computed (``None`` when ``done == 0``).
      done: units of work kept (steps, frames, or 1 for a one-shot call).
      overflow: the capacity was too small for the next unit: grow and redo it.
    """

    state: _Tree
    output: _Tree | None
    done: int
    overflow: bool


def drive(
    run: Callable[[Any, Any, int], Attempt],
    state: _Tree,
    capacity: Hashable,
    grow: Callable[[Any, Any], Any],
    *,
    total: int = 1,
    progress: Callable[[int], None] | None = None,
) -> tuple[_Tree, list[_Tree], Hashable]:
    """Run ``run(state, capacity, remaining)`` until ``total`` units are done, growing on overflow.

    Args:
      run: one compiled attempt (see :class:`Attempt`); ``remaining`` is how
        many units are still to do (it may do fewer).
      state: the starting state.
      capacity: the starting capacity (hashable: a jit cache key).
      grow: ``(capacity, state) -> larger capacity`` after an overflow at
        ``state``; returning an equal capacity raises :class:`CapacityError`.
      total: units of work.
      progress: ``progress(done)`` whenever units were kept.

    Returns:
      ``(state, outputs, capacity)``: the final state, the outputs of the
      attempts that kept units (in order), and the capacity that fitted last
      (reuse it for the next call).
    """
    outputs, done = [], 0
    while done < total:
        attempt = run(state, capacity, total - done)
        if attempt.done:
            outputs.append(attempt.output)
            done += int(attempt.done)
            if progress is not None:
                progress(done)
        state = attempt.state
        if attempt.overflow:
            grown = grow(capacity, state)
            if grown == capacity:
                raise CapacityError(
                    f"the capacity {capacity} overflows and cannot grow (everything already fits): "
                    "the positions at that step are probably not finite"
                )
            capacity = grown
        elif not attempt.done:
            raise RuntimeError(f"an attempt made no progress without an overflow ({run!r})")
    return state, outputs, capacity
