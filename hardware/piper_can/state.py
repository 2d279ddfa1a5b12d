"""Thread-safe cache of the latest decoded frames, with timestamps and measured frame rates."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from .codec import (
    NUM_JOINTS,
    ArmStatus,
    ArmStatusCode,
    FirmwareChunk,
    GripperCommand,
    GripperFeedback,
    HighSpeedInfo,
    JointCommand,
    JointFeedback,
    LowSpeedInfo,
    ModeControl,
    MotorLimits,
    parse_firmware_version,
)
from .errors import Fault

RATE_WINDOW_S = 0.5
_FIRMWARE_TEXT_MAX = 256
_NOT_FAULTS = {
    ArmStatusCode.NORMAL,
    ArmStatusCode.TEACH_RECORD,
    ArmStatusCode.TEACH_EXECUTE,
    ArmStatusCode.TEACH_PAUSE,
}


@dataclass(frozen=True, slots=True)
class Stamped[T]:
    """A value and the CAN timestamp (seconds, ``time.time()`` epoch) of the frame it came from."""

    value: T
    timestamp: float


@dataclass(frozen=True)
class ArmState:
    """An immutable snapshot of everything last heard on the bus."""

    joints: tuple[Stamped[float] | None, ...]
    gripper: Stamped[GripperFeedback] | None
    status: Stamped[ArmStatus] | None
    high_speed: tuple[Stamped[HighSpeedInfo] | None, ...]
    low_speed: tuple[Stamped[LowSpeedInfo] | None, ...]
    leader_joints: tuple[Stamped[float] | None, ...]
    leader_gripper: Stamped[GripperCommand] | None
    leader_mode: Stamped[ModeControl] | None
    motor_limits: dict[int, MotorLimits] = field(default_factory=dict)
    firmware_version: str | None = None
    rates_hz: dict[int, float] = field(default_factory=dict)

    @property
    def joint_positions_rad(self) -> tuple[float, ...] | None:
        """Measured joint angles, or None until all six have been heard."""
        return _values(self.joints)

    @property
    def leader_joint_targets_rad(self) -> tuple[float, ...] | None:
        """Joint targets sent by another host or a linked leader arm (0x155..0x157)."""
        return _values(self.leader_joints)

    @property
    def joints_enabled(self) -> tuple[bool, ...]:
        """Per-joint driver enable bits (0x261..0x266 byte 5 bit 6); False until heard."""
        return tuple(s is not None and s.value.enabled for s in self.low_speed)

    @property
    def gripper_enabled(self) -> bool:
        return self.gripper is not None and self.gripper.value.enabled

    def faults(self) -> tuple[Fault, ...]:
        """Every fault the firmware currently reports, by part."""
        found: list[Fault] = []
        if self.status is not None:
            status = self.status.value
            if status.arm_status not in _NOT_FAULTS:
                found.append(Fault("arm", _status_name(status.arm_status)))
            found += [Fault(f"joint_{j}", "angle limit exceeded") for j in status.angle_limit_joints]
            found += [Fault(f"joint_{j}", "communication error") for j in status.comm_error_joints]
        for info in self.low_speed:
            if info is not None:
                found += [Fault(f"joint_{info.value.joint}", name) for name in info.value.faults]
        if self.gripper is not None:
            found += [Fault("gripper", name) for name in self.gripper.value.faults]
        return tuple(found)


def _values(stamped: tuple[Stamped[float] | None, ...]) -> tuple[float, ...] | None:
    if any(s is None for s in stamped):
        return None
    return tuple(s.value for s in stamped)  # type: ignore[union-attr]


def _status_name(code: int) -> str:
    try:
        return ArmStatusCode(code).name.lower().replace("_", " ")
    except ValueError:
        return f"unknown status 0x{code:02X}"


class FeedbackCache:
    """Latest value per frame kind, written by the reader thread and read as ``ArmState`` snapshots."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._joints: list[Stamped[float] | None] = [None] * NUM_JOINTS
        self._leader_joints: list[Stamped[float] | None] = [None] * NUM_JOINTS
        self._high: list[Stamped[HighSpeedInfo] | None] = [None] * NUM_JOINTS
        self._low: list[Stamped[LowSpeedInfo] | None] = [None] * NUM_JOINTS
        self._gripper: Stamped[GripperFeedback] | None = None
        self._status: Stamped[ArmStatus] | None = None
        self._leader_gripper: Stamped[GripperCommand] | None = None
        self._leader_mode: Stamped[ModeControl] | None = None
        self._limits: dict[int, MotorLimits] = {}
        self._firmware_text = b""
        self._counts: dict[int, int] = {}
        self._rates: dict[int, float] = {}
        self._window_start: float | None = None

    def update(self, frame_id: int, message: object, timestamp: float) -> None:
        """Store one decoded frame (feedback, or control frames of another host / linked leader)."""
        with self._lock:
            self._counts[frame_id] = self._counts.get(frame_id, 0) + 1
            match message:
                case JointFeedback(first_joint=j, positions_rad=(a, b)):
                    self._joints[j - 1] = Stamped(a, timestamp)
                    self._joints[j] = Stamped(b, timestamp)
                case JointCommand(first_joint=j, positions_rad=(a, b)):
                    self._leader_joints[j - 1] = Stamped(a, timestamp)
                    self._leader_joints[j] = Stamped(b, timestamp)
                case GripperFeedback():
                    self._gripper = Stamped(message, timestamp)
                case ArmStatus():
                    self._status = Stamped(message, timestamp)
                case HighSpeedInfo(joint=j):
                    self._high[j - 1] = Stamped(message, timestamp)
                case LowSpeedInfo(joint=j):
                    self._low[j - 1] = Stamped(message, timestamp)
                case GripperCommand():
                    self._leader_gripper = Stamped(message, timestamp)
                case ModeControl():
                    self._leader_mode = Stamped(message, timestamp)
                case MotorLimits(motor=m):
                    self._limits[m] = message
                case FirmwareChunk(data=data):
                    self._firmware_text = (self._firmware_text + data)[-_FIRMWARE_TEXT_MAX:]

    def roll_rates(self, now: float) -> None:
        """Close the rate window when it is ``RATE_WINDOW_S`` old: rate = frames / elapsed."""
        with self._lock:
            if self._window_start is None:
                self._window_start = now
                return
            elapsed = now - self._window_start
            if elapsed < RATE_WINDOW_S:
                return
            ids = set(self._counts) | set(self._rates)
            self._rates = {i: self._counts.get(i, 0) / elapsed for i in ids}
            self._counts.clear()
            self._window_start = now

    def snapshot(self) -> ArmState:
        with self._lock:
            return ArmState(
                joints=tuple(self._joints),
                gripper=self._gripper,
                status=self._status,
                high_speed=tuple(self._high),
                low_speed=tuple(self._low),
                leader_joints=tuple(self._leader_joints),
                leader_gripper=self._leader_gripper,
                leader_mode=self._leader_mode,
                motor_limits=dict(self._limits),
                firmware_version=parse_firmware_version(self._firmware_text),
                rates_hz=dict(self._rates),
            )
