"""Worlds: where rollouts run, what their tasks are called, and which initial states each purpose uses.

A world is one folder of :mod:`lerobot_cso.worlds` holding its env, its task names and initial states, its scripted
expert where it has one, and its settings: a :class:`WorldConfig` registered under a name, chosen with
``--world.type=<name>`` (its own settings are ``--world.*``). The stage settings build the world once
(:meth:`WorldConfig.build`); R-SFT, SPO and evaluation then only ask it for task names, language descriptions,
initial states and a rollout backend. Initial states are plain integers whose meaning is the world's own
(MetaWorld: the reset seed, from the disjoint ranges of :mod:`lerobot_cso.seeds`).

A third party adds a world as LeRobot plugins add robots: a distribution named ``lerobot_env_<name>`` (LeRobot
imports every one at start-up) whose module registers ``@WorldConfig.register_subclass("<name>")``.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal, Protocol

import draccus
import numpy as np
from lerobot.utils.constants import OBS_IMAGE, OBS_IMAGES

from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.backend import Controller, RolloutBackend
from lerobot_cso.rollout.pool import Frames

Purpose = Literal["rsft", "spo"]


@dataclass(frozen=True)
class Rollouts:
    """What a stage asks of a world's backend: the envs, how they are stepped, what its policy reads."""

    num_envs: int
    vectorization: str  # processes | sync | async
    horizon: int  # the episode cap of the rollouts
    max_steps: int | None  # the stage's own cap (null: the world's, per task where it has one)
    frames: Frames  # all: every frame is kept; decisions: only the frames a decision reads need rendering
    cameras: tuple[str, ...]  # the cameras the policy reads
    features: Mapping[str, Any]  # the policy's input features (none for a policy still to be trained)


class World(Protocol):
    """A world's names, initial states and backend. A world whose LeRobot env renders one camera, given to a policy
    as LeRobot's single-camera ``observation.image``, names it in an optional ``single_camera`` attribute
    (:func:`camera_inputs`)."""

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

    def backend(self, rollouts: Rollouts) -> RolloutBackend:
        """A backend rolling out on this world."""


class SimWorld(World, Protocol):
    """A simulated world: the shapes of its observations and actions, which a dataset for it must have."""

    state_dims: tuple[int, ...]  # the sizes observation.state may have
    action_dim: int  # action
    cameras: tuple[str, ...]  # the cameras its envs render (observation.images.<camera>)


class DemoExpert(Protocol):
    """A world's scripted expert, and the demonstration dataset ``lerobot-cso demos`` makes with it: the envs it
    drives (which may show it the simulator's true state; the dataset keeps only what a policy reads), the
    controller, and the dataset's layout. Its defaults fill the demo settings left unset."""

    prefix: str  # per-frame metadata columns <prefix>.task, <prefix>.init_seed, <prefix>.success
    fps: int
    robot_type: str
    action_names: list[str]
    cameras: tuple[str, ...]  # the cameras its envs can render
    states: tuple[str, ...]  # the state layouts its datasets can hold (the first is the default)
    noise_std: float  # default action noise
    image_size: int  # default camera resolution
    demo_states: range  # episode i of a task starts from demo_states[i]: never a training or evaluation state

    def check_tasks(self, tasks: list[str]) -> None:
        """``ValueError`` naming the tasks among ``tasks`` the expert cannot do."""

    def horizon(self, tasks: list[str]) -> int:
        """The longest episode the expert may take on ``tasks`` (the default and upper bound of ``max_steps``)."""

    def state_dim(self, state: str) -> int:
        """The size of ``observation.state`` under layout ``state``."""

    def dataset_state(self, state: np.ndarray, layout: str) -> np.ndarray:
        """The dataset's ``observation.state`` of a recorded env state."""

    def pool(self, num_envs: int, cameras: Sequence[str], image_size: int, max_steps: int) -> RolloutBackend:
        """Envs showing the expert what it needs, rendering ``cameras``."""

    def controller(self, num_envs: int, noise_std: float, seed: int) -> Controller:
        """The expert for ``num_envs`` slots; episode noise seeded by ``(seed, task, init_seed)``."""


@dataclass
class WorldConfig(draccus.ChoiceRegistry, abc.ABC):
    """``--world.type=<name>`` and the world's own settings (``--world.*``)."""

    simulated: ClassVar[bool] = True  # False: a real one (its cameras give every frame; no ablations on it)

    def demo_expert(self) -> DemoExpert | None:
        """The world's scripted expert (``lerobot-cso demos`` generates its demos), or None."""
        return None

    @property
    def type(self) -> str:
        return self.get_choice_name(self.__class__)

    @classmethod
    def claims(cls, tasks: str) -> bool:
        """Whether a ``--tasks`` spec names this world's tasks, so that it is the world without ``--world.type``."""
        return False

    def spec(self) -> dict[str, Any]:
        """The world's settings that an episode depends on, for a stage's spec (none by default)."""
        return {}

    def validate(self) -> None:
        """Check the settings; raises ``UsageError``."""

    @abc.abstractmethod
    def build(self, tasks: str, policy: Any, output_dir: Path | None) -> World:
        """The world a stage with these ``--tasks``, policy config and output dir rolls out in."""


def camera_inputs(features: Mapping[str, Any], world: Any = None) -> dict[str, str]:
    """The camera each image input of a policy shows, by input key (the one mapping between a policy's image
    features and a world's cameras): ``observation.images.<camera>`` shows ``<camera>``; LeRobot's single-camera
    ``observation.image`` shows the world's ``single_camera``, the camera its LeRobot env renders (MetaWorld's
    ``corner2``). ``UsageError`` for ``observation.image`` in a world without one."""
    cameras = {}
    for key in features:
        if key == OBS_IMAGE:
            single = getattr(world, "single_camera", None)
            if single is None:
                name = getattr(world, "name", "this world")
                raise UsageError(
                    f"{OBS_IMAGE} (LeRobot's single-camera key) shows no camera of {name}: "
                    f"its camera images are named {OBS_IMAGES}.<camera>"
                )
            cameras[key] = single
        elif key.startswith(f"{OBS_IMAGES}."):
            cameras[key] = key.removeprefix(f"{OBS_IMAGES}.")
    return cameras


def image_size_of(features: Mapping[str, Any], default: int) -> int:
    """The side of the policy's (square) camera images (``observation.images.<camera>``, or LeRobot's single-camera
    ``observation.image``), ``default`` when it reads none."""
    sizes = [ft.shape[-1] for key, ft in features.items() if key == OBS_IMAGE or key.startswith(f"{OBS_IMAGES}.")]
    return sizes[0] if sizes else default
