"""Helpers of the LIBERO tests: a tiny two-camera cso policy, and success brought about through the simulator."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso.envs.libero_env import ACTION_DIM, STATE_DIM, CSOLiberoEnv, task_description
from lerobot_cso.policy import CSOConfig, CSOPolicy

DRAWER_TASK = "libero_goal-0"  # open the middle drawer of the cabinet: success is one joint's position
DRAWER_REGION = "wooden_cabinet_1_middle_region"
OPEN = -0.15  # inside the wooden cabinet's open range [-0.16, -0.14]
CAMERAS = ("image", "image2")
IMAGE = 32  # small frames: software rendering costs scale with pixels


def open_drawer(env: CSOLiberoEnv) -> None:
    """Open the middle drawer by setting its joint in the simulator (what a successful policy would do)."""
    inner = env._libero()._env.env
    for joint in inner.object_sites_dict[DRAWER_REGION].joints:
        inner.sim.data.set_joint_qpos(joint, OPEN)
    inner.sim.forward()


class DrawerOpeningEnv(CSOLiberoEnv):
    """A LIBERO env whose drawer opens at step 4 when the action taken there says so (a pseudo-random, per-sample
    function of the policy's action), so that some rollouts of an untrained policy succeed and some fail."""

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if not self._parked and self._t == 4 and int(np.abs(action).sum() * 1e4) % 2 == 0:
            open_drawer(self)
        return super().step(action)


def save_tiny_libero_policy(path: Path) -> Path:
    """A tiny untrained cso policy reading LIBERO's 8-d state and both cameras at 32x32, acting in 7-d."""
    torch.manual_seed(0)
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (STATE_DIM,))}
    for cam in CAMERAS:
        inputs[f"observation.images.{cam}"] = PolicyFeature(FeatureType.VISUAL, (3, IMAGE, IMAGE))
    config = CSOConfig(
        **TINY_POLICY_KWARGS,
        device="cpu",
        push_to_hub=False,
        n_autoencoder_steps=0,
        tasks=[task_description(DRAWER_TASK)],
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
    )
    stats: dict[str, dict[str, torch.Tensor]] = {
        "observation.state": {"mean": torch.zeros(STATE_DIM), "std": torch.ones(STATE_DIM)},
        "action": {"min": -torch.ones(ACTION_DIM), "max": torch.ones(ACTION_DIM)},
    }
    for cam in CAMERAS:
        stats[f"observation.images.{cam}"] = {"mean": torch.zeros(3, 1, 1), "std": torch.ones(3, 1, 1)}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    CSOPolicy(config).save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path
