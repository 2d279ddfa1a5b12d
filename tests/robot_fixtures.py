"""Helpers for the robot-rollout tests: a tiny PiPER-shaped cso policy, operator scripts, the emulated arm."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso.policy import CSOConfig, CSOPolicy

sys.path.insert(0, str(Path(__file__).parent / "hardware"))  # the PiPER test helpers

from piper_processes import (  # noqa: E402
    BIN,
    ChannelRecorder,
    EmulatorProcess,
    cli_env,
    explain,
    run_cli,
    start_emulator,
)
from piper_rig import unique_udp_channel  # noqa: E402

__all__ = ["ChannelRecorder", "EmulatorProcess", "explain", "run_cli", "start_emulator", "unique_udp_channel"]

TASK = "put the cube on the plate"
PIPER_STATE = 7  # joint_1..joint_6 (rad), gripper (m)
# Where the tiny policy's actions live: near a rest pose inside the PiPER's limits, at most 0.05 away.
REST = [0.0, 0.3, -0.3, 0.0, 0.2, 0.0, 0.02]
ACTION_SPAN = 0.05


def save_tiny_piper_policy(path: Path, state_dim: int = PIPER_STATE, camera: tuple[int, int] | None = None) -> Path:
    """A tiny untrained cso policy for the PiPER (7-D state and action; optionally one camera ``cam``)."""
    torch.manual_seed(0)
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    if camera is not None:
        inputs["observation.images.cam"] = PolicyFeature(FeatureType.VISUAL, (3, *camera))
    config = CSOConfig(
        **TINY_POLICY_KWARGS,
        device="cpu",
        push_to_hub=False,
        n_autoencoder_steps=0,
        tasks=[TASK],
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (PIPER_STATE,))},
    )
    rest = torch.tensor(REST)
    stats = {
        "observation.state": {"mean": torch.zeros(state_dim), "std": torch.ones(state_dim)},
        "action": {"min": rest - ACTION_SPAN, "max": rest + ACTION_SPAN},
    }
    if camera is not None:
        stats["observation.images.cam"] = {"mean": torch.zeros(3, 1, 1), "std": torch.ones(3, 1, 1)}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    CSOPolicy(config).save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


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
