"""A gymnasium env over MetaWorld v3 tasks: a state (39-d, or proprio only), optional cameras, seeded initial states.

Initial states are named by an integer: ``reset(seed=s)`` seeds the task's own RNG with ``seed_offset + s``
and redraws object and goal positions from it (``_freeze_rand_vec=False``, ``seeded_rand_vec=True``, the
route LeRobot's MetaWorld env takes), so the same seed replays the same state exactly, whatever ran before.
``reset(options={"task": name})`` switches the task; one MuJoCo env per task is built lazily (at the
first reset on that task, ≈0.25 s) and kept in a small LRU cache (≈20 MB each), so one env serves many
tasks. The goal position is part of the observation (MT-style), as the scripted experts and a state-only
policy need it.

Episodes, parking and the render cadence (``reset(options={"park": True})``, ``{"render_every": k}``) are the
pool's env protocol, :class:`~lerobot_cso.rollout.env.PoolEnv`.

The observation is a dict in LeRobot's env convention: ``agent_pos`` (float32), and with cameras
``pixels`` = ``{camera: uint8 (H, W, 3)}``, which ``lerobot.envs.utils.preprocess_observation`` maps to
``observation.state`` and ``observation.images.<camera>``. ``state`` picks what ``agent_pos`` holds
(:data:`~lerobot_cso.worlds.metaworld.constants.STATE_LAYOUTS`): the full 39-d state (object and goal positions:
what the scripted experts read), QueST's 8-d proprio (hand and gripper, now and one frame before: a policy that reads it
must find the objects in the image), or LeRobot's 4-d hand state.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Sequence
from functools import cache
from typing import Any

import metaworld
import mujoco
import numpy as np
from gymnasium import spaces
from metaworld.env_dict import ALL_V3_ENVIRONMENTS

from lerobot_cso.rollout.env import PoolEnv
from lerobot_cso.worlds.metaworld.constants import ACTION_DIM, CAMERAS, FPS, HORIZON, IMAGE_SIZE, STATE_LAYOUTS
from lerobot_cso.worlds.metaworld.tasks import check_task, task_description

_UPSIDE_DOWN = ("corner", "corner2")
DEFAULT_RENDER_CAMERA = "corner2"

warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")


@cache
def _goal_observable_task(task: str) -> metaworld.Task:
    """A fixed metaworld ``Task`` with the goal in the observation (built once per process)."""
    return metaworld.MT1(task, seed=0).train_tasks[0]


_RENDERERS: dict[tuple[str, int], mujoco.Renderer] = {}


def _renderer(task: str, size: int, model: mujoco.MjModel) -> mujoco.Renderer:
    """The process's renderer of ``task`` at ``size``², built from the first ``model`` asked for it.

    One per task and size, not one per env: a renderer holds an EGL context (≈ 58 MB in Mesa's llvmpipe, against ≈ 27
    MB for the task's simulation), and a worker of 24 envs over 3 tasks held 5-7 GB with one per env. Every env of a
    task has the same model structure, meshes and textures; what differs between them (object and goal placements,
    the camera pose) reaches the scene through each env's own ``data``.
    """
    renderer = _RENDERERS.get((task, size))
    if renderer is None:
        model.vis.quality.offsamples = 0
        model.vis.quality.shadowsize = 0
        model.vis.global_.offwidth = size
        model.vis.global_.offheight = size
        renderer = mujoco.Renderer(model, size, size)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        _RENDERERS[(task, size)] = renderer
    return renderer


def check_cameras(cameras: Sequence[str]) -> None:
    """Raise ``ValueError`` naming the valid cameras when one is unknown."""
    unknown = [c for c in cameras if c not in CAMERAS]
    if unknown:
        raise ValueError(f"unknown camera(s) {', '.join(unknown)}; valid cameras: {', '.join(CAMERAS)}")


def check_state(state: str) -> None:
    """Raise ``ValueError`` naming the valid state layouts when ``state`` is not one."""
    if state not in STATE_LAYOUTS:
        raise ValueError(f"unknown state layout {state!r}; valid: {', '.join(STATE_LAYOUTS)}")


def state_layout(dim: int) -> str:
    """The state layout whose ``observation.state`` has ``dim`` values (a policy's or dataset's state size)."""
    for name, size in STATE_LAYOUTS.items():
        if size == dim:
            return name
    sizes = ", ".join(f"{size} ({name})" for name, size in STATE_LAYOUTS.items())
    raise ValueError(f"a MetaWorld observation.state has {sizes} values, not {dim}")


def select_state(full: np.ndarray, state: str) -> np.ndarray:
    """The ``state`` layout's part of MetaWorld's 39-d observation (float32)."""
    if state == "proprio":
        full = np.concatenate([full[:4], full[18:22]])
    elif state == "hand":
        full = full[:4]
    return full.astype(np.float32)


class CSOMetaWorldEnv(PoolEnv):
    """One MetaWorld task at a time (switchable on reset), a state layout, optional cameras."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        task: str,
        cameras: Sequence[str] = (),
        image_size: int = IMAGE_SIZE,
        max_episode_steps: int = HORIZON,
        seed_offset: int = 0,
        render_camera: str | None = None,
        max_cached_tasks: int = 4,
        state: str = "full",
    ) -> None:
        super().__init__()
        check_task(task)
        check_cameras(cameras)
        check_state(state)
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.cameras = tuple(cameras)
        self.render_camera = render_camera or (self.cameras[0] if self.cameras else DEFAULT_RENDER_CAMERA)
        check_cameras([self.render_camera])
        self.image_size = image_size
        self.state = state
        self.seed_offset = seed_offset
        self.render_mode = "rgb_array"
        self._max_episode_steps = max_episode_steps
        self._max_cached_tasks = max(1, max_cached_tasks)
        self._sims: OrderedDict[str, Any] = OrderedDict()
        self._set_task(task)

        state_space = spaces.Box(-np.inf, np.inf, (STATE_LAYOUTS[state],), dtype=np.float32)
        obs_spaces: dict[str, spaces.Space] = {"agent_pos": state_space}
        if self.cameras:
            image = spaces.Box(0, 255, (image_size, image_size, 3), dtype=np.uint8)
            obs_spaces["pixels"] = spaces.Dict({cam: image for cam in self.cameras})
        self.observation_space = spaces.Dict(obs_spaces)
        self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), dtype=np.float32)

    @property
    def sim(self) -> Any:
        """The MuJoCo MetaWorld env of the current task, built on first use."""
        sim = self._sims.get(self.task)
        if sim is None:
            while len(self._sims) >= self._max_cached_tasks:
                self._evict(next(iter(self._sims)))
            sim = ALL_V3_ENVIRONMENTS[self.task]()
            sim.set_task(_goal_observable_task(self.task))
            sim._freeze_rand_vec = False
            sim.seeded_rand_vec = True
            sim.max_path_length = max(HORIZON, self._max_episode_steps)
            # The corner2 framing QueST and LeRobot use, set before the first reset computes the camera poses (set
            # with the renderer, the first frame of a task's first episode still had the default framing).
            sim.model.cam_pos[sim.model.camera("corner2").id] = [0.75, 0.075, 0.7]
            self._sims[self.task] = sim
        self._sims.move_to_end(self.task)
        return sim

    def _evict(self, task: str) -> None:
        self._sims.pop(task).close()

    def _set_task(self, task: str) -> None:
        check_task(task)
        self.task = task
        self.task_description = task_description(task)

    def _image(self, camera: str) -> np.ndarray:
        renderer = _renderer(self.task, self.image_size, self.sim.model)
        renderer.update_scene(self.sim.data, camera=camera)
        image = renderer.render()
        return np.ascontiguousarray(image[::-1, ::-1]) if camera in _UPSIDE_DOWN else image

    def _observe(self, full: np.ndarray) -> dict[str, Any]:
        obs: dict[str, Any] = {"agent_pos": select_state(full, self.state)}
        if self.cameras:
            if self._t % self._render_every == 0 or self._last_obs is None:
                obs["pixels"] = {cam: self._image(cam) for cam in self.cameras}
            else:  # not a decision step: nobody reads this frame
                obs["pixels"] = self._last_obs["pixels"]
        return obs

    def _restart(self, seed: int | None) -> np.ndarray:
        if seed is not None:
            self.sim.seed(self.seed_offset + seed)
        state, _ = self.sim.reset()
        return state

    def _advance(self, action: np.ndarray) -> tuple[np.ndarray, float, bool]:
        state, reward, _, _, info = self.sim.step(np.clip(action, -1.0, 1.0))
        return state, reward, bool(info["success"])

    def render(self) -> np.ndarray:
        """An RGB frame of the render camera (for LeRobot's eval videos)."""
        return self._image(self.render_camera)

    def close(self) -> None:
        for task in list(self._sims):
            self._evict(task)
