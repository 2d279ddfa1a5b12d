"""Helpers of the LIBERO tests: a tiny dataset recorded from LIBERO, and success brought about through the
simulator."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_cso import seeds
from lerobot_cso.worlds.libero.env import ACTION_DIM, FPS, STATE_DIM, CSOLiberoEnv

DRAWER_TASK = "libero_goal-0"  # open the middle drawer of the cabinet: success is one joint's position
DRAWER_REGION = "wooden_cabinet_1_middle_region"
OPEN = -0.15  # inside the wooden cabinet's open range [-0.16, -0.14]
CAMERAS = ("image", "image2")
IMAGE = 32  # small frames: software rendering costs scale with pixels
REPO_ID = "local/libero_tiny"


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


class KeptDrawerOpeningEnv(DrawerOpeningEnv):
    """A :class:`DrawerOpeningEnv` that outlives the pools it is lent to (their ``close`` leaves it open), so that
    every stage of a pipeline reuses one MuJoCo model instead of building its own; :meth:`release` closes it."""

    def close(self) -> None:
        return None

    def release(self) -> None:
        super().close()


def record_libero_dataset(env: CSOLiberoEnv, root: Path, episodes: int, steps: int) -> Path:
    """A LeRobotDataset of ``episodes`` short episodes of ``env``'s task with LeRobot's LIBERO features (8-d
    state, 7-d action, both cameras, the language instruction as the task): smooth scripted actions from
    training placements that the tests' rollouts never use (the end of the training range)."""
    image = {"dtype": "image", "shape": (env.image_size, env.image_size, 3), "names": ["height", "width", "channel"]}
    features: dict[str, dict] = {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
        "action": {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
        **{f"observation.images.{cam}": image for cam in env.cameras},
    }
    ds = LeRobotDataset.create(REPO_ID, FPS, features, root=root, robot_type="panda", use_videos=False)
    for episode in range(episodes):
        obs, _ = env.reset(seed=seeds.TRAIN.stop - 1 - episode)
        for t in range(steps):
            action = (0.5 * np.sin(t / 4 + np.arange(ACTION_DIM) + episode)).astype(np.float32)
            frame = {"observation.state": obs["agent_pos"], "action": action, "task": env.task_description}
            frame.update({f"observation.images.{cam}": obs["pixels"][cam] for cam in env.cameras})
            ds.add_frame(frame)
            obs = env.step(action)[0]
        ds.save_episode()
    ds.finalize()
    return root
