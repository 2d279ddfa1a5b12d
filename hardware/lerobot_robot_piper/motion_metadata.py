"""The PiPER motion mode a dataset was recorded in, kept in its ``meta/info.json`` (key ``piper_motion``).

Demos recorded with a hardware-linked leader run the follower in high-follow (0xAD, no planning);
deploying the policy in position mode at 50 % would not match them. ``write_motion_mode`` stamps a
recorded dataset; ``read_motion_mode`` reads it back from the dataset root or from a trained policy
directory (through its ``train_config.json``), which ``--robot.motion_mode_from`` uses.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from piper_can.driver import MOTION_MODES

INFO_KEY = "piper_motion"


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


def write_motion_mode(dataset_root: str | Path, mode: MotionMode) -> None:
    """Record ``mode`` in the dataset's ``meta/info.json``."""
    info_path = Path(dataset_root) / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info[INFO_KEY] = asdict(mode)
    info_path.write_text(json.dumps(info, indent=4))


def read_motion_mode(path: str | Path) -> MotionMode | None:
    """The mode recorded for a dataset root, or for the dataset a policy directory was trained on;
    None when nothing was recorded (or the dataset is not on this machine)."""
    info_path = _info_path(Path(path))
    if info_path is None or not info_path.is_file():
        return None
    recorded = json.loads(info_path.read_text()).get(INFO_KEY)
    return None if recorded is None else MotionMode(**recorded)


def _info_path(path: Path) -> Path | None:
    if (path / "meta" / "info.json").is_file():
        return path / "meta" / "info.json"
    train_config = path / "train_config.json"
    if not train_config.is_file():
        return None
    root = json.loads(train_config.read_text()).get("dataset", {}).get("root")
    return None if root is None else Path(root) / "meta" / "info.json"
