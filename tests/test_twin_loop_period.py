"""``benchmarks/twin_loop_period.py``'s count of late periods by their tick's place in its skill, on hand-made times
(it is what located the late ticks at the decode's start, docs/benchmarks.md session 35)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_late_periods_are_counted_at_the_place_of_the_tick_that_sent_them(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from twin_loop_period import late_by_place

    # 20 ticks 33 ms apart; each tick calls select_action at its start and sends its command 2 ms later, except
    # ticks 4 and 12 (place 4 of 8) and tick 9 (place 1), which send 6 ms late: periods of 37 ms into them.
    starts = np.arange(20) * 0.033
    delays = np.full(20, 0.002)
    delays[[4, 9, 12]] = 0.006
    commands = starts + delays
    calls = [(float(t), 0.05) for t in starts]
    late = late_by_place(commands, start=0.0, select_calls=calls, steps=8, limit_ms=36.7)
    assert late == [0, 1, 0, 0, 2, 0, 0, 0]
    # only periods ending after ``start`` count
    assert late_by_place(commands, start=0.2, select_calls=calls, steps=8, limit_ms=36.7) == [0, 1, 0, 0, 1, 0, 0, 0]
