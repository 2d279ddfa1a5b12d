"""Configuration of the ``piper_follower`` robot (joint angles in radians, gripper opening in metres).

Every plain driver setting (bus, motion mode, speed, timeouts, recovery, disconnect policy, rest pose …)
is inherited from ``piper_can.settings.DriverSettings``, with its default and its check; only the
settings LeRobot shapes differently (``max_relative_target``, ``joint_limits``, ``port``), the motion
mode (which defaults to the recorded one) and the robot's own ones are declared here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig
from piper_can.safety import SDK_SOFT_LIMITS, JointLimits
from piper_can.settings import MOTION_MODES, DriverConfig, DriverSettings, check_speed_percent

from .features import GRIPPER_KEY, JOINT_KEYS, MOTOR_KEYS
from .motion_metadata import DEFAULT_MOTION_MODE, DEFAULT_SPEED_PERCENT, MotionMode


def _default_limits() -> dict[str, tuple[float, float]]:
    limits = dict(zip((k.removesuffix(".pos") for k in JOINT_KEYS), SDK_SOFT_LIMITS.joints_rad, strict=True))
    return {**limits, "gripper": SDK_SOFT_LIMITS.gripper_m}


@RobotConfig.register_subclass("piper_follower")
@dataclass
class PiperFollowerConfig(RobotConfig, DriverSettings):
    """An AgileX PiPER arm driven over CAN (``--robot.interface/--robot.channel``)."""

    # "position" or "high_follow"; None: the mode recorded with the dataset or policy being deployed
    # (motion_mode_from, else the command line's --policy.path / --dataset.root / --dataset.repo_id),
    # else position. Giving it overrides the recording.
    motion_mode: str | None = None
    # Firmware speed in position mode; None: the recorded one (when the recorded mode is used), else 50.
    speed_percent: int | None = None
    # UDP port for interface=udp_multicast (None: python-can's default 43113).
    port: int | None = None
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    # Per-command cap on |target - measured|: a float applies to the six joints (rad), a dict must name
    # every action key (rad for joints, m for the gripper) and then also sets the gripper's; None: no
    # cap on the joints.
    max_relative_target: float | dict[str, float] | None = 0.2
    # The gripper's cap in metres unless max_relative_target is a dict (its stroke is only 0.07 m, so
    # the joints' 0.2 would be no cap); None: none.
    gripper_max_relative_target: float | None = 0.02
    # Soft limits [lower, upper] in rad (joint_1..joint_6) and m (gripper); targets are clamped to them
    # (and to the firmware's own limits, read on connect).
    joint_limits: dict[str, tuple[float, float]] = field(default_factory=_default_limits)
    # A leader arm is linked to this follower in hardware (same bus): never send anything, only observe.
    hardware_linked_leader: bool = False
    # A recorded dataset root or a trained policy directory whose recorded motion mode (meta/info.json
    # "piper_motion") to use when motion_mode is None; it must have one. None: the command line's.
    motion_mode_from: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if set(self.joint_limits) != {k.removesuffix(".pos") for k in MOTOR_KEYS}:
            raise ValueError("joint_limits must name joint_1 … joint_6 and gripper")
        if isinstance(self.max_relative_target, dict) and set(self.max_relative_target) != set(MOTOR_KEYS):
            raise ValueError(f"max_relative_target as a dict must name exactly {', '.join(MOTOR_KEYS)}")
        self.rest_pose_rad = tuple(self.rest_pose_rad)
        self.driver_config()  # validates the rest

    def _check_motion(self) -> None:
        if self.motion_mode is not None and self.motion_mode not in MOTION_MODES:
            raise ValueError(f"motion_mode must be one of {MOTION_MODES} or null, got {self.motion_mode!r}")
        if self.speed_percent is not None:
            check_speed_percent(self.speed_percent)

    def resolve_motion(self, recorded: MotionMode | None = None) -> MotionMode:
        """The mode to move in: ``motion_mode`` / ``speed_percent`` where given, the ``recorded`` mode
        where not (its speed only with its mode), else position at 50 %."""
        if self.motion_mode is None and recorded is not None:
            speed = recorded.speed_percent if self.speed_percent is None else self.speed_percent
            return MotionMode(recorded.motion_mode, speed)
        return MotionMode(
            self.motion_mode or DEFAULT_MOTION_MODE,
            DEFAULT_SPEED_PERCENT if self.speed_percent is None else self.speed_percent,
        )

    def driver_config(self, motion: MotionMode | None = None) -> DriverConfig:
        """The ``piper_can`` driver settings this robot config stands for, moving in ``motion``
        (default: ``resolve_motion()``)."""
        motion = motion or self.resolve_motion()
        cap = self.max_relative_target
        if isinstance(cap, dict):
            joint_steps: float | tuple[float, ...] | None = tuple(float(cap[k]) for k in JOINT_KEYS)
            gripper_step: float | None = float(cap[GRIPPER_KEY])
        else:
            joint_steps = None if cap is None else float(cap)
            gripper_step = self.gripper_max_relative_target
        limits = JointLimits(
            joints_rad=tuple(tuple(self.joint_limits[k.removesuffix(".pos")]) for k in JOINT_KEYS),
            gripper_m=tuple(self.joint_limits["gripper"]),
        )
        return DriverConfig.from_settings(
            self,
            bus_options={} if self.port is None else {"port": self.port},
            limits=limits,
            max_step_rad=joint_steps,
            max_gripper_step_m=gripper_step,
            motion_mode=motion.motion_mode,
            speed_percent=motion.speed_percent,
        )
