"""``benchmarks/twin_grasp_tolerance.py``: the scripted cube demonstration with its grasp put off on purpose, on the
physics alone. On development scene 300000 the grasp as planned holds and carries the cube into the bowl; moved
25 mm (0 of 30 scenes held at that offset, docs/benchmarks.md) it does not."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "twin_grasp_tolerance.py"


def test_the_grasp_as_planned_succeeds_and_one_moved_25_mm_fails():
    spec = importlib.util.spec_from_file_location("twin_grasp_tolerance", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.trial(300000, 0, 0, np.random.default_rng(0))
    assert not module.trial(300000, 25, 0, np.random.default_rng(0))
