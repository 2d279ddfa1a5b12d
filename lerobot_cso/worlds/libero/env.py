"""LIBERO tasks on LeRobot's ``LiberoEnv``, behind the env protocol of the rollout pool.

A task is named ``<suite>-<index>`` (``libero_spatial-0`` … ``libero_90-89``, in the benchmark's order). An
initial state is an integer:

- ``0 <= state < 50``: the benchmark's fixed init state of that index (what evaluation uses, as LIBERO and
  QueST do; LeRobot's ``LiberoEnv`` restores it);
- ``state >= 1_000_000`` (the online-training and placed-demo ranges of :mod:`lerobot_cso.seeds`): a fresh
  placement drawn from the task's BDDL regions with ``np.random.seed(state)`` — the same state for the same
  integer, and never one of the evaluation states.

Observations follow the engine's gym format: ``agent_pos`` is LeRobot's 8-d LIBERO state (eef position,
eef axis-angle, two gripper joints, as ``LiberoProcessorStep`` builds it) and ``pixels`` holds the requested
cameras (``image``: agentview, ``image2``: wrist, LeRobot's names) turned 180° as LeRobot's LIBERO datasets
store them. An env built with ``expert=True`` (for scripted demos) also observes ``expert``: the simulator's
true state the expert reads (:func:`~lerobot_cso.worlds.libero.expert.expert_view`), never stored in a dataset.
Episodes, parking and the render cadence are the pool's env protocol, :class:`~lerobot_cso.rollout.env.PoolEnv`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from lerobot_cso.rollout.env import PoolEnv
from lerobot_cso.worlds.libero.expert import VIEW_DIM, expert_view
from lerobot_cso.worlds.libero.setup import configure

configure()  # before any libero import, in every process that unpickles a LIBERO env

from lerobot.envs.libero import TASK_SUITE_MAX_STEPS, LiberoEnv  # noqa: E402
from lerobot.processor.env_processor import LiberoProcessorStep  # noqa: E402
from libero.libero import benchmark  # noqa: E402

SUITES: tuple[str, ...] = tuple(TASK_SUITE_MAX_STEPS)  # libero_spatial, libero_object, libero_goal, libero_10, 90
FIXED_STATES = 50  # init states per task in the benchmark's init files
CAMERAS = {"image": "agentview_image", "image2": "robot0_eye_in_hand_image"}  # LeRobot's names -> LIBERO's
STATE_DIM = 8
ACTION_DIM = 7
FPS = 20
IMAGE_SIZE = 128


@functools.cache
def suite(name: str) -> Any:
    """The LIBERO benchmark suite ``name`` (its tasks in the benchmark's order)."""
    if name not in SUITES:
        raise ValueError(f"unknown LIBERO suite '{name}'; valid suites: {', '.join(SUITES)}")
    return benchmark.get_benchmark_dict()[name]()


def parse_task(task: str) -> tuple[str, int]:
    """``"libero_spatial-3"`` → ``("libero_spatial", 3)``; ``ValueError`` naming the valid choices otherwise."""
    name, sep, index = task.rpartition("-")
    if not sep:
        raise ValueError(f"unknown LIBERO task '{task}': name a suite ({', '.join(SUITES)}) or a task <suite>-<index>")
    tasks = suite(name).tasks
    if not index.isdigit() or not 0 <= int(index) < len(tasks):
        raise ValueError(f"unknown LIBERO task '{task}'; {name} has tasks {name}-0 .. {name}-{len(tasks) - 1}")
    return name, int(index)


def task_description(task: str) -> str:
    """The language instruction of a LIBERO task."""
    name, index = parse_task(task)
    return suite(name).get_task(index).language


def max_steps(task: str) -> int:
    """The standard horizon of a task's suite (LeRobot's ``TASK_SUITE_MAX_STEPS``)."""
    return TASK_SUITE_MAX_STEPS[parse_task(task)[0]]


class _FrameSkippingLiberoEnv(LiberoEnv):
    """LeRobot's ``LiberoEnv`` whose cameras can skip rendering: while ``rendering`` is False, each camera's
    robosuite sensor returns its last frame instead of rendering. Only the sensor call is replaced, so the
    frames that are rendered are exactly the ones the unmodified env gives at the same steps."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.rendering = True
        self._frames: dict[str, np.ndarray] = {}

    def reset(self, seed: int | None = None, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.rendering = True
        observation, info = super().reset(seed=seed, **kwargs)
        observables = self._env.env._observables  # a hard reset builds them anew
        for camera in self.camera_name:
            observable = observables[camera]
            self._frames[camera] = observable.obs
            if not hasattr(observable._sensor, "__wrapped__"):
                observable._sensor = self._lazy(camera, observable._sensor)
        return observation, info

    def _lazy(self, camera: str, sensor: Callable[[dict], np.ndarray]) -> Callable[[dict], np.ndarray]:
        @functools.wraps(sensor)  # keeps robosuite's sensor attributes (its modality)
        def lazy(obs_cache: dict) -> np.ndarray:
            if self.rendering:
                self._frames[camera] = sensor(obs_cache)
            return self._frames[camera]

        return lazy


class CSOLiberoEnv(PoolEnv):
    """One LIBERO task at a time (switchable on reset), 8-d state, optional cameras, fixed or sampled states."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        task: str,
        cameras: Sequence[str] = (),
        image_size: int = IMAGE_SIZE,
        max_episode_steps: int | None = None,
        expert: bool = False,
    ) -> None:
        super().__init__()
        unknown = [c for c in cameras if c not in CAMERAS]
        if unknown:
            raise ValueError(f"unknown LIBERO camera(s) {', '.join(unknown)}; valid cameras: {', '.join(CAMERAS)}")
        parse_task(task)
        self.cameras = tuple(cameras)
        self.image_size = image_size
        self.max_episode_steps = max_episode_steps
        self.render_mode = "rgb_array"
        self.task = task
        self.expert = expert
        self._env: _FrameSkippingLiberoEnv | None = None
        self._env_task: str | None = None
        self._to_state = LiberoProcessorStep()
        obs_spaces: dict[str, spaces.Space] = {"agent_pos": spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)}
        if self.cameras:
            image = spaces.Box(0, 255, (image_size, image_size, 3), dtype=np.uint8)
            obs_spaces["pixels"] = spaces.Dict({cam: image for cam in self.cameras})
        if expert:
            obs_spaces["expert"] = spaces.Box(-np.inf, np.inf, (VIEW_DIM,), np.float32)
        self.observation_space = spaces.Dict(obs_spaces)
        self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), dtype=np.float32)

    @property
    def task_description(self) -> str:
        return task_description(self.task)

    @property
    def _max_episode_steps(self) -> int:
        return max_steps(self.task) if self.max_episode_steps is None else self.max_episode_steps

    def _libero(self) -> _FrameSkippingLiberoEnv:
        """LeRobot's env of the current task, built on first use (one task's MuJoCo model at a time)."""
        if self._env_task != self.task:
            self.close()
            name, index = parse_task(self.task)
            # Always built with every camera LiberoEnv renders; the ones not requested are switched off.
            self._env = _FrameSkippingLiberoEnv(
                suite(name),
                index,
                name,
                camera_name=[CAMERAS[c] for c in self.cameras] or [CAMERAS["image"]],
                obs_type="pixels_agent_pos",
                observation_width=self.image_size,
                observation_height=self.image_size,
                init_states=True,
            )
            self._env_task = self.task
        return self._env

    def _observe(self, raw: dict[str, Any]) -> dict[str, Any]:
        # Render during the next step only if its observation is one the caller asked frames for.
        self._libero().rendering = bool(self.cameras) and (self._t + 1) % self._render_every == 0
        robot = raw["robot_state"]
        eef = {key: torch.as_tensor(robot["eef"][key])[None] for key in ("pos", "quat")}
        gripper = {"qpos": torch.as_tensor(robot["gripper"]["qpos"])[None]}
        batch = {"observation.robot_state": {"eef": eef, "gripper": gripper}}
        state = self._to_state._process_observation(batch)["observation.state"][0]
        obs: dict[str, Any] = {"agent_pos": state.numpy().astype(np.float32)}
        if self.cameras:
            obs["pixels"] = {cam: np.ascontiguousarray(raw["pixels"][cam][::-1, ::-1]) for cam in self.cameras}
        if self.expert:
            obs["expert"] = expert_view(self._libero()._env.env)
        return obs

    def _set_task(self, task: str) -> None:
        parse_task(task)
        self.task = task

    def _restart(self, seed: int | None) -> dict[str, Any]:
        state = 0 if seed is None else int(seed)
        if FIXED_STATES <= state < 1_000_000 or state < 0:
            raise ValueError(f"LIBERO initial state {state}: use 0..{FIXED_STATES - 1} (fixed) or >= 1000000")
        env = self._libero()
        env.init_states = state < FIXED_STATES  # fixed benchmark state, or a placement drawn from the seed
        env.init_state_id = state
        raw, _ = env.reset(seed=state)
        return raw

    def _advance(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool]:
        raw, reward, _, _, info = self._libero().step(np.clip(np.asarray(action, np.float64), -1.0, 1.0))
        return raw, reward, bool(info["is_success"])

    def render(self) -> np.ndarray:
        """An RGB frame of the agentview camera (for videos)."""
        return self._libero().render()

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env = self._env_task = None
