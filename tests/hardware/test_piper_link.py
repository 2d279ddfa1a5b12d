"""The link's parts without an arm: the stale-feedback watchdog judged on exact, made-up times (no bus, no
threads), and what opening a bus does to python-can's logging."""

from __future__ import annotations

import pytest
from piper_can.link import Watchdog, open_bus

PERIOD = 0.005
LIMIT = 3 * PERIOD


def flowing(watchdog: Watchdog, ids: tuple[int, ...], start: float, cycles: int) -> float:
    """Frames of every ID in ``ids`` once per period; returns the time of the last cycle."""
    t = start
    for n in range(cycles):
        t = start + n * PERIOD
        for i in ids:
            watchdog.seen(i, t)
        assert watchdog.overdue(t + PERIOD - 1e-9) == []
    return t


def test_flowing_feedback_never_trips_and_one_missing_id_trips_just_after_its_limit():
    watchdog = Watchdog({0x2A5: LIMIT, 0x2A6: LIMIT, 0x261: LIMIT + 0.05})
    watchdog.arm(100.0)
    last = flowing(watchdog, (0x2A5, 0x2A6, 0x261), 100.0, 400)  # two seconds of 200 Hz feedback
    flowing(watchdog, (0x2A5, 0x261), last + PERIOD, 2)  # 0x2A6 stops after ``last``
    assert watchdog.overdue(last + LIMIT - 1e-9) == []
    assert watchdog.overdue(last + LIMIT + 1e-6) == [(0x2A6, pytest.approx(LIMIT + 1e-6))]
    assert watchdog.next_deadline() == pytest.approx(last + LIMIT)


def test_each_id_has_its_own_timeout_and_the_window_starts_at_arming():
    watchdog = Watchdog({0x2A1: LIMIT, 0x261: 0.065})
    watchdog.arm(10.0)  # nothing heard yet: the window starts now, not at 0
    assert watchdog.overdue(10.0 + LIMIT - 1e-9) == []
    watchdog.seen(0x2A1, 10.03)
    assert [i for i, _ in watchdog.overdue(10.04)] == []
    assert [i for i, _ in watchdog.overdue(10.066)] == [0x2A1, 0x261]
    assert watchdog.seen(0x999, 10.0) is None and 0x999 not in watchdog.last_seen  # unwatched IDs are ignored


def test_re_arming_needs_every_watched_id_after_the_trip():
    watchdog = Watchdog({0x2A5: LIMIT, 0x2A8: LIMIT})
    watchdog.arm(0.0)
    watchdog.seen(0x2A5, 1.0)
    watchdog.seen(0x2A8, 1.0)
    tripped_at = 1.02
    assert watchdog.missing_since(tripped_at, 1.03) == [0x2A5, 0x2A8]
    watchdog.seen(0x2A5, 1.025)
    assert watchdog.missing_since(tripped_at, 1.03) == [0x2A8]
    watchdog.seen(0x2A8, 1.03)
    assert watchdog.missing_since(tripped_at, 1.03) == []
    assert watchdog.missing_since(tripped_at, 1.1) == [0x2A5, 0x2A8]  # fresh means recent, too


def test_a_disarmed_watchdog_judges_nothing_and_timeouts_must_be_positive():
    watchdog = Watchdog({0x2A5: LIMIT})
    assert watchdog.overdue(1e9) == [] and watchdog.next_deadline() is None
    with pytest.raises(ValueError, match="0x2A5 must be positive"):
        Watchdog({0x2A5: 0.0})


def test_opening_a_bus_stops_python_cans_per_frame_record_but_keeps_a_level_set_on_purpose():
    """LeRobot's ``init_logging`` leaves the root logger at NOTSET, so python-can's level-9 "Received" record was
    built for each of the arm's 3 040 frames/s (≈ 15 µs each, GIL held) and dropped by every handler."""
    import logging

    root, frames = logging.getLogger(), logging.getLogger("can.bus")
    kept = root.level, frames.level
    try:
        root.setLevel(logging.NOTSET)  # as init_logging leaves it
        frames.setLevel(logging.NOTSET)
        assert frames.isEnabledFor(9)  # the waste, before
        open_bus("virtual", "quiet-frame-log", 1_000_000, {}).shutdown()
        assert frames.level == logging.DEBUG and not frames.isEnabledFor(9)

        frames.setLevel(5)  # someone who wants to see every frame
        open_bus("virtual", "quiet-frame-log", 1_000_000, {}).shutdown()
        assert frames.level == 5 and frames.isEnabledFor(9)
    finally:
        root.setLevel(kept[0])
        frames.setLevel(kept[1])
