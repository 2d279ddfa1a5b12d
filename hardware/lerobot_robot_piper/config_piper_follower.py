"""Configuration of the ``piper_follower`` robot (joint angles in radians, gripper opening in metres)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig
from piper_can.driver import DisconnectPolicy, DriverConfig
from piper_can.safety import SDK_SOFT_LIMITS, JointLimits

from .features import GRIPPER_KEY, JOINT_KEYS, MOTOR_KEYS

MOTION_MODES = ("position", "high_follow")


def _default_limits() -> dict[str, tuple[float, float]]:
    limits = dict(zip((k.removesuffix(".pos") for k in JOINT_KEYS), SDK_SOFT_LIMITS.joints_rad, strict=True))
    return {**limits, "gripper": SDK_SOFT_LIMITS.gripper_m}


@RobotConfig.register_subclass("piper_follower")
@dataclass
class PiperFollowerConfig(RobotConfig):
    """An AgileX PiPER arm driven over CAN (``--robot.interface/--robot.channel``)."""

    # python-can interface and channel: socketcan/can0 on a real arm, udp_multicast/<group> for the emulator.
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    # UDP port for interface=udp_multicast (None: python-can's default 43113).
    port: int | None = None
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    # "position": the firmware plans each move at speed_percent; "high_follow": 0xAD, no planning.
    motion_mode: str = "position"
    speed_percent: int = 50
    # Per-command cap on |target - measured| (rad for joints, m for the gripper); a float applies to
    # every key, a dict must name every action key; None turns it off.
    max_relative_target: float | dict[str, float] | None = 0.2
    # Soft limits [lower, upper] in rad (joint_1..joint_6) and m (gripper); targets are clamped to them.
    joint_limits: dict[str, tuple[float, float]] = field(default_factory=_default_limits)
    gripper_effort_nm: float = 1.0
    # Stale-feedback watchdog: no joint feedback for longer than this stops commanding (3 x 5 ms).
    feedback_timeout_s: float = 0.015
    connect_timeout_s: float = 1.0
    enable_timeout_s: float = 2.0
    # "hold": stay enabled at the last target; "rest": walk to rest_pose_rad, then disable.
    disconnect_policy: str = "hold"
    rest_pose_rad: list[float] = field(default_factory=lambda: [0.0] * 6)
    rest_gripper_m: float = 0.0
    rest_speed_rad_s: float = 0.5
    # A leader arm is linked to this follower in hardware (same bus): never send anything, only observe.
    hardware_linked_leader: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.motion_mode not in MOTION_MODES:
            raise ValueError(f"motion_mode must be one of {MOTION_MODES}, got {self.motion_mode!r}")
        if set(self.joint_limits) != {k.removesuffix(".pos") for k in MOTOR_KEYS}:
            raise ValueError("joint_limits must name joint_1 … joint_6 and gripper")
        if isinstance(self.max_relative_target, dict) and set(self.max_relative_target) != set(MOTOR_KEYS):
            raise ValueError(f"max_relative_target as a dict must name exactly {', '.join(MOTOR_KEYS)}")
        self.driver_config()  # validates the rest

    def driver_config(self) -> DriverConfig:
        """The ``piper_can`` driver settings this robot config stands for."""
        cap = self.max_relative_target
        if isinstance(cap, dict):
            joint_steps: float | tuple[float, ...] | None = tuple(float(cap[k]) for k in JOINT_KEYS)
            gripper_step: float | None = float(cap[GRIPPER_KEY])
        else:
            joint_steps = gripper_step = None if cap is None else float(cap)
        limits = JointLimits(
            joints_rad=tuple(tuple(self.joint_limits[k.removesuffix(".pos")]) for k in JOINT_KEYS),
            gripper_m=tuple(self.joint_limits["gripper"]),
        )
        return DriverConfig(
            interface=self.interface,
            channel=self.channel,
            bitrate=self.bitrate,
            bus_options={} if self.port is None else {"port": self.port},
            limits=limits,
            max_step_rad=joint_steps,
            max_gripper_step_m=gripper_step,
            feedback_timeout_s=self.feedback_timeout_s,
            connect_timeout_s=self.connect_timeout_s,
            enable_timeout_s=self.enable_timeout_s,
            speed_percent=self.speed_percent,
            high_follow=self.motion_mode == "high_follow",
            gripper_effort_nm=self.gripper_effort_nm,
            disconnect_policy=DisconnectPolicy(self.disconnect_policy),
            rest_pose_rad=tuple(self.rest_pose_rad),
            rest_gripper_m=self.rest_gripper_m,
            rest_speed_rad_s=self.rest_speed_rad_s,
        )
