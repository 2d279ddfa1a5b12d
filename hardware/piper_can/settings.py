"""The driver's settings: the plain-valued ``DriverSettings`` (shared as they are by the LeRobot plugin's
configs) and ``DriverConfig`` (plus the bus options, limits and step caps), each checked when built, with
the choices they name and the arm's timing facts they are checked against.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum

from .codec import GRIPPER_EFFORT_MAX_NM, NUM_JOINTS
from .safety import SDK_SOFT_LIMITS, JointLimits

FEEDBACK_PERIOD_S = 0.005  # 0x2A1..0x2A8 and 0x251..0x256 at 200 Hz
# The firmware switches the motors off this long after a reset (measured on a real arm).
RESET_MOTOR_OFF_S = 0.73
MOTION_MODES = ("position", "high_follow")
# A watchdog looser than this is no watchdog (200 feedback periods; the emulator over UDP needs 0.1-0.3 s).
MAX_FEEDBACK_TIMEOUT_S = 1.0
MAX_JOINT_SPEED_RAD_S = 3.0  # the firmware's own cap (0x474 accepts 0-3 rad/s)
MAX_JOINT_ACCEL_RAD_S2 = 5.0  # the firmware's own cap (0x475 accepts 0-5 rad/s^2)


class DisconnectPolicy(StrEnum):
    """What ``disconnect`` does to an enabled arm."""

    HOLD = "hold"  # stay enabled, holding the last target (the arm does not fall)
    REST = "rest"  # move slowly to the rest pose, then disable; if it cannot get there, hold


class Recovery(StrEnum):
    """What ``enable`` does about faults the firmware reports (``recovery``)."""

    NONE = "none"  # refuse: raise FirmwareFaultError
    CLEAR_ERRORS = "clear_errors"  # 0x475 clear-error (joints) and 0x159 clear-error (gripper), then enable
    RESET = "reset"  # 0x150 reset (the motors switch off for a moment), then enable


class CollisionOff(StrEnum):
    """What ``connect`` does when the arm reports its collision protection off (level 0) on a joint."""

    WARN = "warn"  # log an error and go on
    REFUSE = "refuse"  # raise CollisionProtectionOffError


class HighFollowExit(StrEnum):
    """What ``enable`` in position mode does when old firmware may still be in high-follow."""

    RESET = "reset"  # leave it with the reset sequence (the motors switch off for a moment)
    REFUSE = "refuse"  # raise HighFollowError


@dataclass
class DriverSettings:
    """The plain-valued driver settings, shared as they are by ``PiperFollowerConfig`` (one source)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    # "position": the firmware plans each move at speed_percent; "high_follow": 0xAD, no planning.
    motion_mode: str = "position"
    speed_percent: int = 50
    gripper_effort_nm: float = 1.0
    # Stale-feedback watchdog: no joint, gripper or status frame for longer than this stops commanding.
    feedback_timeout_s: float = 3 * FEEDBACK_PERIOD_S
    connect_timeout_s: float = 1.0
    enable_timeout_s: float = 2.0
    # After a reset, wait up to this long for the firmware's delayed motor-off (~0.73 s) before enabling.
    reset_settle_s: float = 1.0
    high_follow_exit: str = HighFollowExit.RESET
    recovery: str = Recovery.NONE
    read_firmware_limits: bool = True
    # Also read (and watch) 0x251..0x256: joint velocities and efforts.
    use_velocity_and_torque: bool = False
    disconnect_policy: str = DisconnectPolicy.HOLD
    rest_pose_rad: tuple[float, ...] = (0.0,) * NUM_JOINTS
    rest_gripper_m: float = 0.0
    rest_speed_rad_s: float = 0.5
    rest_timeout_s: float = 10.0
    # The arm's collision protection (0x47B) read on connect; level 0 (off) on a joint: warn or refuse.
    collision_off: str = CollisionOff.WARN
    # The firmware's own per-joint caps, written on connect (they persist in the arm): max joint speed
    # (0x474, sent in 0.01 rad/s) and max joint acceleration (0x475, 0.01 rad/s^2). None: left as they are.
    max_joint_speed_rad_s: float | None = None
    max_joint_accel_rad_s2: float | None = None

    def __post_init__(self) -> None:
        self._check_motion()
        if len(self.rest_pose_rad) != NUM_JOINTS:
            raise ValueError(f"rest_pose_rad needs {NUM_JOINTS} angles, got {len(self.rest_pose_rad)}")
        for j, angle in enumerate(self.rest_pose_rad, start=1):
            _check_range(f"rest_pose_rad[{j}]", angle, -math.pi, math.pi)
        _check_range("rest_gripper_m", self.rest_gripper_m, 0.0, 0.1)
        _check_range("gripper_effort_nm", self.gripper_effort_nm, 0.0, GRIPPER_EFFORT_MAX_NM)
        _check_range("feedback_timeout_s", self.feedback_timeout_s, 0.0, MAX_FEEDBACK_TIMEOUT_S, positive=True)
        _check_range("rest_speed_rad_s", self.rest_speed_rad_s, 0.0, MAX_JOINT_SPEED_RAD_S, positive=True)
        # Shorter than the firmware's delayed motor-off, a reset's re-enable would be lost (the arm left limp).
        _check_range("reset_settle_s", self.reset_settle_s, RESET_MOTOR_OFF_S, 60.0)
        for name in ("connect_timeout_s", "enable_timeout_s", "rest_timeout_s"):
            _check_range(name, getattr(self, name), 0.0, 600.0, positive=True)
        if self.max_joint_speed_rad_s is not None:
            _check_range("max_joint_speed_rad_s", self.max_joint_speed_rad_s, 0.01, MAX_JOINT_SPEED_RAD_S)
        if self.max_joint_accel_rad_s2 is not None:
            _check_range("max_joint_accel_rad_s2", self.max_joint_accel_rad_s2, 0.01, MAX_JOINT_ACCEL_RAD_S2)
        if isinstance(self.bitrate, bool) or not isinstance(self.bitrate, int) or self.bitrate <= 0:
            raise ValueError(f"bitrate must be a positive integer, got {self.bitrate!r}")
        for name, kind in (
            ("disconnect_policy", DisconnectPolicy),
            ("recovery", Recovery),
            ("high_follow_exit", HighFollowExit),
            ("collision_off", CollisionOff),
        ):
            value = getattr(self, name)
            if value not in set(kind):
                raise ValueError(f"{name} must be one of {[k.value for k in kind]}, got {value!r}")

    def _check_motion(self) -> None:
        if self.motion_mode not in MOTION_MODES:
            raise ValueError(f"motion_mode must be one of {MOTION_MODES}, got {self.motion_mode!r}")
        check_speed_percent(self.speed_percent)


def check_speed_percent(value: object) -> None:
    """``speed_percent``: an integer 0..100 (the 0x151 byte)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 100:
        raise ValueError(f"speed_percent must be an integer 0..100, got {value!r}")


def _check_range(name: str, value: object, lower: float, upper: float, positive: bool = False) -> None:
    """One clear error unless ``value`` is a finite number in ``[lower, upper]`` (above ``lower`` when
    ``positive``); NaN fails every bound."""
    number = not isinstance(value, bool) and isinstance(value, int | float)
    if number and math.isfinite(value) and (lower < value if positive else lower <= value) and value <= upper:
        return
    bounds = f"({lower}, {upper}]" if positive else f"[{lower}, {upper}]"
    raise ValueError(f"{name} must be a finite number in {bounds}, got {value!r}")


@dataclass
class DriverConfig(DriverSettings):
    """Bus, motion and safety settings of a ``PiperDriver`` (all safety features on by default)."""

    bus_options: Mapping[str, object] = field(default_factory=dict)
    limits: JointLimits = SDK_SOFT_LIMITS
    # LeRobot ``max_relative_target`` semantics: per command, each target stays within this of the
    # measured position. One value or one per joint; None turns the step limit off.
    max_step_rad: float | Sequence[float] | None = 0.2
    max_gripper_step_m: float | None = 0.02

    def __post_init__(self) -> None:
        super().__post_init__()
        steps = self.joint_steps()
        if steps is not None and not all(0 < s and math.isfinite(s) for s in steps):
            raise ValueError(f"max_step_rad must be positive and finite, got {self.max_step_rad}")
        if self.max_gripper_step_m is not None:
            _check_range("max_gripper_step_m", self.max_gripper_step_m, 0.0, math.inf, positive=True)
        for j, (angle, (lower, upper)) in enumerate(zip(self.rest_pose_rad, self.limits.joints_rad, strict=True), 1):
            if not lower <= angle <= upper:
                raise ValueError(f"rest_pose_rad joint_{j} = {angle} is outside its limits [{lower}, {upper}]")
        lower, upper = self.limits.gripper_m
        if not lower <= self.rest_gripper_m <= upper:
            raise ValueError(f"rest_gripper_m = {self.rest_gripper_m} is outside the gripper range [{lower}, {upper}]")

    @classmethod
    def from_settings(cls, settings: DriverSettings, **extra: object) -> DriverConfig:
        """Every ``DriverSettings`` field of ``settings`` (e.g. a robot config), replaced or added by ``extra``."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(DriverSettings)} | extra)

    @property
    def high_follow(self) -> bool:
        return self.motion_mode == "high_follow"

    def joint_steps(self) -> tuple[float, ...] | None:
        """The per-joint step limit, or None when off."""
        if self.max_step_rad is None:
            return None
        if isinstance(self.max_step_rad, int | float):
            return (float(self.max_step_rad),) * NUM_JOINTS
        steps = tuple(float(s) for s in self.max_step_rad)
        if len(steps) != NUM_JOINTS:
            raise ValueError(f"max_step_rad needs one value or {NUM_JOINTS}, got {len(steps)}")
        return steps
