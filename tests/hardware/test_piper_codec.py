"""Codec: byte-exact against the example frames of the reference notes, and hypothesis round trips."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from piper_can import codec
from piper_can.codec import (
    ArmStatus,
    CodecError,
    EmergencyStop,
    EStopAction,
    FirmwareQuery,
    Frame,
    GripperCommand,
    GripperFeedback,
    HighSpeedInfo,
    JointCommand,
    JointFeedback,
    LimitQuery,
    LowSpeedInfo,
    MasterSlaveConfig,
    ModeControl,
    MotorEnable,
    MotorLimits,
    decode_command,
    decode_feedback,
    encode,
    encode_joint_targets,
)


def hexframe(frame: Frame) -> str:
    return f"{frame.arbitration_id:x}: {frame.data.hex(' ')}"


# ------------------------------------------------------------------ examples from piper-can.md
def test_joint_ctrl_example_is_byte_exact():
    # JointCtrl(10000, -20000, -30000, 0, 5000, -1000) in 0.001 degrees.
    targets = [math.radians(v / 1000) for v in (10000, -20000, -30000, 0, 5000, -1000)]
    assert [hexframe(f) for f in encode_joint_targets(targets)] == [
        "155: 00 00 27 10 ff ff b1 e0",
        "156: ff ff 8a d0 00 00 00 00",
        "157: 00 00 13 88 ff ff fc 18",
    ]


def test_gripper_ctrl_example_is_byte_exact():
    # GripperCtrl(50000, 1000, 1, 0): 50 mm opening, 1 N·m, enable.
    frame = encode(GripperCommand(opening_m=0.05, effort_nm=1.0, status_code=0x01))
    assert hexframe(frame) == "159: 00 00 c3 50 03 e8 01 00"


@pytest.mark.parametrize(
    ("message", "expected"),
    [
        (ModeControl(0x01, 0x01, 50, 0x00), "151: 01 01 32 00 00 00 00 00"),  # MotionCtrl_2(1,1,50,0)
        (ModeControl(0x01, 0x01, 100, 0xAD), "151: 01 01 64 ad 00 00 00 00"),  # high-follow
        (ModeControl(0x01, 0x04, 0, 0xAD), "151: 01 04 00 ad 00 00 00 00"),  # MIT
        (MasterSlaveConfig(0xFA), "470: fa 00 00 00 00 00 00 00"),  # MasterSlaveConfig(0xFA,0,0,0)
        (MotorEnable(7, True), "471: 07 02 00 00 00 00 00 00"),  # EnableArm()
        (MotorEnable(7, False), "471: 07 01 00 00 00 00 00 00"),  # DisableArm()
        (EmergencyStop(EStopAction.STOP), "150: 01 00 00 00 00 00 00 00"),
        (EmergencyStop(EStopAction.RESUME), "150: 02 00 00 00 00 00 00 00"),
        (FirmwareQuery(), "4af: 01 00 00 00 00 00 00 00"),
        (LimitQuery(3, 0x01), "472: 03 01 00 00 00 00 00 00"),
        (GripperCommand(0.0, 1.0, 0x03, set_zero=True), "159: 00 00 00 00 03 e8 03 ae"),
        (codec.JointConfig(7, clear_error=True), "475: 07 00 00 7f ff ae 00 00"),  # JointConfig(7,0,0,0x7FFF,0xAE)
        (codec.JointConfig(2, accel_valid=True, max_accel_raw=500), "475: 02 00 ae 01 f4 00 00 00"),
    ],
)
def test_command_examples_are_byte_exact(message, expected):
    assert hexframe(encode(message)) == expected
    assert decode_command(encode(message).arbitration_id, encode(message).data) == message


def test_arm_status_capture_decodes():
    # pyAgxArm's captured 0x2A1: CAN mode, normal, MOVE J.
    status = decode_feedback(0x2A1, bytes.fromhex("0100010000000000"))
    assert status == ArmStatus(ctrl_mode=1, arm_status=0, mode_feed=1)
    assert status.target_reached


def test_error_bits_name_the_joints():
    status = decode_feedback(0x2A1, bytes.fromhex("0104010001002401"))
    assert status.arm_status == codec.ArmStatusCode.TARGET_EXCEEDS_LIMIT
    assert not status.target_reached
    assert status.angle_limit_joints == (3, 6)  # 0x24 = bits 2 and 5
    assert status.comm_error_joints == (1,)


def test_low_speed_capture_decodes():
    # pyAgxArm's captured 0x261: 48.0 V, 25 °C driver, 25 °C motor, enabled.
    info = decode_feedback(0x261, bytes.fromhex("01e0001919400000"))
    assert info == LowSpeedInfo(
        joint=1, voltage_v=48.0, driver_temp_c=25, motor_temp_c=25, status=0x40, bus_current_a=0
    )
    assert info.enabled and info.faults == ()
    stalled = decode_feedback(0x266, bytes.fromhex("00f0001e1c900000"))
    assert stalled.joint == 6 and stalled.faults == ("collision protection triggered", "stall protection triggered")
    assert not stalled.enabled


def test_joint_and_gripper_feedback_decode():
    joints = decode_feedback(0x2A6, bytes.fromhex("ffff8ad000000000"))
    assert joints.first_joint == 3
    assert joints.positions_rad == pytest.approx((math.radians(-30), 0.0))
    gripper = decode_feedback(0x2A8, bytes.fromhex("0000c35003e8c000"))
    assert gripper.opening_m == pytest.approx(0.05) and gripper.effort_nm == pytest.approx(1.0)
    assert gripper.enabled and gripper.homed and gripper.faults == ()
    assert decode_feedback(0x2A8, bytes.fromhex("0000000000000400")).faults == ("over-current",)


def test_high_speed_and_limits_decode():
    info = decode_feedback(0x253, struct.pack(">hhi", -1500, 250, 1234))
    assert info == HighSpeedInfo(joint=3, speed_rad_s=-1.5, current_a=0.25, position_rad=1.234)
    limits = decode_feedback(0x473, bytes.fromhex("01057afa86012c00"))  # +140.2°, -140.2°, 300
    assert limits.motor == 1 and limits.max_speed_raw == 300
    assert limits.max_angle_rad == pytest.approx(math.radians(140.2))
    assert limits.min_angle_rad == pytest.approx(math.radians(-140.2))


def test_firmware_version_is_found_in_the_text():
    text = b"H-V1.2-1\x00S-V1.8-2\x00\x00"
    assert codec.parse_firmware_version(text) == "S-V1.8-2"
    assert codec.parse_firmware_version(b"no version here") is None


# ---------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_targets_are_refused(bad):
    with pytest.raises(CodecError, match="joint_2 target must be a finite number"):
        encode_joint_targets([0.0, bad, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(CodecError, match="finite"):
        encode(GripperCommand(bad, 1.0))


def test_out_of_range_values_are_refused():
    with pytest.raises(CodecError, match="out of range"):
        encode(JointCommand(1, (1e9, 0.0)))  # beyond int32 of 0.001°
    with pytest.raises(CodecError, match="speed_percent"):
        encode(ModeControl(1, 1, 101))
    with pytest.raises(CodecError, match="effort_nm"):
        encode(GripperCommand(0.01, 5.5))
    with pytest.raises(CodecError, match="first_joint"):
        encode(JointCommand(2, (0.0, 0.0)))
    with pytest.raises(CodecError, match="expected 8 data bytes"):
        decode_feedback(0x2A5, b"\x00" * 7)
    with pytest.raises(CodecError, match="enable flag"):
        decode_command(0x471, bytes.fromhex("0703000000000000"))


def test_unknown_ids_decode_to_none():
    assert decode_feedback(0x2B1, bytes(8)) is None
    assert decode_command(0x2A1, bytes(8)) is None


# ------------------------------------------------------------------------ round trips (hypothesis)
int32 = st.integers(-(2**31), 2**31 - 1)
int16 = st.integers(-(2**15), 2**15 - 1)
uint16 = st.integers(0, 2**16 - 1)
byte = st.integers(0, 255)


@settings(max_examples=300, deadline=None)
@given(frame_id=st.sampled_from([*codec.ID_JOINT_FEEDBACK, *codec.ID_JOINT_COMMAND]), a=int32, b=int32)
def test_joint_frames_round_trip_exactly(frame_id, a, b):
    data = struct.pack(">ii", a, b)
    decoder = decode_feedback if frame_id in codec.ID_JOINT_FEEDBACK else decode_command
    assert encode(decoder(frame_id, data)).data == data


@settings(max_examples=300, deadline=None)
@given(opening=int32, effort=int16, status=byte)
def test_gripper_feedback_round_trips_exactly(opening, effort, status):
    data = struct.pack(">ihBx", opening, effort, status)
    assert encode(decode_feedback(0x2A8, data)).data == data


@settings(max_examples=300, deadline=None)
@given(opening=int32, effort=st.integers(0, 5000), code=st.integers(0, 3), zero=st.booleans())
def test_gripper_command_round_trips_exactly(opening, effort, code, zero):
    data = struct.pack(">iHBB", opening, effort, code, 0xAE if zero else 0)
    assert encode(decode_command(0x159, data)).data == data


@settings(max_examples=300, deadline=None)
@given(joint=st.integers(1, 6), speed=int16, current=int16, position=int32)
def test_high_speed_round_trips_exactly(joint, speed, current, position):
    data = struct.pack(">hhi", speed, current, position)
    assert encode(decode_feedback(0x250 + joint, data)).data == data


@settings(max_examples=300, deadline=None)
@given(joint=st.integers(1, 6), volt=uint16, dtemp=int16, mtemp=st.integers(-128, 127), status=byte, bus=uint16)
def test_low_speed_round_trips_exactly(joint, volt, dtemp, mtemp, status, bus):
    data = struct.pack(">HhbBH", volt, dtemp, mtemp, status, bus)
    assert encode(decode_feedback(0x260 + joint, data)).data == data


@settings(max_examples=300, deadline=None)
@given(raw=st.lists(byte, min_size=8, max_size=8))
def test_status_round_trips_exactly(raw):
    assert encode(decode_feedback(0x2A1, bytes(raw))).data == bytes(raw)


@settings(max_examples=200, deadline=None)
@given(motor=st.integers(1, 6), hi=int16, lo=int16, speed=uint16)
def test_motor_limits_round_trip_exactly(motor, hi, lo, speed):
    data = struct.pack(">BhhHx", motor, hi, lo, speed)
    assert encode(decode_feedback(0x473, data)).data == data


@settings(max_examples=200, deadline=None)
@given(ctrl=byte, move=byte, speed=st.integers(0, 100), mit=byte, dwell=byte, install=byte)
def test_mode_control_round_trips_exactly(ctrl, move, speed, mit, dwell, install):
    message = ModeControl(ctrl, move, speed, mit, dwell, install)
    assert decode_command(0x151, encode(message).data) == message


angle = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(first=st.sampled_from([1, 3, 5]), a=angle, b=angle)
def test_si_values_survive_within_half_a_unit(first, a, b):
    half_millideg = math.radians(0.0005) * (1 + 1e-9)
    for message_type, decoder in ((JointCommand, decode_command), (JointFeedback, decode_feedback)):
        frame = encode(message_type(first, (a, b)))
        decoded = decoder(frame.arbitration_id, frame.data)
        assert decoded.first_joint == first
        assert abs(decoded.positions_rad[0] - a) <= half_millideg
        assert abs(decoded.positions_rad[1] - b) <= half_millideg


@settings(max_examples=300, deadline=None)
@given(opening=st.floats(-0.1, 0.2, allow_nan=False), effort=st.floats(0, 5, allow_nan=False))
def test_gripper_si_values_survive_within_half_a_unit(opening, effort):
    back = decode_command(0x159, encode(GripperCommand(opening, effort)).data)
    assert abs(back.opening_m - opening) <= 0.5e-6 + 1e-15
    assert abs(back.effort_nm - effort) <= 0.5e-3 + 1e-15
    fb = decode_feedback(0x2A8, encode(GripperFeedback(opening, effort, 0x40)).data)
    assert abs(fb.opening_m - opening) <= 0.5e-6 + 1e-15 and fb.enabled


def test_every_message_type_has_an_encoder_and_a_decoder():
    samples = [
        (MotorLimits(2, math.radians(150), math.radians(-150), 300), decode_feedback),
        (codec.MotorAccelLimit(4, 5.0), decode_feedback),
        (codec.FirmwareChunk(b"S-V1.8-2"), decode_feedback),
        (LowSpeedInfo(6, 24.0, 30, 28, 0x40, 0.0), decode_feedback),
        (codec.InstructionResponse(0x75, True), decode_feedback),
    ]
    for message, decoder in samples:
        frame = encode(message)
        assert len(frame.data) == 8
        assert decoder(frame.arbitration_id, frame.data) == message


def test_joint_config_flags_must_be_0xae_or_zero_and_versions_parse():
    with pytest.raises(CodecError, match="clear-error flag must be 0x00 or 0xAE"):
        decode_command(0x475, bytes([7, 0, 0, 0x7F, 0xFF, 0x01, 0, 0]))
    with pytest.raises(CodecError, match="joint must be 1..7"):
        encode(codec.JointConfig(0))
    assert codec.firmware_release("S-V1.8-5") == (1, 8, 5) and codec.firmware_release("S-V1.8-2") < (1, 8, 5)
    assert codec.firmware_release(None) is None and codec.firmware_release("H-V1.2-1") is None


def test_the_collision_and_joint_cap_frames_match_the_vendor_layout():
    # piper_sdk 0.6.2: ArmParamEnquiryAndConfig(0x02, 0, 0, 0, 0x03), CrashProtectionConfig(1..6),
    # MotorMaxSpdSet(motor, 0x7FFF, 0x7FFF, speed) byte layouts.
    assert encode(codec.ParamQuery(codec.PARAM_QUERY_COLLISION)).data == bytes([2, 0, 0, 0, 3, 0, 0, 0])
    assert encode(codec.CollisionProtectionConfig((1, 2, 3, 4, 5, 6))) == Frame(0x47A, bytes([1, 2, 3, 4, 5, 6, 0, 0]))
    assert encode(codec.MotorLimitsSet(3, max_speed_raw=60)) == Frame(0x474, bytes.fromhex("037fff7fff003c00"))
    samples = [
        (codec.MotorLimitsSet(2, math.radians(90.0), math.radians(-90.0), 150), decode_command),
        (codec.MotorLimitsSet(6), decode_command),
        (codec.ParamQuery(0x02), decode_command),
        (codec.CollisionProtectionConfig((0, 1, 2, 3, 4, 8)), decode_command),
        (codec.CollisionProtectionLevels((8, 7, 6, 5, 4, 0)), decode_feedback),
    ]
    for message, decoder in samples:
        frame = encode(message)
        assert decoder(frame.arbitration_id, frame.data) == message
    with pytest.raises(CodecError, match="0x47A: needs 6 levels 0..8"):
        encode(codec.CollisionProtectionConfig((9, 0, 0, 0, 0, 0)))
    with pytest.raises(CodecError, match="0x474: motor must be 1..6"):
        encode(codec.MotorLimitsSet(7))
