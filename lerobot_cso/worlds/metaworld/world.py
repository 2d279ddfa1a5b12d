"""The MetaWorld world (``--world.type=metaworld``, the default): seeded initial states, a pool of envs.

Its envs give a policy what it reads (:func:`policy_pool`, :func:`env_inputs`): the state layout its
``observation.state`` size names, its cameras at its image size, LeRobot's own MetaWorld format included
(``observation.image``: LeRobot's ``corner2`` view; ``observation.state``: the 4-d hand state).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from lerobot.utils.constants import OBS_STATE

from lerobot_cso import seeds
from lerobot_cso.rollout.backend import RolloutBackend
from lerobot_cso.rollout.pool import Frames, open_pool
from lerobot_cso.worlds.base import DemoExpert, Purpose, Rollouts, WorldConfig, camera_inputs, image_size_of
from lerobot_cso.worlds.metaworld.constants import (
    ACTION_DIM,
    CAMERAS,
    FPS,
    HORIZON,
    IMAGE_SIZE,
    LEROBOT_CAMERA,
    STATE_LAYOUTS,
)
from lerobot_cso.worlds.metaworld.tasks import check_task, resolve_tasks, task_description


def pool(
    num_envs: int,
    cameras: Sequence[str] = (),
    image_size: int = IMAGE_SIZE,
    max_steps: int = HORIZON,
    state: str = "full",
    **kwargs: Any,
) -> RolloutBackend:
    """A pool (:func:`~lerobot_cso.rollout.pool.open_pool`; ``kwargs``: ``vectorization``, ``workers``,
    ``frames``) of MetaWorld envs with this state layout and these cameras at ``image_size``²."""
    from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv, check_cameras

    check_cameras(cameras)
    # The task given here is only the initial one; every job resets its slot onto its own task.
    factory = partial(CSOMetaWorldEnv, "reach-v3", tuple(cameras), image_size, max_steps, state=state)
    return open_pool(num_envs, cameras, env_factory=factory, check_task=check_task, **kwargs)


def policy_pool(
    features: Mapping[str, Any],
    num_envs: int,
    max_steps: int = HORIZON,
    vectorization: str = "processes",
    frames: Frames = "all",
    **kwargs: Any,
) -> RolloutBackend:
    """A pool whose envs give a policy with these input features what it reads (:func:`env_inputs`)."""
    cameras, size, state = env_inputs(features)
    return pool(num_envs, cameras, size, max_steps, state, vectorization=vectorization, frames=frames, **kwargs)


def env_inputs(features: Mapping[str, Any]) -> tuple[tuple[str, ...], int, str]:
    """The cameras, image size and state layout of envs that give a policy with these input features what it reads:
    the cameras of its ``observation.images.<camera>`` inputs, or for LeRobot's own MetaWorld format
    (``observation.image``) the camera LeRobot's MetaWorld env renders (:func:`~lerobot_cso.worlds.base.camera_inputs`),
    flipped as it flips it; its image size;
    the state layout of its ``observation.state`` size (the full state without one)."""
    from lerobot_cso.worlds.metaworld.env import state_layout

    cameras = tuple(camera_inputs(features, MetaWorld).values())
    state = state_layout(features[OBS_STATE].shape[-1]) if OBS_STATE in features else "full"
    return cameras, image_size_of(features, IMAGE_SIZE), state


class MetaWorld:
    """MetaWorld v3: seeded initial states, a pool of vector envs."""

    name = "metaworld"
    robot_type = "sawyer"
    state_dims = tuple(STATE_LAYOUTS.values())
    action_dim = ACTION_DIM
    cameras = CAMERAS
    single_camera = LEROBOT_CAMERA  # what a policy reading LeRobot's observation.image sees
    fps = FPS
    horizon = HORIZON
    eval_seeds = len(seeds.EVAL) // seeds.EVAL_BLOCK
    eval_states_per_seed = seeds.EVAL_BLOCK

    def resolve_tasks(self, spec: str) -> list[str]:
        return resolve_tasks(spec)

    def task_description(self, task: str) -> str:
        return task_description(task)

    def training_states(self, task: str, purpose: Purpose, start: int, count: int) -> list[int]:
        return seeds.training_seeds(purpose, start, count)

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        return seeds.eval_seeds(count, eval_seed)

    def backend(self, rollouts: Rollouts) -> RolloutBackend:
        """Envs whose state layout and image size are the ones the stage's policy reads."""
        return policy_pool(
            rollouts.features, rollouts.num_envs, rollouts.horizon, rollouts.vectorization, rollouts.frames
        )


@WorldConfig.register_subclass("metaworld")
@dataclass
class MetaWorldConfig(WorldConfig):
    """MetaWorld v3 (``--tasks``: a task, a comma list, MT10, MT50, ML45-train, ML45-test)."""

    def demo_expert(self) -> DemoExpert:
        """metaworld.policies' experts (expert.py)."""
        from lerobot_cso.worlds.metaworld.expert import MetaWorldDemos

        return MetaWorldDemos(pool)

    def build(self, tasks: str, policy: Any, output_dir: Path | None) -> MetaWorld:
        return MetaWorld()
