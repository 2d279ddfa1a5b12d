"""The PiPER motion mode a dataset was recorded in, kept in its ``meta/info.json`` (key ``piper_motion``).

Demos recorded with a hardware-linked leader run the follower in high-follow (0xAD, no planning);
deploying the policy in position mode at 50 % would not match them. ``piper-record`` stamps the
dataset it records (``write_motion_mode``); ``read_motion_mode`` reads the stamp back from a dataset
root or from a trained policy directory (through its ``train_config.json``), and ``deployment_source``
finds the dataset or policy named on a LeRobot command line, so a follower deploys in the recorded
mode by default.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from lerobot.configs import parser
from lerobot.utils.constants import HF_LEROBOT_HOME
from piper_can.settings import MOTION_MODES

INFO_KEY = "piper_motion"
DEFAULT_MOTION_MODE = "position"
DEFAULT_SPEED_PERCENT = 50


@dataclass(frozen=True)
class MotionMode:
    """How the follower moved: ``position`` (planned at ``speed_percent``) or ``high_follow``."""

    motion_mode: str
    speed_percent: int

    def __post_init__(self) -> None:
        if self.motion_mode not in MOTION_MODES:
            raise ValueError(f"motion_mode must be one of {MOTION_MODES}, got {self.motion_mode!r}")
        if not 0 <= self.speed_percent <= 100:
            raise ValueError(f"speed_percent must be 0..100, got {self.speed_percent}")

    def __str__(self) -> str:
        return f"{self.motion_mode} at {self.speed_percent} %"


def write_motion_mode(dataset_root: str | Path, mode: MotionMode) -> None:
    """Record ``mode`` in the dataset's ``meta/info.json`` (atomically: a reader sees the old or the new file)."""
    info_path = Path(dataset_root) / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info[INFO_KEY] = asdict(mode)
    partial = info_path.with_name(f".{info_path.name}.{os.getpid()}.tmp")
    partial.write_text(json.dumps(info, indent=4))
    os.replace(partial, info_path)


def read_motion_mode(path: str | Path) -> MotionMode | None:
    """The mode recorded for a dataset root, or for the dataset a policy directory was trained on;
    None when nothing was recorded (or the dataset is not on this machine)."""
    info_path = _info_path(Path(path))
    if info_path is None or not info_path.is_file():
        return None
    recorded = json.loads(info_path.read_text()).get(INFO_KEY)
    return None if recorded is None else MotionMode(**recorded)


def deployment_source(args: Sequence[str] | None = None) -> Path | None:
    """The policy or dataset a LeRobot command line deploys, read as LeRobot's own configs read it:
    ``--policy.path`` (lerobot-rollout), else ``--dataset.root``, else ``--dataset.repo_id`` under
    ``$HF_LEROBOT_HOME`` (lerobot-replay); None when it names neither."""
    policy = parser.get_path_arg("policy", args)
    if policy:
        return Path(policy)
    root = parser.parse_arg("dataset.root", args)
    if root:
        return Path(root)
    repo_id = parser.parse_arg("dataset.repo_id", args)
    return HF_LEROBOT_HOME / repo_id if repo_id else None


def dataset_root(root: str | Path | None, repo_id: str) -> Path:
    """Where LeRobot keeps a dataset: ``root``, or ``$HF_LEROBOT_HOME/<repo_id>``."""
    return Path(root) if root is not None else HF_LEROBOT_HOME / repo_id


def _info_path(path: Path) -> Path | None:
    if (path / "meta" / "info.json").is_file():
        return path / "meta" / "info.json"
    train_config = path / "train_config.json"
    if not train_config.is_file():
        return None
    dataset = json.loads(train_config.read_text()).get("dataset") or {}
    if dataset.get("root") is None and not dataset.get("repo_id"):
        return None
    return dataset_root(dataset.get("root"), dataset.get("repo_id", "")) / "meta" / "info.json"
