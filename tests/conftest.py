"""Shared fixtures of the policy and CSO tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from tiny_data import make_synthetic_dataset


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "synthetic"
    make_synthetic_dataset(root)
    return root
