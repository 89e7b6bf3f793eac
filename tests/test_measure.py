"""The one timer (codecsplat_warp.measure): timed, PhaseTimer and no_timer, as the codec and the commands use them.

The timers are checked with a scripted clock, not against the wall clock: what they record (the difference of the
clock's readings around each call or phase, in order) is exact, and a loaded machine cannot change it."""

from __future__ import annotations

import inspect
import time

import pytest
import torch

from codecsplat_warp.measure import PhaseTimer, no_timer, timed

CPU = torch.device("cpu")


class ScriptedClock:
    """A clock that returns ``readings`` one after another and logs each read as ``"clock"`` in ``events``."""

    def __init__(self, readings: list[float], events: list[str]):
        self.readings = iter(readings)
        self.events = events

    def __call__(self) -> float:
        self.events.append("clock")
        return next(self.readings)


def test_timed_returns_the_result_and_the_clock_difference_around_the_call():
    """Catches: a clock read inside the call or not at all, or seconds other than the end reading minus the start."""
    events: list[str] = []
    result, seconds = timed(lambda: events.append("call") or "done", CPU, ScriptedClock([10.0, 12.5], events))
    assert result == "done" and seconds == 2.5
    assert events == ["clock", "call", "clock"]


def test_phase_timer_sums_each_phase_and_counts_a_phase_that_raises():
    """Catches: a phase's later run replacing its earlier one instead of adding to it, a raising phase left
    uncounted or its exception swallowed, or clock reads outside the phase they time."""
    events: list[str] = []
    timer = PhaseTimer(CPU, ScriptedClock([1.0, 1.25, 2.0, 2.5, 3.0, 4.0], events))
    for _ in range(2):
        with timer("entropy"):
            events.append("entropy")
    with pytest.raises(ValueError, match="stop"), timer("bitstream"):
        events.append("bitstream")
        raise ValueError("stop")
    assert timer.seconds == {"entropy": 0.75, "bitstream": 1.0}
    assert events == ["clock", "entropy", "clock"] * 2 + ["clock", "bitstream", "clock"]


def test_the_timers_read_the_monotonic_performance_counter_by_default():
    """Catches: a default clock that can step backwards or is coarse (``time.time``), for every caller that passes
    no clock (the codec, the commands, the benchmarks)."""
    assert inspect.signature(timed).parameters["clock"].default is time.perf_counter
    assert inspect.signature(PhaseTimer).parameters["clock"].default is time.perf_counter
    assert PhaseTimer(CPU).clock is time.perf_counter


def test_no_timer_times_nothing():
    with no_timer("entropy") as value:
        assert value is None
