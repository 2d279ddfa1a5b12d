"""The settings every rollout stage shares (evaluation, R-SFT, SPO), checked by one ``validate()``, and the one
the training stages (R-SFT, SPO) add: their torch threads while they train.

A rollout stage rolls a saved policy out on the tasks of one world (:mod:`lerobot_cso.worlds`): ``--world.type``
chooses it (``metaworld``, ``libero``, ``robot``, or a plugin's; without it, the world whose tasks ``--tasks``
names), ``--world.*`` are its own settings, ``--tasks`` names the tasks, ``--sampling.temperature/top_k/greedy``
say how skills are drawn, ``--num_envs``, ``--vectorization`` and ``--max_steps`` shape the rollouts. The world is
built once, by ``validate()``; :func:`stage_engine` gives a stage its rollout engine on it.

``--world.type=robot --robot.type=...`` (a LeRobot robot, e.g. ``piper_follower``; ``--robot.type`` alone implies
the world) runs the stage on that robot with an operator in the loop (:mod:`lerobot_cso.worlds.robot`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch

from lerobot_cso.checkpoints import PolicyPathConfig
from lerobot_cso.errors import UsageError, check_output_dir
from lerobot_cso.rollout.engine import RolloutEngine, SkillPolicy
from lerobot_cso.rollout.pool import VECTORIZATIONS
from lerobot_cso.sampling import Sampling
from lerobot_cso.stage import PIPELINE_FIELDS, POLICY_ROLES, settings_spec
from lerobot_cso.worlds.base import Rollouts, World, WorldConfig, camera_inputs
from lerobot_cso.worlds.registry import default_world

# Each env is a simulator held in memory (100 000 were tried); the shipped configs use at most 64.
MAX_ENVS = 1024


@dataclass
class RolloutStageConfig(PolicyPathConfig):
    """Base of ``EvalConfig`` and of the training stages' ``TrainingStageConfig``."""

    # What --policy.path must point at, for the error message when it is missing.
    policy_role: ClassVar[str] = POLICY_ROLES["eval"]
    # Whether the stage keeps every frame of an episode (R-SFT's buffer does); a world may then render only
    # the frames a decision needs.
    records_frames: ClassVar[bool] = True
    # Whether each decision keeps the encoders' inputs (SPO without the encoder freeze recomputes its contexts).
    keeps_inputs: ClassVar[bool] = False

    # The world to roll out in (--world.type=metaworld|libero|robot, and its own --world.* settings); null: the
    # world whose tasks --tasks names (LIBERO's for libero_* tasks, else MetaWorld).
    world: WorldConfig | None = None
    # One task, a comma list, or a set of the world (MetaWorld: MT10, MT50, ML45-train, ML45-test).
    tasks: str = "MT10"
    output_dir: Path | None = None
    sampling: Sampling = field(default_factory=Sampling)
    num_envs: int = 16
    # processes (envs split over one worker process per core) | sync (this process) | async (a process per env)
    vectorization: str = "processes"
    # Episode cap of the rollouts (a failure runs to the cap); null: the world's horizon.
    max_steps: int | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        self._world: World | None = None

    def world_settings(self) -> WorldConfig:
        """``--world``, or the world whose tasks ``--tasks`` names."""
        return self.world if self.world is not None else default_world(self.tasks)

    def rollout_world(self) -> World:
        """The world the stage rolls out in, built once (by ``validate()``)."""
        if self._world is None:
            self._world = self.world_settings().build(self.tasks, self.policy, self.output_dir)
        return self._world

    def stage_spec(self) -> dict[str, Any]:
        """The settings the stage's output depends on: not the pipeline's fields, and of the world only what its
        episodes depend on (a simulated world's choice follows from the tasks; a robot's type, operator, teleop)."""
        spec = settings_spec(self, exclude=(*PIPELINE_FIELDS, "world", "train_threads"))
        return spec | settings_spec(self.world_settings().spec())

    def horizon(self) -> int:
        """The episode cap of the rollouts: ``max_steps``, or the world's horizon."""
        return self.rollout_world().horizon if self.max_steps is None else self.max_steps

    def rollouts(self, cameras: tuple[str, ...]) -> Rollouts:
        """What the stage asks of its world's backend, for a policy reading ``cameras``."""
        return Rollouts(
            num_envs=self.num_envs,
            vectorization=self.vectorization,
            horizon=self.horizon(),
            max_steps=self.max_steps,
            frames="all" if self.records_frames else "decisions",
            cameras=cameras,
            features=policy_features(self),
        )

    def validate(self) -> list[str]:
        """Check the shared settings and build the world; returns the resolved task list. Raises ``UsageError``."""
        if self.policy is None or self.policy.pretrained_path is None:
            raise UsageError(f"--policy.path is required ({self.policy_role})")
        self.world_settings().validate()
        if self.output_dir is not None:
            check_output_dir(self.output_dir)
        self._world = None
        world = self.rollout_world()
        try:
            tasks = world.resolve_tasks(self.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        if not 1 <= self.num_envs <= MAX_ENVS:
            raise UsageError(f"num_envs must be in [1, {MAX_ENVS}], got {self.num_envs}")
        if self.vectorization not in VECTORIZATIONS:
            raise UsageError(f"vectorization must be one of {', '.join(VECTORIZATIONS)}, got '{self.vectorization}'")
        if self.max_steps is not None and not 1 <= self.max_steps <= world.horizon:
            raise UsageError(f"max_steps must be in [1, {world.horizon}], got {self.max_steps}")
        self.sampling.check("sampling.")
        check_policy_fits(self.policy, world)
        known = getattr(self.policy, "tasks", None)  # the task strings a language/one-hot policy was trained on
        unknown = [t for t in tasks if known and world.task_description(t) not in known]
        if unknown:
            raise UsageError(
                f"the policy was not trained on {', '.join(unknown)}; it knows: {'; '.join(map(repr, known))}"
            )
        return tasks


def check_policy_fits(policy: Any, world: World) -> None:
    """Refuse a policy whose state or action size is not one of the world's (a policy trained for another world or
    robot), before any env is made; a world that does not say its sizes (a robot) is not checked here."""
    features = {**(getattr(policy, "input_features", None) or {}), **(getattr(policy, "output_features", None) or {})}
    for key, attribute in (("observation.state", "state_dims"), ("action", "action_dim")):
        try:
            allowed = getattr(world, attribute, None) if key in features else None
        except ValueError as e:  # a world whose simulator is not installed (LIBERO's says how to install it)
            raise UsageError(str(e)) from None
        if allowed is None:
            continue
        allowed = allowed if isinstance(allowed, tuple) else (allowed,)
        shape = tuple(features[key].shape)
        if shape not in [(n,) for n in allowed]:
            wanted = " or ".join(f"({n},)" for n in allowed)
            raise UsageError(
                f"the policy's '{key}' has shape {shape}, {world.name}'s is {wanted}: --policy.path="
                f"{policy.pretrained_path} was trained for another world or robot"
            )


def policy_features(settings: RolloutStageConfig) -> dict[str, Any]:
    """The input features of the stage's policy (none when the settings carry no policy config)."""
    return getattr(settings.policy, "input_features", None) or {}


def stage_engine(
    policy: SkillPolicy, preprocessor: Any, postprocessor: Any, settings: RolloutStageConfig
) -> RolloutEngine:
    """The engine of a rollout stage: the backend of its world, with the cameras the policy reads, keeping each
    decision's encoder inputs when the stage asks for them."""
    world = settings.rollout_world()
    cameras = tuple(camera_inputs(policy.config.input_features, world).values())
    backend = world.backend(settings.rollouts(cameras))
    return RolloutEngine(policy, preprocessor, postprocessor, backend, world.task_description, settings.keeps_inputs)


@dataclass
class TrainingStageConfig(RolloutStageConfig):
    """Base of ``RSFTConfig`` and ``SPOConfig``: rollout stages that also train the policy."""

    # torch's CPU threads while the stage trains (R-SFT's fine-tune, SPO's updates); null: the process's
    # setting. The rollouts' env workers idle meanwhile, so on 2 cores 2 threads train faster than 1
    # (docs/cso-on-cpu.md); the decisions during rollouts keep the process's setting. Not part of the spec.
    train_threads: int | None = None

    @contextmanager
    def training(self) -> Iterator[None]:
        """A block run with ``train_threads`` torch threads (unchanged when null), restored afterwards."""
        before = torch.get_num_threads()
        if self.train_threads is not None:
            torch.set_num_threads(self.train_threads)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    def validate(self) -> list[str]:
        if self.train_threads is not None and self.train_threads < 1:
            raise UsageError(f"train_threads must be >= 1 or null, got {self.train_threads}")
        return super().validate()
