"""The robot world (``--world.type=robot``): a LeRobot robot on a table, one task, arranged initial states.

``--tasks`` is the task instruction the policy was trained with. Initial states are the arranged-state indices the
operator is prompted with (R-SFT: 0, 1, ...; SPO: the group cursor; evaluation: trial 0 .. N-1). Episodes run on
:class:`~lerobot_cso.worlds.robot.backend.RobotBackend` and are journaled in ``<output_dir>/robot_journal``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lerobot.configs.types import FeatureType
from lerobot.robots import Robot, make_robot_from_config
from lerobot.utils.constants import OBS_IMAGES, OBS_STATE

from lerobot_cso.durable import read_json
from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.journal import TraceJournal
from lerobot_cso.worlds.base import Rollouts
from lerobot_cso.worlds.robot.backend import RobotBackend, state_keys
from lerobot_cso.worlds.robot.devices import Devices
from lerobot_cso.worlds.robot.operator import OperatorConfig

if TYPE_CHECKING:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.robots.config import RobotConfig
    from lerobot.teleoperators.config import TeleoperatorConfig

JOURNAL_DIR = "robot_journal"
EVAL_STATES = 1000  # evaluation trials per run are numbered 0 .. N-1 (the paper: 20)


def camera_shapes(robot: Robot) -> dict[str, tuple[int, ...]]:
    """Camera name → (H, W, 3) of ``robot``."""
    return {k: v for k, v in robot.observation_features.items() if isinstance(v, tuple)}


def check_policy_fits(robot_config: RobotConfig, policy: PreTrainedConfig) -> None:
    """Raise ``UsageError`` unless the policy reads exactly what the robot observes and commands what it takes."""
    quiet = logging.root.manager.disable
    logging.disable(logging.WARNING)  # what a robot logs when built is logged again by the one that connects
    name = robot_config.type
    try:
        robot = make_robot_from_config(robot_config)  # builds the object only: nothing is connected
    except Exception as exc:  # a setting the plugin refuses (e.g. --robot.motion_mode_from=<missing>): one line
        raise UsageError(f"robot {name} cannot be made: {exc.__cause__ or exc}") from exc
    finally:
        logging.disable(quiet)
    inputs, outputs = policy.input_features, policy.output_features
    states, actions, cameras = state_keys(robot), list(robot.action_features), camera_shapes(robot)
    if OBS_STATE in inputs and tuple(inputs[OBS_STATE].shape) != (len(states),):
        raise UsageError(
            f"the policy reads {OBS_STATE} of shape {tuple(inputs[OBS_STATE].shape)}, but robot {name} observes "
            f"{len(states)} values ({', '.join(states)}): it was trained on other features"
        )
    if "action" in outputs and tuple(outputs["action"].shape) != (len(actions),):
        raise UsageError(
            f"the policy outputs actions of shape {tuple(outputs['action'].shape)}, but robot {name} takes "
            f"{len(actions)} ({', '.join(actions)}): it was trained on other features"
        )
    for key, feature in inputs.items():
        if feature.type != FeatureType.VISUAL:
            continue
        cam = key.removeprefix(f"{OBS_IMAGES}.")
        if cam not in cameras:
            have = ", ".join(cameras) or "none"
            raise UsageError(f"the policy reads camera '{cam}', but robot {name} has cameras: {have} (--robot.cameras)")
        c, h, w = feature.shape
        if tuple(cameras[cam]) != (h, w, c):
            raise UsageError(
                f"the policy reads camera '{cam}' as {h}x{w}x{c}, but robot {name} gives {cameras[cam]} "
                f"(set --robot.cameras.{cam}.height/width)"
            )


def policy_fps(policy: PreTrainedConfig) -> int | None:
    """The control fps a policy was trained at: its ``lerobot-train`` dataset's (``train_config.json``), or for
    an R-SFT / SPO checkpoint the fps its robot rollouts ran at (``../robot_journal/spec.json``)."""
    path = getattr(policy, "pretrained_path", None)
    if not path:
        return None
    train = read_json(Path(path) / "train_config.json")
    root = ((train or {}).get("dataset") or {}).get("root")
    info = read_json(Path(root) / "meta" / "info.json") if root else None
    spec = read_json(Path(path).parent / JOURNAL_DIR / "spec.json")
    return (info or {}).get("fps") or (spec or {}).get("fps")


class RobotWorld:
    """A LeRobot robot on a table: one task (the instruction the policy was trained with), arranged states."""

    name = "robot"
    eval_seeds = 1
    eval_states_per_seed = EVAL_STATES

    def __init__(
        self,
        robot: RobotConfig,
        teleop: TeleoperatorConfig | None,
        operator: OperatorConfig,
        display_data: bool,
        tasks: str,
        policy: Any,
        output_dir: Path,
    ) -> None:
        self.robot, self.teleop, self.operator, self.display_data = robot, teleop, operator, display_data
        self.tasks, self.output_dir = tasks, output_dir
        self.policy_path = str(policy.pretrained_path) if policy is not None else None
        self.robot_type = robot.type
        fps = operator.fps or (policy_fps(policy) if policy is not None else None)
        if fps is None:
            raise UsageError(
                "give --operator.fps=<the fps of the dataset the policy was trained on> (--policy.path has no "
                "train_config.json naming a local dataset, and no robot_journal beside it)"
            )
        self.fps = fps
        self.horizon = max(1, round(operator.episode_time_s * fps))

    def resolve_tasks(self, spec: str) -> list[str]:
        if not spec.strip():
            raise ValueError("--tasks must be the task instruction the policy was trained with")
        return [spec.strip()]

    def task_description(self, task: str) -> str:
        return task

    def training_states(self, task: str, purpose: str, start: int, count: int) -> list[int]:
        return list(range(start, start + count))

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        return list(range(count))

    def journal(self) -> TraceJournal:
        """``<output_dir>/robot_journal``: its episodes belong to this robot, task, policy and fps only."""
        spec = {"robot": self.robot_type, "tasks": self.tasks, "policy": self.policy_path, "fps": self.fps}
        return TraceJournal(self.output_dir / JOURNAL_DIR, spec, what="a robot rollout journal")

    def backend(self, rollouts: Rollouts) -> RobotBackend:
        devices = Devices(self.robot, self.teleop)
        journal, fps = self.journal(), self.fps
        return RobotBackend(devices, self.operator, journal, rollouts.cameras, fps, rollouts.horizon, self.display_data)
