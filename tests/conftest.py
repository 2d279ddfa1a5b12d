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


# The longest modules first: with one worker per core (``-n auto --dist loadfile``), the two workers then end
# together instead of one running the end-to-end pipeline alone at the end.
SLOWEST_FIRST = (
    "test_pipeline.py",
    "test_libero.py",
    "test_robot_rollouts.py",
    "test_piper_lerobot_cli.py",
    "test_policy_model.py",
    "test_distributed.py",
    "test_eval.py",
    "test_policy_train_cli.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        name = item.path.name
        return SLOWEST_FIRST.index(name) if name in SLOWEST_FIRST else len(SLOWEST_FIRST)

    items.sort(key=rank)  # stable: the order within a module is kept
