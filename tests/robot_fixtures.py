"""Helpers for the robot-rollout tests: a tiny PiPER-shaped cso policy, operator scripts, ``lerobot-cso`` started."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import torch
from lerobot_robot_piper.cli_processes import cli_env
from piper_can.emulator_process import BIN
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso.untrained import save_untrained_policy

TASK = "put the cube on the plate"
PIPER_STATE = 7  # joint_1..joint_6 (rad), gripper (m)
# Where the tiny policy's actions live: near a rest pose inside the PiPER's limits, at most 0.05 away.
REST = [0.0, 0.3, -0.3, 0.0, 0.2, 0.0, 0.02]
ACTION_SPAN = 0.05


def save_tiny_piper_policy(path: Path, state_dim: int = PIPER_STATE, camera: tuple[int, int] | None = None) -> Path:
    """A tiny untrained cso policy for the PiPER (7-D state and action; optionally one camera ``cam``)."""
    images = {} if camera is None else {"observation.images.cam": (3, *camera)}
    rest = torch.tensor(REST)
    stats = {
        "observation.state": {"mean": torch.zeros(state_dim), "std": torch.ones(state_dim)},
        "action": {"min": rest - ACTION_SPAN, "max": rest + ACTION_SPAN},
    }
    stats |= {key: {"mean": torch.zeros(3, 1, 1), "std": torch.ones(3, 1, 1)} for key in images}
    return save_untrained_policy(path, stats, [TASK], state_dim, PIPER_STATE, images, **TINY_POLICY_KWARGS)


def write_script(
    path: Path, targets: dict[str, dict[str, float]], keys: dict[str, list], tolerance: float, gates: dict[str, str]
) -> Path:
    """A ``--operator.type=scripted`` script (see :class:`lerobot_cso.worlds.robot.operator.ScriptedOperator`)."""
    path.write_text(json.dumps({"targets": targets, "keys": keys, "tolerance": tolerance, "gates": gates}))
    return path


def lerobot_cso(args: list[str], home: Path, **popen) -> subprocess.Popen:
    """Start ``lerobot-cso ARGS`` from this venv (offline, LeRobot's caches under ``home``)."""
    return subprocess.Popen(
        [str(BIN / "lerobot-cso"), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=cli_env(home),
        cwd=home,
        **popen,
    )
