"""Worlds: where rollouts run, what their tasks are called, and which initial states each purpose uses.

R-SFT, SPO and evaluation never name a world: they ask their settings' :class:`World` for task names,
language descriptions, initial states and a rollout backend. Initial states are plain integers whose meaning
is the world's own (MetaWorld: the reset seed, from the disjoint ranges of :mod:`lerobot_cso.envs.seeds`).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import Any, Literal, Protocol

from lerobot_cso.envs import seeds
from lerobot_cso.envs.constants import ACTION_DIM, CAMERAS, FPS, HORIZON, IMAGE_SIZE, STATE_LAYOUTS
from lerobot_cso.envs.tasks import resolve_tasks, task_description
from lerobot_cso.rollout.backend import RolloutBackend

Purpose = Literal["rsft", "spo"]


class RolloutSettings(Protocol):
    """The rollout settings of a stage (``RolloutStageConfig`` implements it)."""

    tasks: str
    num_envs: int
    vectorization: str

    records_frames: bool  # the stage keeps every frame (else only decision frames need rendering)
    keeps_inputs: bool  # each decision keeps the encoders' inputs (SPO without the encoder freeze)

    def world(self) -> World: ...

    def horizon(self) -> int:
        """The episode cap of the rollouts."""


class World(Protocol):
    """A world's names, initial states and backend."""

    name: str
    robot_type: str  # LeRobotDataset's robot_type of buffers recorded in this world
    fps: int  # control frequency (frames per second of recorded buffers)
    horizon: int  # the longest episode the world allows, and the default episode cap
    eval_seeds: int  # evaluation seeds 0 .. eval_seeds - 1 exist
    eval_states_per_seed: int  # at most this many evaluation episodes per task and seed

    def resolve_tasks(self, spec: str) -> list[str]:
        """The tasks named by ``spec``; ``ValueError`` naming the valid choices otherwise."""

    def task_description(self, task: str) -> str:
        """The language instruction of ``task``."""

    def training_states(self, task: str, purpose: Purpose, start: int, count: int) -> list[int]:
        """The ``start .. start + count - 1``-th initial states of ``task`` for online training (``purpose``)."""

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        """The first ``count`` evaluation initial states of ``task`` under evaluation seed ``eval_seed``."""

    def backend(self, settings: RolloutSettings, cameras: Sequence[str]) -> RolloutBackend:
        """A backend rolling out on this world with the given settings and cameras."""


class SimWorld(World, Protocol):
    """A simulated world: the shapes of its observations and actions, which a dataset for it must have."""

    state_dims: tuple[int, ...]  # the sizes observation.state may have
    action_dim: int  # action
    cameras: tuple[str, ...]  # the cameras its envs render (observation.images.<camera>)


class MetaWorld:
    """MetaWorld v3: seeded initial states, a pool of vector envs (:func:`~lerobot_cso.rollout.pool.open_pool`)."""

    name = "metaworld"
    robot_type = "sawyer"
    state_dims = tuple(STATE_LAYOUTS.values())
    action_dim = ACTION_DIM
    cameras = CAMERAS
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

    def backend(self, settings: RolloutSettings, cameras: Sequence[str]) -> RolloutBackend:
        """Envs whose state layout and image size are the ones the stage's policy reads."""
        from lerobot_cso.envs.metaworld_env import CSOMetaWorldEnv, state_layout
        from lerobot_cso.rollout.pool import open_pool

        features = policy_features(settings)
        state = state_layout(features["observation.state"].shape[-1]) if "observation.state" in features else "full"
        image_size = image_size_of(features, IMAGE_SIZE)
        factory = partial(CSOMetaWorldEnv, "reach-v3", tuple(cameras), image_size, settings.horizon(), state=state)
        return open_pool(
            settings.num_envs,
            cameras,
            image_size=image_size,
            max_steps=settings.horizon(),
            vectorization=settings.vectorization,
            env_factory=factory,
            frames="all" if settings.records_frames else "decisions",
        )


def policy_features(settings: RolloutSettings) -> dict[str, Any]:
    """The input features of the stage's policy (none when the settings carry no policy config)."""
    return getattr(getattr(settings, "policy", None), "input_features", None) or {}


def image_size_of(features: dict[str, Any], default: int) -> int:
    """The side of the policy's (square) camera images, ``default`` when it reads none."""
    sizes = [ft.shape[-1] for key, ft in features.items() if key.startswith("observation.images.")]
    return sizes[0] if sizes else default


def world_for(tasks: str) -> SimWorld:
    """The world whose tasks ``tasks`` names (MetaWorld unless another world claims them)."""
    from lerobot_cso.rollout.libero import Libero, names_libero

    if names_libero(tasks):
        return Libero(tasks)
    return MetaWorld()
