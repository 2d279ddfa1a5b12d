"""Thread-safe cache of the latest decoded frames, with timestamps and measured frame rates."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from .codec import (
    ID_EMERGENCY_STOP,
    ID_FIRMWARE,
    ID_MODE_CONTROL,
    ID_MOTOR_LIMITS,
    NUM_JOINTS,
    ArmStatus,
    ArmStatusCode,
    CollisionProtectionLevels,
    EmergencyStop,
    GripperCommand,
    GripperFeedback,
    HighSpeedInfo,
    JointCommand,
    JointFeedback,
    LowSpeedInfo,
    ModeControl,
    MotorLimits,
    decode_command,
    decode_feedback,
    parse_firmware_version,
)
from .errors import Fault

RATE_WINDOW_S = 0.5
# Control frames whose every distinct payload is remembered with its newest stamp (not only the latest frame):
# another host's mode changes and resets, so one frame cannot hide an earlier one.
HISTORY_IDS = frozenset({ID_MODE_CONTROL, ID_EMERGENCY_STOP})
_PAYLOADS_KEPT = 512
# Motor torque constants (N·m per A of 0x25x current), J1-J3 and J4-J6, as the vendor SDK scales
# effort. Per the vendor's Q&A, firmware up to S-V1.8-2 may report J1-J3 at a quarter of the torque.
TORQUE_CONSTANTS_NM_PER_A = (1.18125,) * 3 + (0.95844,) * 3
_FIRMWARE_TEXT_MAX = 256
_NOT_FAULTS = {
    ArmStatusCode.NORMAL,
    ArmStatusCode.TEACH_RECORD,
    ArmStatusCode.TEACH_EXECUTE,
    ArmStatusCode.TEACH_PAUSE,
}


@dataclass(frozen=True, slots=True)
class Stamped[T]:
    """A value and when its frame arrived (seconds on the clock's monotonic time, see ``piper_can.link``)."""

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
    foreign_estop: Stamped[EmergencyStop] | None = None  # another host's last 0x150 (stop or reset)
    collision_levels: Stamped[CollisionProtectionLevels] | None = None  # 0x47B, the answer to 0x477 02
    motor_limits: dict[int, MotorLimits] = field(default_factory=dict)
    firmware_version: str | None = None
    rates_hz: dict[int, float] = field(default_factory=dict)

    @property
    def joint_positions_rad(self) -> tuple[float, ...] | None:
        """Measured joint angles, or None until all six have been heard."""
        return _values(self.joints)

    @property
    def joint_velocities_rad_s(self) -> tuple[float, ...] | None:
        """Motor speeds from 0x251..0x256, or None until all six have been heard."""
        if any(s is None for s in self.high_speed):
            return None
        return tuple(s.value.speed_rad_s for s in self.high_speed)  # type: ignore[union-attr]

    @property
    def joint_torques_nm(self) -> tuple[float, ...] | None:
        """Motor torques (current × torque constant) from 0x251..0x256, or None until all six are heard."""
        if any(s is None for s in self.high_speed):
            return None
        currents = (s.value.current_a for s in self.high_speed)  # type: ignore[union-attr]
        return tuple(i * k for i, k in zip(currents, TORQUE_CONSTANTS_NM_PER_A, strict=True))

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
    """The latest raw frame per ID, stored by the reader thread (no decoding on its hot path) and
    decoded into an ``ArmState`` snapshot on demand."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: dict[int, tuple[bytes, float]] = {}
        self._payloads: dict[int, dict[bytes, float]] = {i: {} for i in HISTORY_IDS}
        self._limits: dict[int, MotorLimits] = {}
        self._firmware_text = b""
        self._counts: dict[int, int] = {}
        self._rates: dict[int, float] = {}
        self._window_start: float | None = None

    def update(self, frame_id: int, data: bytes, timestamp: float) -> None:
        """Store one 8-byte frame (feedback, or control frames of another host / linked leader). A frame
        stamped before the one kept for its ID (delivered late) is counted, not kept: the newest wins."""
        if frame_id == ID_MOTOR_LIMITS:  # one reply per motor: keep all of them
            limits = decode_feedback(frame_id, data)
            with self._lock:
                self._limits[limits.motor] = limits
        elif frame_id == ID_FIRMWARE:  # a version text spread over several frames
            with self._lock:
                self._firmware_text = (self._firmware_text + data)[-_FIRMWARE_TEXT_MAX:]
        with self._lock:
            kept = self._latest.get(frame_id)
            if kept is None or kept[1] <= timestamp:
                self._latest[frame_id] = (data, timestamp)
            payloads = self._payloads.get(frame_id)
            if payloads is not None:
                payloads[data] = max(timestamp, payloads.pop(data, timestamp))  # re-inserted: newest last
                if len(payloads) > _PAYLOADS_KEPT:
                    del payloads[next(iter(payloads))]
            self._counts[frame_id] = self._counts.get(frame_id, 0) + 1

    def latest(self, frame_id: int) -> tuple[bytes, float] | None:
        """The raw data and stamp kept for ``frame_id`` (cheap: no decoding), or None."""
        with self._lock:
            return self._latest.get(frame_id)

    def payloads_since(self, frame_id: int, since: float) -> list[tuple[bytes, float]]:
        """Every distinct payload of ``frame_id`` (one of ``HISTORY_IDS``) received after ``since``, with its
        newest stamp, oldest first."""
        with self._lock:
            found = [(data, stamp) for data, stamp in self._payloads[frame_id].items() if stamp > since]
        return sorted(found, key=lambda item: item[1])

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
            latest = dict(self._latest)
            limits = dict(self._limits)
            firmware_text = self._firmware_text
            rates = dict(self._rates)
        joints: list[Stamped[float] | None] = [None] * NUM_JOINTS
        leader_joints: list[Stamped[float] | None] = [None] * NUM_JOINTS
        high: list[Stamped[HighSpeedInfo] | None] = [None] * NUM_JOINTS
        low: list[Stamped[LowSpeedInfo] | None] = [None] * NUM_JOINTS
        found: dict[type, Stamped] = {}
        for frame_id, (data, timestamp) in latest.items():
            if frame_id in (ID_MOTOR_LIMITS, ID_FIRMWARE):
                continue
            message = decode_feedback(frame_id, data) or decode_command(frame_id, data)
            match message:
                case JointFeedback(first_joint=j, positions_rad=(a, b)):
                    joints[j - 1], joints[j] = Stamped(a, timestamp), Stamped(b, timestamp)
                case JointCommand(first_joint=j, positions_rad=(a, b)):
                    leader_joints[j - 1], leader_joints[j] = Stamped(a, timestamp), Stamped(b, timestamp)
                case HighSpeedInfo(joint=j):
                    high[j - 1] = Stamped(message, timestamp)
                case LowSpeedInfo(joint=j):
                    low[j - 1] = Stamped(message, timestamp)
                case (
                    GripperFeedback()
                    | ArmStatus()
                    | GripperCommand()
                    | ModeControl()
                    | EmergencyStop()
                    | CollisionProtectionLevels()
                ):
                    found[type(message)] = Stamped(message, timestamp)
        return ArmState(
            joints=tuple(joints),
            gripper=found.get(GripperFeedback),
            status=found.get(ArmStatus),
            high_speed=tuple(high),
            low_speed=tuple(low),
            leader_joints=tuple(leader_joints),
            leader_gripper=found.get(GripperCommand),
            leader_mode=found.get(ModeControl),
            foreign_estop=found.get(EmergencyStop),
            collision_levels=found.get(CollisionProtectionLevels),
            motor_limits=limits,
            firmware_version=parse_firmware_version(firmware_text),
            rates_hz=rates,
        )
