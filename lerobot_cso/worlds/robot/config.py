"""``--world.type=robot``: a LeRobot robot on a table, with an operator in the loop (its settings).

``--world.robot.type=...`` (any LeRobot ``Robot``, cameras included) is the arm, ``--world.teleop.type=...``
optionally drives it while the operator arranges the scene, ``--world.operator.*`` says who labels the episodes and
how long they run, ``--world.display_data=true`` shows them in rerun. ``lerobot-cso`` takes the short spellings
``--robot.*``, ``--teleop.*``, ``--operator.*`` and ``--display_data`` for them (:func:`lerobot_cso.cli.main`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import lerobot.scripts.lerobot_record  # noqa: F401  (registers LeRobot's robots, teleoperators and cameras)
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig

from lerobot_cso.errors import UsageError
from lerobot_cso.worlds.base import WorldConfig
from lerobot_cso.worlds.robot.operator import OperatorConfig
from lerobot_cso.worlds.robot.world import RobotWorld, check_policy_fits


@WorldConfig.register_subclass("robot")
@dataclass
class RobotWorldConfig(WorldConfig):
    """A LeRobot robot, an optional teleoperator for the scene-arranging phase, the operator."""

    simulated: ClassVar[bool] = False

    # The robot to roll out on (with an operator).
    robot: RobotConfig | None = None
    # Optional teleoperator that moves the robot while the operator arranges each scene.
    teleop: TeleoperatorConfig | None = None
    operator: OperatorConfig = field(default_factory=OperatorConfig)
    # Show cameras, commanded vs measured joints and the current skill in rerun.
    display_data: bool = False

    def spec(self) -> dict[str, Any]:
        """How the arm is reached and recovered does not change what an episode keeps: the robot's type only."""
        return {"robot": {"type": self.robot.type}, "teleop": self.teleop, "operator": self.operator}

    def validate(self) -> None:
        if self.robot is None:
            raise UsageError("--robot.type is required with --world.type=robot (e.g. piper_follower)")
        self.operator.validate()

    def build(self, tasks: str, policy: Any, output_dir: Path | None) -> RobotWorld:
        if output_dir is None:
            raise UsageError("--output_dir is required with --robot.type (the episodes are journaled there)")
        if policy is not None:
            check_policy_fits(self.robot, policy)
        return RobotWorld(self.robot, self.teleop, self.operator, self.display_data, tasks, policy, output_dir)
