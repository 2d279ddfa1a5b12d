"""The simulated clock the driver unit tests run on: time moves only in sleep, timers fire in order."""

from __future__ import annotations

import pytest
from piper_can.clock import SYSTEM_CLOCK, SimulatedClock


def test_time_moves_only_in_sleep_and_timers_fire_at_their_due_times_in_order():
    clock = SimulatedClock(start=10.0)
    fired: list[tuple[str, float]] = []
    clock.every(0.005, lambda: fired.append(("fast", clock.time())))
    clock.every(0.010, lambda: fired.append(("slow", clock.time())))
    assert clock.time() == clock.monotonic() == 10.0 and fired == []
    clock.sleep(0.012)
    assert fired == [("fast", 10.005), ("fast", 10.01), ("slow", 10.01)]  # a tie: registration order
    assert clock.time() == 10.012
    clock.sleep(0.0)
    assert len(fired) == 3
    clock.sleep(1.0)
    fast = [t for name, t in fired if name == "fast"]
    assert len(fast) == 202 and fast[-1] == pytest.approx(11.01, abs=1e-12)  # no drift over 200 periods


def test_bad_periods_and_negative_sleeps_are_refused():
    clock = SimulatedClock()
    with pytest.raises(ValueError, match="period_s must be positive"):
        clock.every(0.0, lambda: None)
    with pytest.raises(ValueError, match="cannot sleep -1"):
        clock.sleep(-1)
    assert SYSTEM_CLOCK.real_time and not clock.real_time


def test_a_wall_clock_step_leaves_monotonic_time_and_timers_alone():
    clock = SimulatedClock(start=10.0)
    fired: list[float] = []
    clock.every(0.005, lambda: fired.append(clock.monotonic()))
    clock.step_wall(-2.0)  # an NTP step back
    assert (clock.time(), clock.monotonic()) == (8.0, 10.0)
    clock.sleep(0.01)
    assert fired == [10.005, 10.01] and clock.time() == pytest.approx(8.01, abs=1e-12)
