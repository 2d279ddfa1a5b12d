"""Pure encode/decode of the AgileX PiPER CAN protocol (framing of piper_sdk 0.6.2).

Every frame is a classic CAN 2.0A frame with DLC 8, big-endian fields and unused bytes zero.
The API speaks SI units (radians, metres, newton-metres, volts, amperes, degrees Celsius) and every
field name carries its unit; inside, values are scaled to the firmware's integers exactly once
(``round``), so ``encode(decode(frame)) == frame`` for every well-formed frame.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

# ---------------------------------------------------------------------------------------------- IDs
ID_EMERGENCY_STOP = 0x150
ID_MODE_CONTROL = 0x151
ID_JOINT_COMMAND = (0x155, 0x156, 0x157)
ID_GRIPPER_COMMAND = 0x159
ID_MASTER_SLAVE = 0x470
ID_MOTOR_ENABLE = 0x471
ID_LIMIT_QUERY = 0x472
ID_MOTOR_LIMITS = 0x473
ID_MOTOR_LIMITS_SET = 0x474
ID_JOINT_CONFIG = 0x475
ID_INSTRUCTION_RESPONSE = 0x476
ID_PARAM_QUERY = 0x477
ID_COLLISION_CONFIG = 0x47A
ID_COLLISION_LEVELS = 0x47B
ID_MOTOR_ACCEL_LIMIT = 0x47C
ID_FIRMWARE = 0x4AF
ID_ARM_STATUS = 0x2A1
ID_END_POSE = (0x2A2, 0x2A3, 0x2A4)
ID_JOINT_FEEDBACK = (0x2A5, 0x2A6, 0x2A7)
ID_GRIPPER_FEEDBACK = 0x2A8
ID_HIGH_SPEED = tuple(range(0x251, 0x257))
ID_LOW_SPEED = tuple(range(0x261, 0x267))

DLC = 8
NUM_JOINTS = 6
FIRMWARE_QUERY_PAYLOAD = bytes([0x01]) + bytes(7)


class CodecError(ValueError):
    """A frame or a value that the PiPER protocol cannot represent."""


class Frame(NamedTuple):
    """One CAN frame: standard 11-bit ID and an 8-byte payload."""

    arbitration_id: int
    data: bytes


# ------------------------------------------------------------------------------------ enumerations
class EStopAction(IntEnum):
    """0x150 byte 0."""

    NONE = 0x00
    STOP = 0x01
    RESUME = 0x02


class CtrlMode(IntEnum):
    """0x151 byte 0 (command) and 0x2A1 byte 0 (feedback, which adds TEACH and LINKAGE_TEACH)."""

    STANDBY = 0x00
    CAN = 0x01
    TEACH = 0x02
    ETHERNET = 0x03
    WIFI = 0x04
    REMOTE = 0x05
    LINKAGE_TEACH = 0x06
    OFFLINE_TRAJECTORY = 0x07


class MoveMode(IntEnum):
    """0x151 byte 1 and 0x2A1 byte 2."""

    P = 0x00
    J = 0x01
    L = 0x02
    C = 0x03
    M = 0x04
    CPV = 0x05


MIT_MODE_POSITION_VELOCITY = 0x00
MIT_MODE_HIGH_FOLLOW = 0xAD


class ArmStatusCode(IntEnum):
    """0x2A1 byte 1."""

    NORMAL = 0x00
    EMERGENCY_STOP = 0x01
    NO_SOLUTION = 0x02
    SINGULARITY = 0x03
    TARGET_EXCEEDS_LIMIT = 0x04
    JOINT_COMM_ERROR = 0x05
    BRAKE_NOT_RELEASED = 0x06
    COLLISION = 0x07
    DRAG_TEACH_OVERSPEED = 0x08
    JOINT_STATUS_ERROR = 0x09
    OTHER = 0x0A
    TEACH_RECORD = 0x0B
    TEACH_EXECUTE = 0x0C
    TEACH_PAUSE = 0x0D
    MAINBOARD_OVER_TEMPERATURE = 0x0E
    DISCHARGE_RESISTOR_OVER_TEMPERATURE = 0x0F


class GripperStatusCode(IntEnum):
    """0x159 byte 6."""

    DISABLE = 0x00
    ENABLE = 0x01
    DISABLE_CLEAR_ERROR = 0x02
    ENABLE_CLEAR_ERROR = 0x03


class Linkage(IntEnum):
    """0x470 byte 0."""

    NONE = 0x00
    LEADER = 0xFA  # "teaching input arm"
    FOLLOWER = 0xFC  # "motion output arm"


MOTOR_ALL_JOINTS = 0x07  # what piper_sdk's EnableArm sends
MOTOR_ALL = 0xFF
GRIPPER_SET_ZERO = 0xAE
FLAG_VALID = 0xAE  # 0x475 set-zero / accel-valid / clear-error flags
ACCEL_NO_CHANGE = 0x7FFF  # 0x475 max acceleration "no change" (firmware >= V1.5-2)
LIMIT_QUERY_ANGLE_SPEED = 0x01
LIMIT_QUERY_ACCELERATION = 0x02
LIMIT_NO_CHANGE = 0x7FFF  # 0x474 angle or speed field "no change"
PARAM_QUERY_COLLISION = 0x02  # 0x477 byte 0: ask for the collision-protection levels (0x47B)
END_LOAD_NO_CHANGE = 0x03  # 0x477 byte 4: the end-load setting is not touched
COLLISION_LEVEL_MAX = 8  # 0x47A/0x47B per joint: 0 = collision detection off, 1..8 = sensitivity
GRIPPER_EFFORT_MAX_NM = 5.0

# 0x26x byte 5 and 0x2A8 byte 6: bit -> fault name; bit 6 is "enabled" in both.
DRIVER_FAULT_BITS = {
    0: "under-voltage",
    1: "motor over-temperature",
    2: "over-current",
    3: "driver over-temperature",
    4: "collision protection triggered",
    5: "driver error",
    7: "stall protection triggered",
}
GRIPPER_FAULT_BITS = {
    0: "under-voltage",
    1: "motor over-temperature",
    2: "over-current",
    3: "driver over-temperature",
    4: "sensor error",
    5: "driver error",
}
ENABLED_BIT = 6
GRIPPER_HOMED_BIT = 7


# ------------------------------------------------------------------------------- integer scaling
def _scaled(value: float, per_unit: float, name: str) -> int:
    """``round(value * per_unit)``, refusing NaN and infinities with a clear message."""
    if not math.isfinite(value):
        raise CodecError(f"{name} must be a finite number, got {value!r}")
    return round(value * per_unit)


def rad_to_millideg(rad: float, name: str = "angle") -> int:
    """Radians to the firmware's 0.001° integer."""
    return _scaled(math.degrees(rad), 1000, name)


def millideg_to_rad(raw: int) -> float:
    """The firmware's 0.001° integer to radians."""
    return math.radians(raw / 1000)


def rad_to_decideg(rad: float, name: str = "angle") -> int:
    """Radians to 0.1° (motor limit frames)."""
    return _scaled(math.degrees(rad), 10, name)


def decideg_to_rad(raw: int) -> float:
    """0.1° to radians."""
    return math.radians(raw / 10)


def _pack(fmt: str, values: Sequence[int], what: str) -> bytes:
    """``struct.pack`` big-endian into exactly 8 bytes; a value that does not fit is a CodecError."""
    try:
        payload = struct.pack(">" + fmt, *values)
    except struct.error as exc:
        raise CodecError(f"{what}: value out of range for the frame field ({exc}): {list(values)}") from exc
    return payload.ljust(DLC, b"\x00")


def _check_byte(value: int, name: str) -> int:
    if not 0 <= value <= 0xFF:
        raise CodecError(f"{name} must be a byte (0..255), got {value}")
    return value


# ------------------------------------------------------------------------- host -> arm messages
@dataclass(frozen=True, slots=True)
class EmergencyStop:
    """0x150: quick stop (the arm is damped and sinks) or resume (reset: motors drop, standby)."""

    action: EStopAction


@dataclass(frozen=True, slots=True)
class ModeControl:
    """0x151: control mode, move mode, speed % and the MIT / high-follow byte."""

    ctrl_mode: int
    move_mode: int
    speed_percent: int
    mit_mode: int = MIT_MODE_POSITION_VELOCITY
    residence_time_s: int = 0
    installation_pos: int = 0


@dataclass(frozen=True, slots=True)
class JointCommand:
    """0x155 / 0x156 / 0x157: target angles of joints (first_joint, first_joint + 1)."""

    first_joint: int
    positions_rad: tuple[float, float]


@dataclass(frozen=True, slots=True)
class GripperCommand:
    """0x159: gripper opening (finger distance), effort, enable / clear-error code, set-zero flag."""

    opening_m: float
    effort_nm: float
    status_code: int = GripperStatusCode.ENABLE
    set_zero: bool = False


@dataclass(frozen=True, slots=True)
class MasterSlaveConfig:
    """0x470: leader ("teaching input") / follower ("motion output") role and ID offsets."""

    linkage: int
    feedback_offset: int = 0
    ctrl_offset: int = 0
    linkage_offset: int = 0


@dataclass(frozen=True, slots=True)
class MotorEnable:
    """0x471: enable or disable motor ``motor`` (1..6 one joint, 7 or 0xFF all)."""

    motor: int
    enable: bool


@dataclass(frozen=True, slots=True)
class LimitQuery:
    """0x472: ask for a motor's angle/speed limits (kind 1) or acceleration limit (kind 2)."""

    motor: int
    kind: int = LIMIT_QUERY_ANGLE_SPEED


@dataclass(frozen=True, slots=True)
class FirmwareQuery:
    """0x4AF ``01 00 …``: ask for the firmware version string."""


@dataclass(frozen=True, slots=True)
class JointConfig:
    """0x475: per joint (1..6, 7 = all) set zero, set the max acceleration, clear the joint's errors.

    ``max_accel_raw`` is in 0.01 rad/s² and applies only with ``accel_valid`` (0x7FFF: no change).
    """

    joint: int
    set_zero: bool = False
    accel_valid: bool = False
    max_accel_raw: int = ACCEL_NO_CHANGE
    clear_error: bool = False


@dataclass(frozen=True, slots=True)
class MotorLimitsSet:
    """0x474: set a motor's (1..6) flash angle limits and max speed; None leaves a field as it is.

    ``max_speed_raw`` stays raw: its unit is disputed (0.001 or 0.01 rad/s, see 0x473).
    """

    motor: int
    max_angle_rad: float | None = None
    min_angle_rad: float | None = None
    max_speed_raw: int | None = None


@dataclass(frozen=True, slots=True)
class ParamQuery:
    """0x477 as a query: ``enquiry`` 0x02 asks for the collision-protection levels (answer 0x47B)."""

    enquiry: int


@dataclass(frozen=True, slots=True)
class CollisionProtectionConfig:
    """0x47A: set each joint's collision-protection level (0 off, 1..8)."""

    levels: tuple[int, ...]


# ------------------------------------------------------------------------- arm -> host messages
@dataclass(frozen=True, slots=True)
class ArmStatus:
    """0x2A1: control mode, status code, move mode, teach state, motion state, error bit masks."""

    ctrl_mode: int
    arm_status: int
    mode_feed: int
    teach_status: int = 0
    motion_status: int = 0
    trajectory_index: int = 0
    angle_limit_mask: int = 0
    comm_error_mask: int = 0

    @property
    def target_reached(self) -> bool:
        return self.motion_status == 0

    @property
    def angle_limit_joints(self) -> tuple[int, ...]:
        """1-based joints whose angle limit is exceeded."""
        return _mask_joints(self.angle_limit_mask)

    @property
    def comm_error_joints(self) -> tuple[int, ...]:
        """1-based joints with a communication error."""
        return _mask_joints(self.comm_error_mask)


@dataclass(frozen=True, slots=True)
class JointFeedback:
    """0x2A5 / 0x2A6 / 0x2A7: measured angles of joints (first_joint, first_joint + 1)."""

    first_joint: int
    positions_rad: tuple[float, float]


@dataclass(frozen=True, slots=True)
class GripperFeedback:
    """0x2A8: measured opening, effort and status bits of the gripper."""

    opening_m: float
    effort_nm: float
    status: int = 0

    @property
    def enabled(self) -> bool:
        return bool(self.status >> ENABLED_BIT & 1)

    @property
    def homed(self) -> bool:
        return bool(self.status >> GRIPPER_HOMED_BIT & 1)

    @property
    def faults(self) -> tuple[str, ...]:
        return _bit_names(self.status, GRIPPER_FAULT_BITS)


@dataclass(frozen=True, slots=True)
class HighSpeedInfo:
    """0x251..0x256: motor speed, current and position (position unit per pyAgxArm: 0.001 rad)."""

    joint: int
    speed_rad_s: float
    current_a: float
    position_rad: float


@dataclass(frozen=True, slots=True)
class LowSpeedInfo:
    """0x261..0x266: driver voltage, temperatures, status bits (enable, faults) and bus current."""

    joint: int
    voltage_v: float
    driver_temp_c: int
    motor_temp_c: int
    status: int
    bus_current_a: float

    @property
    def enabled(self) -> bool:
        return bool(self.status >> ENABLED_BIT & 1)

    @property
    def faults(self) -> tuple[str, ...]:
        return _bit_names(self.status, DRIVER_FAULT_BITS)


@dataclass(frozen=True, slots=True)
class MotorLimits:
    """0x473: a motor's flash angle limits; the max-speed unit is disputed, so it stays raw."""

    motor: int
    max_angle_rad: float
    min_angle_rad: float
    max_speed_raw: int


@dataclass(frozen=True, slots=True)
class MotorAccelLimit:
    """0x47C: a motor's maximum acceleration."""

    motor: int
    max_accel_rad_s2: float


@dataclass(frozen=True, slots=True)
class FirmwareChunk:
    """0x4AF (arm -> host): 8 bytes of the ASCII firmware version text."""

    data: bytes


@dataclass(frozen=True, slots=True)
class CollisionProtectionLevels:
    """0x47B: each joint's collision-protection level (0 = detection off, 1..8)."""

    levels: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class InstructionResponse:
    """0x476: the arm acknowledges a setting command (``command`` = low byte of its ID, e.g. 0x75)."""

    command: int
    zero_set_ok: bool = False


CommandMessage = (
    EmergencyStop
    | ModeControl
    | JointCommand
    | GripperCommand
    | MasterSlaveConfig
    | MotorEnable
    | LimitQuery
    | FirmwareQuery
    | JointConfig
    | MotorLimitsSet
    | ParamQuery
    | CollisionProtectionConfig
)
FeedbackMessage = (
    ArmStatus
    | JointFeedback
    | GripperFeedback
    | HighSpeedInfo
    | LowSpeedInfo
    | MotorLimits
    | MotorAccelLimit
    | FirmwareChunk
    | InstructionResponse
    | CollisionProtectionLevels
)


def _mask_joints(mask: int) -> tuple[int, ...]:
    return tuple(j + 1 for j in range(NUM_JOINTS) if mask >> j & 1)


def _bit_names(status: int, names: dict[int, str]) -> tuple[str, ...]:
    return tuple(name for bit, name in names.items() if status >> bit & 1)


def _pair_id(ids: tuple[int, ...], first_joint: int, what: str) -> int:
    if first_joint not in (1, 3, 5):
        raise CodecError(f"{what}: first_joint must be 1, 3 or 5, got {first_joint}")
    return ids[(first_joint - 1) // 2]


def _joint_id(ids: tuple[int, ...], joint: int, what: str) -> int:
    if not 1 <= joint <= NUM_JOINTS:
        raise CodecError(f"{what}: joint must be 1..6, got {joint}")
    return ids[joint - 1]


# ------------------------------------------------------------------------------------- encoders
def encode_emergency_stop(msg: EmergencyStop) -> Frame:
    return Frame(ID_EMERGENCY_STOP, _pack("B", [EStopAction(msg.action)], "0x150"))


def encode_mode_control(msg: ModeControl) -> Frame:
    if not 0 <= msg.speed_percent <= 100:
        raise CodecError(f"0x151: speed_percent must be 0..100, got {msg.speed_percent}")
    values = [msg.ctrl_mode, msg.move_mode, msg.speed_percent, msg.mit_mode, msg.residence_time_s]
    return Frame(ID_MODE_CONTROL, _pack("6B", [*values, msg.installation_pos], "0x151"))


def encode_joint_command(msg: JointCommand) -> Frame:
    frame_id = _pair_id(ID_JOINT_COMMAND, msg.first_joint, "joint command")
    raw = [rad_to_millideg(p, f"joint_{msg.first_joint + i} target") for i, p in enumerate(msg.positions_rad)]
    return Frame(frame_id, _pack("ii", raw, f"0x{frame_id:X}"))


def encode_gripper_command(msg: GripperCommand) -> Frame:
    if not 0.0 <= msg.effort_nm <= GRIPPER_EFFORT_MAX_NM:
        raise CodecError(f"0x159: effort_nm must be 0..{GRIPPER_EFFORT_MAX_NM}, got {msg.effort_nm}")
    raw = [
        _scaled(msg.opening_m, 1e6, "gripper opening_m"),
        _scaled(msg.effort_nm, 1e3, "gripper effort_nm"),
        _check_byte(msg.status_code, "gripper status_code"),
        GRIPPER_SET_ZERO if msg.set_zero else 0,
    ]
    return Frame(ID_GRIPPER_COMMAND, _pack("iHBB", raw, "0x159"))


def encode_master_slave(msg: MasterSlaveConfig) -> Frame:
    raw = [msg.linkage, msg.feedback_offset, msg.ctrl_offset, msg.linkage_offset]
    return Frame(ID_MASTER_SLAVE, _pack("4B", raw, "0x470"))


def encode_motor_enable(msg: MotorEnable) -> Frame:
    return Frame(ID_MOTOR_ENABLE, _pack("BB", [msg.motor, 0x02 if msg.enable else 0x01], "0x471"))


def encode_limit_query(msg: LimitQuery) -> Frame:
    return Frame(ID_LIMIT_QUERY, _pack("BB", [msg.motor, msg.kind], "0x472"))


def encode_firmware_query(_: FirmwareQuery) -> Frame:
    return Frame(ID_FIRMWARE, FIRMWARE_QUERY_PAYLOAD)


def _flag(value: bool) -> int:
    return FLAG_VALID if value else 0


def encode_joint_config(msg: JointConfig) -> Frame:
    if not 1 <= msg.joint <= NUM_JOINTS + 1:
        raise CodecError(f"0x475: joint must be 1..7 (7 = all), got {msg.joint}")
    raw = [msg.joint, _flag(msg.set_zero), _flag(msg.accel_valid), msg.max_accel_raw, _flag(msg.clear_error)]
    return Frame(ID_JOINT_CONFIG, _pack("BBBHB", raw, "0x475"))


def encode_motor_limits_set(msg: MotorLimitsSet) -> Frame:
    if not 1 <= msg.motor <= NUM_JOINTS:
        raise CodecError(f"0x474: motor must be 1..6, got {msg.motor}")

    def angle(rad: float | None, name: str) -> int:
        return LIMIT_NO_CHANGE if rad is None else rad_to_decideg(rad, name)

    speed = LIMIT_NO_CHANGE if msg.max_speed_raw is None else msg.max_speed_raw
    raw = [msg.motor, angle(msg.max_angle_rad, "max_angle_rad"), angle(msg.min_angle_rad, "min_angle_rad"), speed]
    return Frame(ID_MOTOR_LIMITS_SET, _pack("BhhH", raw, "0x474"))


def encode_param_query(msg: ParamQuery) -> Frame:
    return Frame(ID_PARAM_QUERY, _pack("BBBBB", [msg.enquiry, 0, 0, 0, END_LOAD_NO_CHANGE], "0x477"))


def _levels(levels: Sequence[int], what: str) -> list[int]:
    if len(levels) != NUM_JOINTS or not all(0 <= v <= COLLISION_LEVEL_MAX for v in levels):
        raise CodecError(f"{what}: needs {NUM_JOINTS} levels 0..{COLLISION_LEVEL_MAX}, got {tuple(levels)}")
    return list(levels)


def encode_collision_config(msg: CollisionProtectionConfig) -> Frame:
    return Frame(ID_COLLISION_CONFIG, _pack("6B", _levels(msg.levels, "0x47A"), "0x47A"))


def encode_collision_levels(msg: CollisionProtectionLevels) -> Frame:
    return Frame(ID_COLLISION_LEVELS, _pack("6B", _levels(msg.levels, "0x47B"), "0x47B"))


def encode_arm_status(msg: ArmStatus) -> Frame:
    raw = [
        msg.ctrl_mode,
        msg.arm_status,
        msg.mode_feed,
        msg.teach_status,
        msg.motion_status,
        msg.trajectory_index,
        msg.angle_limit_mask,
        msg.comm_error_mask,
    ]
    return Frame(ID_ARM_STATUS, _pack("8B", raw, "0x2A1"))


def encode_joint_feedback(msg: JointFeedback) -> Frame:
    frame_id = _pair_id(ID_JOINT_FEEDBACK, msg.first_joint, "joint feedback")
    raw = [rad_to_millideg(p, f"joint_{msg.first_joint + i}") for i, p in enumerate(msg.positions_rad)]
    return Frame(frame_id, _pack("ii", raw, f"0x{frame_id:X}"))


def encode_gripper_feedback(msg: GripperFeedback) -> Frame:
    raw = [_scaled(msg.opening_m, 1e6, "gripper opening_m"), _scaled(msg.effort_nm, 1e3, "effort_nm")]
    return Frame(ID_GRIPPER_FEEDBACK, _pack("ihB", [*raw, msg.status], "0x2A8"))


def encode_high_speed(msg: HighSpeedInfo) -> Frame:
    frame_id = _joint_id(ID_HIGH_SPEED, msg.joint, "high-speed info")
    raw = [
        _scaled(msg.speed_rad_s, 1e3, "speed_rad_s"),
        _scaled(msg.current_a, 1e3, "current_a"),
        _scaled(msg.position_rad, 1e3, "position_rad"),
    ]
    return Frame(frame_id, _pack("hhi", raw, f"0x{frame_id:X}"))


def encode_low_speed(msg: LowSpeedInfo) -> Frame:
    frame_id = _joint_id(ID_LOW_SPEED, msg.joint, "low-speed info")
    raw = [
        _scaled(msg.voltage_v, 10, "voltage_v"),
        msg.driver_temp_c,
        msg.motor_temp_c,
        msg.status,
        _scaled(msg.bus_current_a, 1e3, "bus_current_a"),
    ]
    return Frame(frame_id, _pack("HhbBH", raw, f"0x{frame_id:X}"))


def encode_motor_limits(msg: MotorLimits) -> Frame:
    raw = [
        msg.motor,
        rad_to_decideg(msg.max_angle_rad, "max_angle_rad"),
        rad_to_decideg(msg.min_angle_rad, "min_angle_rad"),
        msg.max_speed_raw,
    ]
    return Frame(ID_MOTOR_LIMITS, _pack("BhhH", raw, "0x473"))


def encode_motor_accel_limit(msg: MotorAccelLimit) -> Frame:
    raw = [msg.motor, _scaled(msg.max_accel_rad_s2, 100, "max_accel_rad_s2")]
    return Frame(ID_MOTOR_ACCEL_LIMIT, _pack("BH", raw, "0x47C"))


def encode_firmware_chunk(msg: FirmwareChunk) -> Frame:
    if len(msg.data) > DLC:
        raise CodecError(f"0x4AF: a firmware chunk holds at most 8 bytes, got {len(msg.data)}")
    return Frame(ID_FIRMWARE, bytes(msg.data).ljust(DLC, b"\x00"))


def encode_instruction_response(msg: InstructionResponse) -> Frame:
    return Frame(ID_INSTRUCTION_RESPONSE, _pack("BB", [msg.command, int(msg.zero_set_ok)], "0x476"))


_ENCODERS: dict[type, Callable] = {
    EmergencyStop: encode_emergency_stop,
    ModeControl: encode_mode_control,
    JointCommand: encode_joint_command,
    GripperCommand: encode_gripper_command,
    MasterSlaveConfig: encode_master_slave,
    MotorEnable: encode_motor_enable,
    LimitQuery: encode_limit_query,
    FirmwareQuery: encode_firmware_query,
    JointConfig: encode_joint_config,
    MotorLimitsSet: encode_motor_limits_set,
    ParamQuery: encode_param_query,
    CollisionProtectionConfig: encode_collision_config,
    CollisionProtectionLevels: encode_collision_levels,
    ArmStatus: encode_arm_status,
    JointFeedback: encode_joint_feedback,
    GripperFeedback: encode_gripper_feedback,
    HighSpeedInfo: encode_high_speed,
    LowSpeedInfo: encode_low_speed,
    MotorLimits: encode_motor_limits,
    MotorAccelLimit: encode_motor_accel_limit,
    FirmwareChunk: encode_firmware_chunk,
    InstructionResponse: encode_instruction_response,
}


def encode(msg: CommandMessage | FeedbackMessage) -> Frame:
    """Encode any protocol message into its frame."""
    try:
        encoder = _ENCODERS[type(msg)]
    except KeyError:
        raise CodecError(f"not a PiPER protocol message: {msg!r}") from None
    return encoder(msg)


def encode_joint_targets(positions_rad: Sequence[float]) -> tuple[Frame, Frame, Frame]:
    """The three JointCtrl frames (0x155..0x157) for six target angles."""
    if len(positions_rad) != NUM_JOINTS:
        raise CodecError(f"expected {NUM_JOINTS} joint targets, got {len(positions_rad)}")
    return tuple(  # type: ignore[return-value]
        encode_joint_command(JointCommand(j, (positions_rad[j - 1], positions_rad[j]))) for j in (1, 3, 5)
    )


def encode_joint_positions(positions_rad: Sequence[float]) -> tuple[Frame, Frame, Frame]:
    """The three joint feedback frames (0x2A5..0x2A7) for six measured angles."""
    if len(positions_rad) != NUM_JOINTS:
        raise CodecError(f"expected {NUM_JOINTS} joint positions, got {len(positions_rad)}")
    return tuple(  # type: ignore[return-value]
        encode_joint_feedback(JointFeedback(j, (positions_rad[j - 1], positions_rad[j]))) for j in (1, 3, 5)
    )


# ------------------------------------------------------------------------------------- decoders
def _unpack(fmt: str, data: bytes) -> tuple:
    return struct.unpack_from(">" + fmt, data)


def _decode_emergency_stop(_: int, data: bytes) -> EmergencyStop:
    try:
        return EmergencyStop(EStopAction(data[0]))
    except ValueError:
        raise CodecError(f"0x150: unknown action byte 0x{data[0]:02X}") from None


def _decode_mode_control(_: int, data: bytes) -> ModeControl:
    return ModeControl(*_unpack("6B", data))


def _decode_joint_command(frame_id: int, data: bytes) -> JointCommand:
    a, b = _unpack("ii", data)
    first = 1 + 2 * ID_JOINT_COMMAND.index(frame_id)
    return JointCommand(first, (millideg_to_rad(a), millideg_to_rad(b)))


def _decode_gripper_command(_: int, data: bytes) -> GripperCommand:
    opening, effort, code, zero = _unpack("iHBB", data)
    return GripperCommand(opening / 1e6, effort / 1e3, code, zero == GRIPPER_SET_ZERO)


def _decode_master_slave(_: int, data: bytes) -> MasterSlaveConfig:
    return MasterSlaveConfig(*_unpack("4B", data))


def _decode_motor_enable(_: int, data: bytes) -> MotorEnable:
    motor, flag = _unpack("BB", data)
    if flag not in (0x01, 0x02):
        raise CodecError(f"0x471: enable flag must be 0x01 or 0x02, got 0x{flag:02X}")
    return MotorEnable(motor, flag == 0x02)


def _decode_limit_query(_: int, data: bytes) -> LimitQuery:
    return LimitQuery(*_unpack("BB", data))


def _decode_firmware_query(_: int, data: bytes) -> FirmwareQuery:
    if data[0] != 0x01:
        raise CodecError(f"0x4AF: a version query starts with 0x01, got 0x{data[0]:02X}")
    return FirmwareQuery()


def _decode_joint_config(_: int, data: bytes) -> JointConfig:
    joint, zero, accel_valid, accel, clear = _unpack("BBBHB", data)
    for name, value in (("set-zero", zero), ("accel-valid", accel_valid), ("clear-error", clear)):
        if value not in (0, FLAG_VALID):
            raise CodecError(f"0x475: the {name} flag must be 0x00 or 0xAE, got 0x{value:02X}")
    return JointConfig(joint, zero == FLAG_VALID, accel_valid == FLAG_VALID, accel, clear == FLAG_VALID)


def _decode_motor_limits_set(_: int, data: bytes) -> MotorLimitsSet:
    motor, max_angle, min_angle, speed = _unpack("BhhH", data)

    def angle(raw: int) -> float | None:
        return None if raw == LIMIT_NO_CHANGE else decideg_to_rad(raw)

    return MotorLimitsSet(motor, angle(max_angle), angle(min_angle), None if speed == LIMIT_NO_CHANGE else speed)


def _decode_param_query(_: int, data: bytes) -> ParamQuery:
    return ParamQuery(data[0])


def _decode_collision_config(_: int, data: bytes) -> CollisionProtectionConfig:
    return CollisionProtectionConfig(tuple(_levels(_unpack("6B", data), "0x47A")))


def _decode_collision_levels(_: int, data: bytes) -> CollisionProtectionLevels:
    return CollisionProtectionLevels(tuple(_levels(_unpack("6B", data), "0x47B")))


def _decode_arm_status(_: int, data: bytes) -> ArmStatus:
    return ArmStatus(*_unpack("8B", data))


def _decode_joint_feedback(frame_id: int, data: bytes) -> JointFeedback:
    a, b = _unpack("ii", data)
    first = 1 + 2 * ID_JOINT_FEEDBACK.index(frame_id)
    return JointFeedback(first, (millideg_to_rad(a), millideg_to_rad(b)))


def _decode_gripper_feedback(_: int, data: bytes) -> GripperFeedback:
    opening, effort, status = _unpack("ihB", data)
    return GripperFeedback(opening / 1e6, effort / 1e3, status)


def _decode_high_speed(frame_id: int, data: bytes) -> HighSpeedInfo:
    speed, current, position = _unpack("hhi", data)
    return HighSpeedInfo(ID_HIGH_SPEED.index(frame_id) + 1, speed / 1e3, current / 1e3, position / 1e3)


def _decode_low_speed(frame_id: int, data: bytes) -> LowSpeedInfo:
    voltage, driver_temp, motor_temp, status, bus_current = _unpack("HhbBH", data)
    joint = ID_LOW_SPEED.index(frame_id) + 1
    return LowSpeedInfo(joint, voltage / 10, driver_temp, motor_temp, status, bus_current / 1e3)


def _decode_motor_limits(_: int, data: bytes) -> MotorLimits:
    motor, max_angle, min_angle, max_speed = _unpack("BhhH", data)
    return MotorLimits(motor, decideg_to_rad(max_angle), decideg_to_rad(min_angle), max_speed)


def _decode_motor_accel_limit(_: int, data: bytes) -> MotorAccelLimit:
    motor, accel = _unpack("BH", data)
    return MotorAccelLimit(motor, accel / 100)


def _decode_firmware_chunk(_: int, data: bytes) -> FirmwareChunk:
    return FirmwareChunk(bytes(data))


def _decode_instruction_response(_: int, data: bytes) -> InstructionResponse:
    command, ok = _unpack("BB", data)
    return InstructionResponse(command, ok == 0x01)


_Decoder = Callable[[int, bytes], object]

_COMMAND_DECODERS: dict[int, _Decoder] = {
    ID_EMERGENCY_STOP: _decode_emergency_stop,
    ID_MODE_CONTROL: _decode_mode_control,
    **dict.fromkeys(ID_JOINT_COMMAND, _decode_joint_command),
    ID_GRIPPER_COMMAND: _decode_gripper_command,
    ID_MASTER_SLAVE: _decode_master_slave,
    ID_MOTOR_ENABLE: _decode_motor_enable,
    ID_LIMIT_QUERY: _decode_limit_query,
    ID_FIRMWARE: _decode_firmware_query,
    ID_JOINT_CONFIG: _decode_joint_config,
    ID_MOTOR_LIMITS_SET: _decode_motor_limits_set,
    ID_PARAM_QUERY: _decode_param_query,
    ID_COLLISION_CONFIG: _decode_collision_config,
}

_FEEDBACK_DECODERS: dict[int, _Decoder] = {
    ID_ARM_STATUS: _decode_arm_status,
    **dict.fromkeys(ID_JOINT_FEEDBACK, _decode_joint_feedback),
    ID_GRIPPER_FEEDBACK: _decode_gripper_feedback,
    **dict.fromkeys(ID_HIGH_SPEED, _decode_high_speed),
    **dict.fromkeys(ID_LOW_SPEED, _decode_low_speed),
    ID_MOTOR_LIMITS: _decode_motor_limits,
    ID_MOTOR_ACCEL_LIMIT: _decode_motor_accel_limit,
    ID_FIRMWARE: _decode_firmware_chunk,
    ID_INSTRUCTION_RESPONSE: _decode_instruction_response,
    ID_COLLISION_LEVELS: _decode_collision_levels,
}

COMMAND_IDS = frozenset(_COMMAND_DECODERS)
FEEDBACK_IDS = frozenset(_FEEDBACK_DECODERS)


def _decode(table: dict[int, _Decoder], arbitration_id: int, data: bytes, direction: str):
    decoder = table.get(arbitration_id)
    if decoder is None:
        return None
    if len(data) != DLC:
        raise CodecError(f"0x{arbitration_id:X} ({direction}): expected 8 data bytes, got {len(data)}")
    return decoder(arbitration_id, bytes(data))


def decode_command(arbitration_id: int, data: bytes) -> CommandMessage | None:
    """Decode a host -> arm frame; ``None`` for an ID this codec does not know."""
    return _decode(_COMMAND_DECODERS, arbitration_id, data, "command")


def decode_feedback(arbitration_id: int, data: bytes) -> FeedbackMessage | None:
    """Decode an arm -> host frame; ``None`` for an ID this codec does not know."""
    return _decode(_FEEDBACK_DECODERS, arbitration_id, data, "feedback")


def firmware_release(version: str | None) -> tuple[int, ...] | None:
    """``"S-V1.8-2"`` as ``(1, 8, 2)``; None if it is not of that form."""
    if version is None or not version.startswith("S-V"):
        return None
    try:
        return tuple(int(part) for part in version[3:].replace("-", ".").split("."))
    except ValueError:
        return None


def parse_firmware_version(text: bytes) -> str | None:
    """The ``S-Vx.y-z`` software version in concatenated 0x4AF bytes (8 characters), if present."""
    start = text.find(b"S-V")
    if start < 0 or len(text) < start + 8:
        return None
    return text[start : start + 8].decode("ascii", errors="replace")
