"""``--env.type=cso_metaworld``: the MetaWorld env as a LeRobot ``EnvConfig`` (lerobot-eval, lerobot-train).

State observations (``observation.state``: the 39-d state, or with ``state=proprio`` QueST's 8-d proprio, or
``hand`` LeRobot's 4-d hand state) and, when ``cameras`` is set, ``image_size``² ``observation.images.<camera>``.
``task`` takes one task, a comma list, or a set name (``MT10``, ``ML45-train``, ...); each task gets its own
vector env under a group named after the task, so LeRobot's ``eval_info.json`` reports a success rate per task
name. Seeds that LeRobot passes to ``reset`` are shifted by ``seed_offset`` (default: the start of the evaluation
range of :mod:`lerobot_cso.seeds`).

Importing this module does not import metaworld; the envs are built in ``create_envs``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from lerobot_cso import seeds
from lerobot_cso.worlds.metaworld.constants import ACTION_DIM, FPS, HORIZON, IMAGE_SIZE, STATE_LAYOUTS


def parse_cameras(cameras: str) -> tuple[str, ...]:
    """``"corner2, gripperPOV"`` → ``("corner2", "gripperPOV")``; empty string → no camera."""
    return tuple(c.strip() for c in cameras.split(",") if c.strip())


@EnvConfig.register_subclass("cso_metaworld")
@dataclass
class CSOMetaWorldEnvConfig(EnvConfig):
    """MetaWorld v3 with the full 39-d state or QueST's proprio + camera (LeRobot's ``metaworld`` type: 4-d state)."""

    task: str = "reach-v3"
    fps: int = FPS
    episode_length: int = HORIZON
    cameras: str = ""
    image_size: int = IMAGE_SIZE
    state: str = "full"
    seed_offset: int = seeds.EVAL.start
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.state not in STATE_LAYOUTS:
            raise ValueError(f"env.state must be one of {', '.join(STATE_LAYOUTS)}, got {self.state!r}")
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_LAYOUTS[self.state],)),
        }
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE}
        for cam in parse_cameras(self.cameras):
            key = f"pixels/{cam}"
            self.features[key] = PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3))
            self.features_map[key] = f"{OBS_IMAGES}.{cam}"

    @property
    def gym_kwargs(self) -> dict:
        return {
            "cameras": parse_cameras(self.cameras),
            "image_size": self.image_size,
            "max_episode_steps": self.episode_length,
            "seed_offset": self.seed_offset,
            "state": self.state,
        }

    def create_envs(self, n_envs: int, use_async_envs: bool = False) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """One vector env of ``n_envs`` copies per task: ``{task_name: {0: vec_env}}``."""
        from lerobot.envs.utils import freeze_after_episode_end

        from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv
        from lerobot_cso.worlds.metaworld.tasks import resolve_tasks

        envs: dict[str, dict[int, gym.vector.VectorEnv]] = {}
        for task in resolve_tasks(self.task):
            fns = [freeze_after_episode_end(partial(CSOMetaWorldEnv, task, **self.gym_kwargs))] * n_envs
            if use_async_envs and n_envs > 1:
                vec = gym.vector.AsyncVectorEnv(fns, context="forkserver")
            else:
                vec = gym.vector.SyncVectorEnv(fns)
            envs[task] = {0: vec}
        return envs
