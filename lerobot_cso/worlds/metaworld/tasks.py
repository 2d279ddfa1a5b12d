"""MetaWorld v3 task names, named task sets and language descriptions.

Task sets come from metaworld 3.1.1 itself (``metaworld.env_dict``): ``MT10``, ``MT50``, ``ML45-train`` and
``ML45-test`` (the standard ML45 split). Descriptions are LeRobot 0.6.1's ``TASK_DESCRIPTIONS`` for
MetaWorld, except that ``push-back-v3`` gets its own wording: LeRobot gives it the same sentence as
``push-v3``, and a language-conditioned multi-task policy must be able to tell the two apart.

metaworld is imported lazily, so importing this module stays cheap (the LeRobot plugin imports it).
"""

from __future__ import annotations

import json
from functools import cache
from importlib.util import find_spec
from pathlib import Path

TASK_SET_NAMES = ("MT10", "MT50", "ML45-train", "ML45-test")

_DESCRIPTION_OVERRIDES = {"push-back-v3": "Pull the puck back to a goal"}


@cache
def all_tasks() -> tuple[str, ...]:
    """All 50 MetaWorld v3 task names, in metaworld's canonical (MT50) order."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return tuple(ALL_V3_ENVIRONMENTS)


@cache
def task_sets() -> dict[str, tuple[str, ...]]:
    """Named task sets, each in metaworld's order."""
    from metaworld.env_dict import ML45_V3, MT10_V3

    return {
        "MT10": tuple(MT10_V3),
        "MT50": all_tasks(),
        "ML45-train": tuple(ML45_V3["train"]),
        "ML45-test": tuple(ML45_V3["test"]),
    }


@cache
def _descriptions() -> dict[str, str]:
    # LeRobot's metaworld_config.json, located without importing lerobot (whose env package imports torch)
    package_dir = Path(find_spec("lerobot").submodule_search_locations[0])
    descriptions = json.loads((package_dir / "envs" / "metaworld_config.json").read_text())["TASK_DESCRIPTIONS"]
    return {**descriptions, **_DESCRIPTION_OVERRIDES}


def task_description(task: str) -> str:
    """The language instruction stored in the LeRobot ``task`` field for a MetaWorld task."""
    check_task(task)
    return _descriptions()[task]


def check_task(task: str) -> None:
    """Raise ``ValueError`` naming the valid choices when ``task`` is not a MetaWorld v3 task."""
    if task not in all_tasks():
        raise ValueError(
            f"unknown MetaWorld task '{task}'; valid tasks: {', '.join(all_tasks())}; "
            f"valid task sets: {', '.join(TASK_SET_NAMES)}"
        )


def resolve_tasks(spec: str) -> list[str]:
    """Expand a task spec: one task, a comma list of tasks and/or set names (MT10, ML45-train, ...).

    Duplicates are dropped, first occurrence wins. Raises ``ValueError`` on an unknown name.
    """
    tasks: list[str] = []
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        expanded = task_sets().get(item)
        if expanded is None:
            check_task(item)
            expanded = (item,)
        tasks.extend(t for t in expanded if t not in tasks)
    if not tasks:
        raise ValueError(f"no task given (got '{spec}'); pass a task name or one of {', '.join(TASK_SET_NAMES)}")
    return tasks
