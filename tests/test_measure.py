"""The one timer (codecsplat_warp.measure): timed, PhaseTimer and no_timer, as the codec and the commands use them."""

from __future__ import annotations

import time

import pytest
import torch

from codecsplat_warp.measure import PhaseTimer, no_timer, timed

CPU = torch.device("cpu")


def test_timed_returns_the_result_and_the_wall_seconds():
    result, seconds = timed(lambda: time.sleep(0.02) or "done", CPU)
    assert result == "done" and 0.02 <= seconds < 1.0


def test_phase_timer_sums_each_phase_and_counts_a_phase_that_raises():
    timer = PhaseTimer(CPU)
    for _ in range(2):
        with timer("entropy"):
            time.sleep(0.01)
    with pytest.raises(ValueError), timer("bitstream"):
        time.sleep(0.01)
        raise ValueError("stop")
    assert set(timer.seconds) == {"entropy", "bitstream"}
    assert 0.02 <= timer.seconds["entropy"] < 1.0 and 0.01 <= timer.seconds["bitstream"] < 1.0


def test_no_timer_times_nothing():
    with no_timer("entropy") as value:
        assert value is None
