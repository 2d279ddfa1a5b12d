"""The settings every rollout stage shares (evaluation, R-SFT, SPO), checked by one ``validate()``, and the one
the training stages (R-SFT, SPO) add: their torch threads while they train.

A rollout stage rolls a saved policy out on the tasks of one world (:mod:`lerobot_cso.rollout.world`):
``--tasks`` names them, ``--sampling.temperature/top_k/greedy`` say how skills are drawn, ``--num_envs``,
``--vectorization`` and ``--max_steps`` shape the rollouts.

``--robot.type=...`` (a LeRobot robot, e.g. ``piper_follower``) runs the stage on that robot with an operator in
the loop instead (:mod:`lerobot_cso.rollout.robot`): ``--tasks`` is then the task instruction the policy was
trained with, ``--teleop.type=...`` optionally drives the arm while the operator arranges the scene,
``--operator.*`` says who labels the episodes and how long they run, ``--display_data=true`` shows them in rerun.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import lerobot.scripts.lerobot_record  # noqa: F401  (registers LeRobot's robots, teleoperators and cameras)
import torch
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig

from lerobot_cso.checkpoints import PolicyPathConfig
from lerobot_cso.errors import UsageError, check_number, check_output_dir
from lerobot_cso.rollout.engine import Sampling
from lerobot_cso.rollout.operator import OperatorConfig
from lerobot_cso.rollout.pool import VECTORIZATIONS
from lerobot_cso.rollout.world import World, world_for
from lerobot_cso.stage import PIPELINE_FIELDS, settings_spec

ROBOT_FIELDS = ("robot", "teleop", "operator")  # settings of robot rollouts only


@dataclass
class RolloutStageConfig(PolicyPathConfig):
    """Base of ``EvalConfig`` and of the training stages' ``TrainingStageConfig``."""

    # What --policy.path must point at, for the error message when it is missing.
    policy_role: ClassVar[str] = "a directory written by save_pretrained"
    # Whether the stage keeps every frame of an episode (R-SFT's buffer does); a world may then render only
    # the frames a decision needs.
    records_frames: ClassVar[bool] = True
    # Whether each decision keeps the encoders' inputs (SPO without the encoder freeze recomputes its contexts).
    keeps_inputs: ClassVar[bool] = False

    # One task, a comma list, or a set of the world (MetaWorld: MT10, MT50, ML45-train, ML45-test).
    tasks: str = "MT10"
    output_dir: Path | None = None
    sampling: Sampling = field(default_factory=Sampling)
    num_envs: int = 16
    # processes (envs split over one worker process per core) | sync (this process) | async (a process per env)
    vectorization: str = "processes"
    # Episode cap of the rollouts (a failure runs to the cap); null: the world's horizon.
    max_steps: int | None = None
    # A LeRobot robot to roll out on (with an operator) instead of a simulated world.
    robot: RobotConfig | None = None
    # Optional teleoperator that moves the robot while the operator arranges each scene.
    teleop: TeleoperatorConfig | None = None
    operator: OperatorConfig = field(default_factory=OperatorConfig)
    # Show cameras, commanded vs measured joints and the current skill in rerun (robot rollouts).
    display_data: bool = False

    def world(self) -> World:
        """The world the tasks belong to: the robot's when ``--robot.type`` is given."""
        if self.robot is not None:
            from lerobot_cso.rollout.robot import RobotWorld

            return RobotWorld(self)
        return world_for(self.tasks)

    def stage_spec(self) -> dict[str, Any]:
        """The settings the stage's output depends on: not the pipeline's fields nor ``display_data``, and the
        robot's settings only when it runs on a robot."""
        robot = () if self.robot is not None else ROBOT_FIELDS
        spec = settings_spec(self, exclude=(*PIPELINE_FIELDS, "display_data", "train_threads", *robot))
        if self.robot is not None:  # how the arm is reached and recovered does not change what an episode keeps
            spec["robot"] = {"type": self.robot.type}
        return spec

    def horizon(self) -> int:
        """The episode cap of the rollouts: ``max_steps``, or the world's horizon."""
        return self.world().horizon if self.max_steps is None else self.max_steps

    def validate(self) -> list[str]:
        """Check the shared settings; returns the resolved task list. Raises ``UsageError``."""
        if self.policy is None or self.policy.pretrained_path is None:
            raise UsageError(f"--policy.path is required ({self.policy_role})")
        if self.robot is not None:
            from lerobot_cso.rollout.robot import check_policy_fits

            self.operator.validate()
            if self.output_dir is None:
                raise UsageError("--output_dir is required with --robot.type (the episodes are journaled there)")
            check_policy_fits(self.robot, self.policy)
        if self.output_dir is not None:
            check_output_dir(self.output_dir)
        world = self.world()
        try:
            tasks = world.resolve_tasks(self.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        if self.num_envs < 1:
            raise UsageError(f"num_envs must be >= 1, got {self.num_envs}")
        if self.vectorization not in VECTORIZATIONS:
            raise UsageError(f"vectorization must be one of {', '.join(VECTORIZATIONS)}, got '{self.vectorization}'")
        if self.max_steps is not None and not 1 <= self.max_steps <= world.horizon:
            raise UsageError(f"max_steps must be in [1, {world.horizon}], got {self.max_steps}")
        check_number("sampling.temperature", self.sampling.temperature, gt=0)
        check_number("sampling.top_k", self.sampling.top_k, ge=1, optional=True)
        known = getattr(self.policy, "tasks", None)  # the task strings a language/one-hot policy was trained on
        unknown = [t for t in tasks if known and world.task_description(t) not in known]
        if unknown:
            raise UsageError(
                f"the policy was not trained on {', '.join(unknown)}; it knows: {'; '.join(map(repr, known))}"
            )
        return tasks


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
