"""The clocks the PiPER driver runs on: the system's, or a simulated one that tests step exactly.

A clock gives the wall time (``time``: the kernel stamps received frames on it, and it can step, e.g. an
NTP or VM resync), a monotonic time (deadlines, and the ages of frames: the link re-bases every stamp
onto it) and a way to wait (``sleep``). ``SystemClock`` is the process's own; with it the link reads the bus on a
thread. ``SimulatedClock`` moves only inside ``sleep``, running every callback that falls due on the
way (an emulated arm's ``step``), so a test drives firmware, bus and driver in one thread with exact
times; with it the link reads the bus whenever it is asked for the state (no thread).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol


class Clock(Protocol):
    """What the driver needs of time."""

    @property
    def real_time(self) -> bool:
        """True when time passes by itself (then the link reads the bus on a thread)."""
        ...

    def time(self) -> float:
        """Wall-clock seconds (the epoch the kernel stamps frames with; it may step either way)."""
        ...

    def monotonic(self) -> float:
        """Seconds that never go back (deadlines, and every frame's age)."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds``."""
        ...


class SystemClock:
    """The process's clocks: ``time.time``, ``time.monotonic``, ``time.sleep``."""

    real_time = True

    def time(self) -> float:
        return time.time()

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)


SYSTEM_CLOCK = SystemClock()


@dataclass
class _Timer:
    start: float
    period: float
    callback: Callable[[], None]
    calls: int = 0

    @property
    def due(self) -> float:  # from the start, so periods do not accumulate rounding errors
        return self.start + (self.calls + 1) * self.period


class SimulatedClock:
    """Time that moves only in ``sleep``: every ``every`` callback due by then runs, in time order
    (ties in registration order), with the clock set to its due time. One thread sleeps at a time.
    ``step_wall`` steps the wall clock alone, as an NTP step does (``monotonic`` goes on)."""

    real_time = False

    def __init__(self, start: float = 1_000.0) -> None:
        # Far from today's epoch, so a frame stamped on the system clock cannot pass for a fresh one.
        self._now = start
        self._wall_offset = 0.0
        self._timers: list[_Timer] = []

    def time(self) -> float:
        return self._now + self._wall_offset

    def step_wall(self, seconds: float) -> None:
        """Step the wall clock by ``seconds`` (negative: back), leaving the monotonic time alone."""
        self._wall_offset += seconds

    def monotonic(self) -> float:
        return self._now

    def every(self, period_s: float, callback: Callable[[], None]) -> None:
        """Call ``callback()`` every ``period_s`` from now on (first at now + ``period_s``)."""
        if period_s <= 0:
            raise ValueError(f"period_s must be positive, got {period_s}")
        self._timers.append(_Timer(self._now, period_s, callback))

    def sleep(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"cannot sleep {seconds} s")
        end = self._now + seconds
        while self._timers:
            timer = min(self._timers, key=lambda t: t.due)
            if timer.due > end + 1e-12:
                break
            self._now = max(self._now, timer.due)
            timer.calls += 1
            timer.callback()
        self._now = max(self._now, end)
