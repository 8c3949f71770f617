"""The capacity ladder and the one host driver that grows capacities."""

import math

import pytest

from dispgns.capacity import Attempt, CapacityError, coarse_ladder, drive, ladder


def test_the_ladder_rounds_up_at_most_one_rung():
    rungs = set()
    for need in range(0, 50_000, 13):
        rung = ladder(need, quantum=64)
        assert rung >= need and rung % 64 == 0
        assert rung <= max(64 * math.ceil(need / 64) * 1.19, 64 * math.ceil(need / 64) + 64)
        assert ladder(rung, quantum=64) == rung  # a rung maps to itself
        rungs.add(rung)
    assert len(rungs) < 50
    for need in range(1, 5000):
        rung = coarse_ladder(need)
        assert need <= rung <= max(1.5 * need, 2) and coarse_ladder(rung) == rung
    with pytest.raises(ValueError, match="quantum"):
        ladder(10, quantum=0)


def _counting_run(limits, log):
    """An attempt that may do up to ``capacity`` units per call and overflows beyond ``limits[position]``."""

    def run(position, capacity, remaining):
        log.append((position, capacity, remaining))
        done = 0
        while done < min(remaining, 5):  # at most 5 units per attempt (a chunk)
            if limits[position + done] > capacity:
                return Attempt(position + done, list(range(position, position + done)) or None, done, True)
            done += 1
        return Attempt(position + done, list(range(position, position + done)), done, False)

    return run


def test_drive_keeps_what_fitted_grows_and_redoes_only_the_overflowing_unit():
    limits = [1, 1, 2, 1, 4, 4, 1, 1, 9, 1, 1, 1]
    log, progress = [], []
    state, outputs, capacity = drive(
        _counting_run(limits, log), 0, 1, lambda c, s: 2 * c, total=len(limits), progress=progress.append
    )
    assert state == len(limits) and capacity == 16
    assert [unit for chunk in outputs for unit in chunk] == list(range(len(limits)))
    assert progress == sorted(progress) and progress[-1] == len(limits)
    # Every overflow is followed by an attempt from the unit that overflowed, with a larger capacity.
    for (pos, cap, _), (next_pos, next_cap, _) in zip(log, log[1:]):
        assert next_pos >= pos and next_cap >= cap


def test_drive_refuses_a_capacity_that_cannot_grow():
    with pytest.raises(CapacityError, match="cannot grow"):
        drive(_counting_run([1, 5], []), 0, 2, lambda c, s: min(c * 2, 4), total=2)


def test_a_one_shot_attempt():
    calls = []

    def run(state, capacity, remaining):
        calls.append(capacity)
        if capacity < 3:
            return Attempt(state, None, 0, True)
        return Attempt(state, "result", 1, False)

    assert drive(run, "s", 1, lambda c, s: c + 1) == ("s", ["result"], 3)
    assert calls == [1, 2, 3]
