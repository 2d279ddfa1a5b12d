"""Scripted MetaWorld experts (``metaworld.policies``) with Gaussian action noise, as a pool controller, and the
world's demo expert (:class:`MetaWorldDemos`: the dataset ``lerobot-cso demos`` makes with them).

The noise of an episode is drawn from its own generator, seeded by ``(seed, task, init_seed)``, so an
episode's actions do not depend on which slot runs it or on what ran before: the same seed gives the same
demonstrations, whatever the number of envs and however often generation was interrupted.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from metaworld.policies import ENV_POLICY_MAP

from lerobot_cso import seeds
from lerobot_cso.rollout.backend import RolloutBackend
from lerobot_cso.rollout.pool import Job
from lerobot_cso.worlds.metaworld.constants import (
    CAMERAS,
    FPS,
    HORIZON,
    IMAGE_SIZE,
    LEROBOT_CAMERA,
    LEROBOT_IMAGE_SIZE,
    LEROBOT_STATE,
    STATE_LAYOUTS,
)
from lerobot_cso.worlds.metaworld.env import select_state


class ExpertController:
    """Per slot: the task's scripted expert plus N(0, ``noise_std``²) noise, clipped to [-1, 1]."""

    def __init__(self, num_envs: int, noise_std: float = 0.2, seed: int = 0) -> None:
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std}")
        self.noise_std = noise_std
        self.seed = seed
        self._experts: list[Any] = [None] * num_envs
        self._rngs: list[np.random.Generator | None] = [None] * num_envs

    def start(self, slot: int, job: Job) -> None:
        self._experts[slot] = ENV_POLICY_MAP[job.task]()
        self._rngs[slot] = np.random.default_rng([self.seed, zlib.crc32(job.task.encode()), job.init_seed])

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        actions = np.zeros((len(active), 4), dtype=np.float32)
        for slot in np.flatnonzero(active):
            action = self._experts[slot].get_action(obs["agent_pos"][slot])
            action = action + self._rngs[slot].normal(0.0, self.noise_std, size=action.shape)
            actions[slot] = np.clip(action, -1.0, 1.0)
        return actions

    def finish(self, slot: int) -> None:
        self._experts[slot] = self._rngs[slot] = None

    def current_skill(self, slot: int) -> None:
        return None  # an expert acts step by step, not by skills


class MetaWorldDemos:
    """MetaWorld's demo expert (:class:`~lerobot_cso.worlds.base.DemoExpert`): the expert reads the full 39-d
    state; the dataset keeps the part its state layout names (``full``, QueST's 8-d ``proprio``, LeRobot's 4-d
    ``hand``). With ``lerobot-cso demos --format=lerobot`` it writes LeRobot's own MetaWorld format: the
    ``lerobot_*`` camera, image size and state layout, and LeRobot's task descriptions (:meth:`lerobot_task`)."""

    prefix = "metaworld"
    fps = FPS
    robot_type = "sawyer"
    action_names = ["dx", "dy", "dz", "gripper"]
    cameras = CAMERAS
    states = tuple(STATE_LAYOUTS)
    noise_std = 0.2  # QueST's
    image_size = IMAGE_SIZE
    demo_states = seeds.DEMO
    lerobot_camera = LEROBOT_CAMERA  # shown as observation.image, flipped as LeRobot's metaworld env flips it
    lerobot_image_size = LEROBOT_IMAGE_SIZE
    lerobot_state = LEROBOT_STATE

    def check_tasks(self, tasks: list[str]) -> None:
        """Every MetaWorld task has its expert."""

    def horizon(self, tasks: list[str]) -> int:
        return HORIZON

    def state_dim(self, state: str) -> int:
        return STATE_LAYOUTS[state]

    def dataset_state(self, state: np.ndarray, layout: str) -> np.ndarray:
        return select_state(state, layout)

    def lerobot_task(self, task: str) -> str:
        """LeRobot's own description of ``task`` (its metaworld env's ``TASK_DESCRIPTIONS``; for ``push-back-v3`` the
        sentence it gives ``push-v3`` too, where this project's world has its own)."""
        from lerobot.envs.metaworld import TASK_DESCRIPTIONS

        return TASK_DESCRIPTIONS[task]

    def __init__(self, pool: Callable[..., RolloutBackend]) -> None:
        self._pool = pool  # the world's pool of envs (world.pool): their full state is what the expert reads

    def pool(self, num_envs: int, cameras: Sequence[str], image_size: int, max_steps: int) -> RolloutBackend:
        return self._pool(num_envs, cameras, image_size, max_steps)

    def controller(self, num_envs: int, noise_std: float, seed: int) -> ExpertController:
        return ExpertController(num_envs, noise_std, seed)
