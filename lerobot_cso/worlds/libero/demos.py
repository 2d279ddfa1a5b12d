"""LIBERO's demo expert: the pick-and-place expert (:mod:`lerobot_cso.worlds.libero.expert`) on envs that show
it the simulator's state, and the dataset ``lerobot-cso demos`` makes with it (the world's
:class:`~lerobot_cso.worlds.base.DemoExpert`)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import numpy as np

from lerobot_cso import seeds
from lerobot_cso.rollout.backend import RolloutBackend
from lerobot_cso.rollout.pool import open_pool
from lerobot_cso.worlds.libero import env
from lerobot_cso.worlds.libero.expert import LiberoExpertController

EXPERT_SUITES = ("libero_object",)  # the suites whose tasks it does (its success measured on each: docs/libero.md)


class LiberoDemos:
    """LIBERO's demo expert (:class:`~lerobot_cso.worlds.base.DemoExpert`) for its pick-and-place tasks: datasets
    in the layout of LeRobot's LIBERO datasets (``observation.images.image`` agentview, ``observation.images.image2``
    wrist, turned 180°; the 8-d ``observation.state``; the 7-d action), from placements drawn from the seeds of
    :data:`~lerobot_cso.seeds.DEMO_PLACEMENTS` — never one of the 50 fixed evaluation states."""

    prefix = "libero"
    fps = 20
    robot_type = "panda"
    action_names = ["dx", "dy", "dz", "droll", "dpitch", "dyaw", "gripper"]
    cameras = ("image", "image2")
    states = ("full",)  # LIBERO has one: eef position, axis-angle, two gripper joints
    noise_std = 0.05
    image_size = 128  # LIBERO's own datasets; a policy may resize
    demo_states = seeds.DEMO_PLACEMENTS

    def check_tasks(self, tasks: list[str]) -> None:
        other = [task for task in tasks if task.rpartition("-")[0] not in EXPERT_SUITES]
        if other:
            raise ValueError(
                f"LIBERO's scripted expert does {', '.join(EXPERT_SUITES)} (pick and place), not {', '.join(other)}"
            )

    def horizon(self, tasks: list[str]) -> int:
        return max(env.max_steps(task) for task in tasks)

    def state_dim(self, state: str) -> int:
        return env.STATE_DIM

    def dataset_state(self, state: np.ndarray, layout: str) -> np.ndarray:
        return state.astype(np.float32)

    def pool(self, num_envs: int, cameras: Sequence[str], image_size: int, max_steps: int) -> RolloutBackend:
        # The task given here is only the initial one; every job resets its slot onto its own task.
        factory = partial(env.CSOLiberoEnv, "libero_object-0", tuple(cameras), image_size, max_steps, expert=True)
        return open_pool(num_envs, cameras, env_factory=factory, check_task=env.parse_task)

    def controller(self, num_envs: int, noise_std: float, seed: int) -> LiberoExpertController:
        return LiberoExpertController(num_envs, noise_std, seed)
