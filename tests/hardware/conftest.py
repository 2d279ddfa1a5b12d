"""Fixtures for the PiPER tests."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from piper_rig import Rig, make_rig

os.environ.setdefault("MUJOCO_GL", "egl")  # the twin's cameras render offscreen (before mujoco is imported)


@pytest.fixture
def rig() -> Iterator[Rig]:
    """An emulated arm in real time and a connected, enabled driver on a unique virtual channel."""
    with make_rig() as r:
        yield r
