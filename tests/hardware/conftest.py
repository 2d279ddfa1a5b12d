"""Fixtures for the PiPER tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from piper_rig import Rig, make_rig


@pytest.fixture
def rig() -> Iterator[Rig]:
    """An emulated arm in real time and a connected, enabled driver on a unique virtual channel."""
    with make_rig() as r:
        yield r
