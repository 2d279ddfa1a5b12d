"""The simulated firmware as a pure model: the test hands it frames and steps time exactly."""

from __future__ import annotations

import math
import time
from collections import Counter

import can
import pytest
from piper_can import codec
from piper_can.codec import (
    ArmStatusCode,
    EmergencyStop,
    EStopAction,
    FirmwareQuery,
    Frame,
    GripperCommand,
    LimitQuery,
    MasterSlaveConfig,
    ModeControl,
    MotorEnable,
    decode_feedback,
    encode,
    encode_joint_targets,
)
from piper_can.emulator import PiperEmulator
from piper_can.firmware import EmulatorConfig, PiperFirmware
from piper_rig import gc_paused, unique_virtual_channel

PERIOD = 0.005


class Host:
    """A host that hands frames to the firmware model and collects the frames it emits (no bus)."""

    def __init__(self, firmware: PiperFirmware):
        self.emulator = firmware
        self._out: list[Frame] = []

    def send(self, *messages) -> None:
        for m in messages:
            for f in m if isinstance(m, tuple) else (encode(m),):
                self._out += self.emulator.handle(f)

    def step(self, n: int = 1) -> list[Frame]:
        for _ in range(n):
            self._out += self.emulator.tick(PERIOD)
        out, self._out = self._out, []
        return out

    def latest(self, frame_id: int, n: int = 1):
        frames = [m for m in self.step(n) if m.arbitration_id == frame_id]
        return decode_feedback(frame_id, frames[-1].data) if frames else None

    def enable_can_mode(self, speed: int = 100, mit: int = 0) -> None:
        self.send(MotorEnable(7, True), ModeControl(1, 1, speed, mit), GripperCommand(0.0, 1.0, 1))
        self.step(10)


def make_host(config: EmulatorConfig | None = None) -> Host:
    return Host(PiperFirmware(config))


@pytest.fixture
def host() -> Host:
    return make_host()


def test_one_step_emits_one_cycle_and_the_rates_are_200_and_40_hz(host):
    counts = Counter(m.arbitration_id for m in host.step(200))  # one simulated second
    for frame_id in (0x2A1, *codec.ID_END_POSE, *codec.ID_JOINT_FEEDBACK, 0x2A8, *codec.ID_HIGH_SPEED):
        assert counts[frame_id] == 200, hex(frame_id)
    for frame_id in codec.ID_LOW_SPEED:
        assert counts[frame_id] == 40, hex(frame_id)
    assert sum(counts.values()) == 3040
    assert all(len(m.data) == 8 and m.arbitration_id <= 0x7FF for m in host.step(5))


def test_light_profile_keeps_joints_status_gripper_and_low_speed():
    host = make_host(EmulatorConfig(profile="light"))
    ids = {m.arbitration_id for m in host.step(5)}
    assert ids == {0x2A1, *codec.ID_JOINT_FEEDBACK, 0x2A8, *codec.ID_LOW_SPEED}


def test_initial_state_is_disabled_standby_and_motion_is_ignored(host):
    status = host.latest(0x2A1)
    assert (status.ctrl_mode, status.arm_status, status.mode_feed, status.motion_status) == (0, 0, 1, 0)
    assert not host.latest(0x261, 5).enabled
    assert not host.latest(0x2A8).enabled
    host.send(encode_joint_targets([0.3] * 6))  # before 0x151: wrong mode
    host.send(ModeControl(1, 1, 100))
    host.send(encode_joint_targets([0.3] * 6))  # before enabling: disabled
    host.step(20)
    assert host.emulator.joints_rad == (0.0,) * 6
    assert host.emulator.ignored["wrong mode"] == 3 and host.emulator.ignored["disabled"] == 3


def test_enable_shows_in_the_first_low_speed_frame_after_the_latency():
    host = make_host(EmulatorConfig(enable_latency_s=0.03))
    host.step(2)  # 0x26x went out at t = 5 ms; the next ones at 30, 55, 80 ms
    host.send(MotorEnable(0xFF, True))  # handled at t = 10 ms: enabled from 40 ms on
    seen = []
    for _ in range(20):
        for m in host.step():
            if m.arbitration_id == 0x263:
                seen.append((round(host.emulator.time_s, 3), decode_feedback(0x263, m.data).enabled))
    assert seen[:3] == [(0.03, False), (0.055, True), (0.08, True)]
    assert host.emulator.enabled == (True,) * 6
    host.send(MotorEnable(2, False))
    host.step(10)
    assert host.emulator.enabled == (True, False, True, True, True, True)


@pytest.mark.parametrize(("speed", "expected_s"), [(100, 1 / 3.0), (50, 2 / 3.0), (20, 1 / 0.6)])
def test_speed_percent_sets_convergence_time_and_the_reached_flag(host, speed, expected_s):
    host.enable_can_mode(speed)
    host.send(encode_joint_targets([1.0, 0.5, -0.5, 0.0, 0.0, 0.0]))
    cycles = 0
    while host.latest(0x2A1).motion_status == 1:
        cycles += 1
        assert cycles < 1000
    assert cycles * PERIOD == pytest.approx(expected_s, abs=2 * PERIOD)
    assert host.emulator.joints_rad[0] == pytest.approx(1.0, abs=1e-5)  # 0.001° quantisation
    joints = host.latest(0x2A5)
    assert joints.positions_rad == pytest.approx((1.0, 0.5), abs=1e-5)
    speed_info = [decode_feedback(0x251, m.data) for m in host.step() if m.arbitration_id == 0x251][0]
    assert speed_info.speed_rad_s == 0.0


def test_high_follow_tracks_fast_without_planning(host):
    host.enable_can_mode(speed=10, mit=0xAD)  # position mode at 10 % would need 0.67 s for 0.2 rad
    host.send(encode_joint_targets([0.2, 0.2, -0.2, 0.0, 0.0, 0.0]))
    host.step(40)
    assert host.emulator.joints_rad[0] == pytest.approx(0.2, abs=1e-3)


def test_out_of_range_targets_are_clamped_by_default(host):
    host.enable_can_mode()
    host.send(encode_joint_targets([3.0, -1.0, 1.0, 0.0, 0.0, 0.0]))
    host.step(300)
    assert host.emulator.joints_rad[:3] == pytest.approx((math.radians(150), 0.0, 0.0))
    assert host.latest(0x2A1).arm_status == 0


def test_reject_policy_keeps_the_pose_and_reports_status_4_until_a_valid_target():
    host = make_host(EmulatorConfig(limit_policy="reject"))
    host.enable_can_mode()
    host.send(encode_joint_targets([3.0, 0.1, -0.1, 0.0, 0.0, 0.0]))
    assert host.latest(0x2A1, 5).arm_status == ArmStatusCode.TARGET_EXCEEDS_LIMIT
    # pairs apply on their own: the rejected (J1, J2) pair keeps its pose, (J3, J4) moves
    assert host.emulator.joints_rad[:2] == (0.0, 0.0) and host.emulator.joints_rad[2] < 0
    assert host.emulator.ignored["out of range"] == 1
    host.send(encode_joint_targets([0.1, 0.1, -0.1, 0.0, 0.0, 0.0]))
    assert host.latest(0x2A1, 100).arm_status == ArmStatusCode.NORMAL
    assert host.emulator.joints_rad[0] == pytest.approx(0.1, abs=1e-5)


def test_a_joint_outside_its_limit_sets_its_error_bit(host):
    host.emulator.set_position(5, math.radians(80))
    assert host.latest(0x2A1).angle_limit_joints == (5,)


def test_a_joint_past_its_limit_is_not_enabled():
    host = make_host(EmulatorConfig(initial_pose_rad=(0.0, -0.01, 0.0, 0.0, 0.0, 0.0)))
    host.send(MotorEnable(7, True))
    host.step(10)
    assert host.emulator.enabled == (True, False, True, True, True, True)
    assert host.emulator.ignored["joint past its limit"] == 1
    host.emulator.set_position(2, 0.0)  # moved back inside by hand
    host.send(MotorEnable(7, True))
    host.step(10)
    assert host.emulator.enabled == (True,) * 6


def test_a_host_frame_can_be_lost_on_the_firmwares_side(host):
    host.emulator.lose_next[0x151] = 1
    host.send(ModeControl(1, 1, 50, 0))
    assert host.emulator.ctrl_mode == codec.CtrlMode.STANDBY and host.emulator.ignored["lost"] == 1
    assert [f.arbitration_id for f in host.emulator.frame_log if f.direction == "rx"] == [0x151]  # it was heard
    host.send(ModeControl(1, 1, 50, 0))
    assert host.emulator.ctrl_mode == codec.CtrlMode.CAN


def test_gripper_units_range_effort_and_zero(host):
    host.enable_can_mode()
    host.send(GripperCommand(0.05, 2.0, 0x01))
    fb = host.latest(0x2A8, 100)
    assert fb.opening_m == pytest.approx(0.05) and fb.effort_nm == pytest.approx(2.0) and fb.enabled
    host.send(GripperCommand(0.5, 1.0, 0x01))  # beyond the 70 mm stroke
    assert host.latest(0x2A8, 100).opening_m == pytest.approx(0.07)
    host.send(GripperCommand(0.07, 1.0, 0x01, set_zero=True))
    assert host.latest(0x2A8).opening_m == pytest.approx(0.0)
    host.send(GripperCommand(0.0, 1.0, 0x00))
    assert not host.latest(0x2A8).enabled


def test_strict_mode_rejects_excess_effort_and_counts_bad_frames():
    host = make_host(EmulatorConfig(strict=True))
    host.enable_can_mode()
    firmware = host.emulator
    firmware.handle(Frame(0x159, bytes.fromhex("0000c350157c0100")))
    firmware.handle(Frame(0x155, bytes(4)))
    firmware.handle(Frame(0x155, bytes(8)), extended_id=True)
    firmware.handle(Frame(0x3FF, bytes(8)))
    ignored = firmware.ignored
    assert ignored["out of range"] == 1 and ignored["wrong DLC or extended ID"] == 2 and ignored["unknown ID"] == 1


def test_estop_damps_and_reset_clears_the_status_at_once_but_cuts_the_motors_later(host):
    host.enable_can_mode()
    host.send(encode_joint_targets([0.0, 1.0, -1.0, 0.0, 0.0, 0.0]))
    host.step(200)
    host.send(EmergencyStop(EStopAction.STOP))
    assert host.latest(0x2A1).arm_status == ArmStatusCode.EMERGENCY_STOP
    host.send(encode_joint_targets([0.0, 1.5, -1.0, 0.0, 0.0, 0.0]))
    host.step(100)  # half a second: sinks slowly toward rest, ignores motion
    assert host.emulator.ignored["e-stop"] == 3
    assert 0.9 < host.emulator.joints_rad[1] < 1.0
    host.send(EmergencyStop(EStopAction.RESUME))
    status = host.latest(0x2A1)
    assert (status.arm_status, status.ctrl_mode) == (0, 0)  # within one cycle: e-stop gone, standby
    # ... but the motors stay on until 0.727 s after the reset (measured on a real arm), then drop.
    host.step(136)
    assert host.latest(0x262, 5).enabled  # 0.71 s after the reset
    assert host.emulator.enabled == (True,) * 6 and host.emulator.motor_off_pending
    host.step(4)  # 0.73 s
    assert host.emulator.enabled == (False,) * 6 and not host.emulator.gripper_enabled
    assert not host.latest(0x262, 5).enabled and not host.latest(0x2A8).enabled


def test_an_enable_sent_before_the_delayed_motor_off_is_lost():
    host = make_host(EmulatorConfig(reset_motor_off_delay_s=0.7))
    host.enable_can_mode()
    host.send(EmergencyStop(EStopAction.RESUME))
    host.step(4)
    host.send(MotorEnable(7, True), ModeControl(1, 1, 50))  # "re-enabled" 20 ms after the reset
    host.step(20)
    assert host.emulator.enabled == (True,) * 6 and host.emulator.ctrl_mode == 1  # looks fine ...
    host.step(120)
    assert host.emulator.enabled == (False,) * 6  # ... until the motors switch off: a limp arm
    host.send(encode_joint_targets([0.1] * 6))
    host.step()
    assert host.emulator.ignored["disabled"] == 3 and host.emulator.joints_rad == (0.0,) * 6
    host.send(MotorEnable(7, True))  # enabling after the motor-off holds
    host.step(100)
    assert host.emulator.enabled == (True,) * 6


def test_the_model_steps_time_exactly():
    firmware = PiperFirmware(EmulatorConfig(reset_motor_off_delay_s=0.0))
    for _ in range(7):
        firmware.tick(0.001)
    assert firmware.time_s == pytest.approx(0.007, abs=1e-12)
    firmware.handle(encode(MotorEnable(7, True)))
    assert firmware.tick(0.019) and firmware.enabled == (False,) * 6  # 20 ms latency not yet over
    firmware.tick(0.001)
    assert firmware.enabled == (True,) * 6
    firmware.handle(encode(EmergencyStop(EStopAction.RESUME)))  # no delay configured: off at once
    assert firmware.enabled == (False,) * 6
    with pytest.raises(ValueError, match="dt"):
        firmware.tick(-0.001)


def test_limit_and_firmware_queries_are_answered(host):
    host.send(*(LimitQuery(m, 1) for m in range(1, 7)), LimitQuery(2, 2), FirmwareQuery())
    replies = host.step()
    limits = [decode_feedback(0x473, m.data) for m in replies if m.arbitration_id == 0x473]
    assert [lim.motor for lim in limits] == [1, 2, 3, 4, 5, 6]
    assert limits[1].max_angle_rad == pytest.approx(math.pi) and limits[1].min_angle_rad == 0.0
    accel = [decode_feedback(0x47C, m.data) for m in replies if m.arbitration_id == 0x47C]
    assert accel == [codec.MotorAccelLimit(2, 5.0)]
    text = b"".join(m.data for m in replies if m.arbitration_id == 0x4AF)
    assert len(text) == 88 and codec.parse_firmware_version(text) == "S-V1.8-2"


def test_clear_error_0x475_clears_driver_bits_and_comm_errors_and_is_acknowledged(host):
    host.enable_can_mode()
    host.emulator.inject_fault("collision", 3)
    host.emulator.inject_fault("comm_error", 2)
    assert host.latest(0x2A1, 5).arm_status == ArmStatusCode.JOINT_COMM_ERROR
    replies = host.emulator.handle(encode(codec.JointConfig(3, clear_error=True)))
    assert [decode_feedback(f.arbitration_id, f.data) for f in replies] == [codec.InstructionResponse(0x75)]
    assert host.latest(0x263, 5).faults == () and host.latest(0x2A1).comm_error_joints == (2,)
    host.send(codec.JointConfig(7, clear_error=True))
    status = host.latest(0x2A1, 5)
    assert status.comm_error_mask == 0 and status.arm_status == ArmStatusCode.NORMAL
    assert host.emulator.enabled == (True,) * 6  # clearing errors does not touch the motors


def test_old_firmware_needs_a_reset_to_leave_high_follow():
    host = make_host(EmulatorConfig(firmware_text="S-V1.8-2"))
    host.enable_can_mode(mit=0xAD)
    host.send(ModeControl(1, 1, 50, 0x00))
    host.step()
    assert host.emulator.mit_mode == 0xAD and host.emulator.speed_percent == 100
    assert host.emulator.ignored["leaving high-follow without reset"] == 1
    host.send(EmergencyStop(EStopAction.RESUME), ModeControl(1, 1, 50, 0x00))
    host.step()
    assert host.emulator.mit_mode == 0x00 and host.emulator.speed_percent == 50


def test_firmware_from_s_v1_8_5_leaves_high_follow_without_reset():
    host = make_host(EmulatorConfig(firmware_text="S-V1.8-5"))
    host.enable_can_mode(mit=0xAD)
    host.send(ModeControl(1, 1, 50, 0x00))
    host.step()
    assert host.emulator.mit_mode == 0x00 and host.emulator.ignored["leaving high-follow without reset"] == 0


def test_an_arm_left_in_high_follow_by_a_linked_leader_ignores_position_mode():
    host = make_host(EmulatorConfig(start_enabled=True))
    assert host.emulator.mit_mode == 0xAD
    host.send(ModeControl(1, 1, 50, 0x00))
    host.step()
    assert host.emulator.mit_mode == 0xAD


def test_leader_role_ignores_commands_and_needs_a_power_cycle_to_leave(host):
    host.send(MasterSlaveConfig(0xFA))
    host.step()
    assert host.emulator.role == "leader"
    host.send(MotorEnable(7, True))
    host.send(MasterSlaveConfig(0xFC))
    host.step(10)
    assert host.emulator.role == "leader" and host.emulator.ignored["leader ignores commands"] == 1
    host.emulator.power_cycle()
    assert host.emulator.role == "follower"


def test_fault_injection_drop_freeze_silence_and_error_bits(host):
    host.enable_can_mode()
    host.emulator.drop_ids = {0x2A6}
    assert 0x2A6 not in {m.arbitration_id for m in host.step(5)}
    host.emulator.drop_ids = set()
    host.emulator.freeze_feedback()
    host.send(encode_joint_targets([0.5, 0.5, -0.5, 0.0, 0.0, 0.0]))
    assert host.latest(0x2A5, 50).positions_rad == (0.0, 0.0)  # frozen values...
    assert host.emulator.joints_rad[0] > 0.0  # ...while the arm moves
    host.emulator.freeze_feedback(False)
    host.emulator.silent = True
    assert host.step(10) == []
    host.emulator.silent = False
    host.emulator.inject_fault("collision", 3)
    host.emulator.inject_fault("comm_error", 2)
    host.emulator.inject_fault("over_current", 7)
    status = host.latest(0x2A1, 5)
    assert status.comm_error_joints == (2,) and status.arm_status == ArmStatusCode.JOINT_COMM_ERROR
    assert host.latest(0x263, 5).faults == ("collision protection triggered",)
    assert host.latest(0x2A8).faults == ("over-current",)
    host.send(EmergencyStop(EStopAction.RESUME))  # reset clears the errors
    assert host.latest(0x2A1).comm_error_mask == 0 and host.latest(0x263, 5).faults == ()


def test_two_arms_do_not_mix():
    left, right = make_host(), make_host()
    left.enable_can_mode()
    right.enable_can_mode()
    left.send(encode_joint_targets([0.2, 0.2, -0.2, 0.0, 0.0, 0.0]))
    left.step(100)
    right.step(100)
    assert left.emulator.joints_rad[0] == pytest.approx(0.2, abs=1e-5) and right.emulator.joints_rad[0] == 0.0


# ------------------------------------------------------------------------------- the bus runner
def test_leader_drives_a_follower_on_the_same_channel():
    channel = unique_virtual_channel()
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]
    follower = PiperEmulator(buses[0], EmulatorConfig(start_enabled=True))
    leader = PiperEmulator(buses[1], EmulatorConfig(role="leader"))
    leader.firmware.leader_pose = ((0.3, 0.5, -0.4, 0.1, 0.2, -0.3), 0.04)
    try:
        for _ in range(100):
            leader.step(PERIOD)
            follower.step(PERIOD)
        ids = {m.arbitration_id for m in iter(lambda: buses[2].recv(timeout=0), None)}
        assert {0x151, *codec.ID_JOINT_COMMAND, 0x159} <= ids and 0x2A5 in ids  # leader frames, follower feedback
        arm = follower.firmware
        assert arm.joints_rad == pytest.approx((0.3, 0.5, -0.4, 0.1, 0.2, -0.3), abs=1e-5)
        assert arm.gripper_m == pytest.approx(0.04) and arm.mit_mode == 0xAD
    finally:
        for b in buses:
            b.shutdown()


def test_real_time_mode_runs_at_the_scaled_rate_with_jitter():
    channel = unique_virtual_channel()
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(2)]
    emulator = PiperEmulator(buses[0], EmulatorConfig(rate_scale=2.0, jitter_s=0.001, profile="light"))
    try:
        emulator.start()
        time.sleep(0.5)
        with emulator.locked() as firmware:
            firmware.inject_fault("stall", 1)  # the model may be changed while the loop runs
        emulator.stop()
        frames = list(iter(lambda: buses[1].recv(timeout=0), None))
    finally:
        for b in buses:
            b.shutdown()
    status_frames = sum(m.arbitration_id == 0x2A1 for m in frames)
    # 400 Hz nominal for 0.5 s, each cycle up to 1 ms late (mean 0.5 ms): ~167 frames; a busy machine
    # only ever makes fewer.
    assert 100 < status_frames <= 200


def test_a_late_real_time_loop_still_handles_host_frames_at_once():
    """A busy machine makes every cycle run late; host frames must not wait until the loop catches up."""
    channel = unique_virtual_channel()
    arm_bus, host_bus = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    emulator = PiperEmulator(arm_bus)
    advance = emulator._advance

    def slow_advance(dt: float) -> None:  # each cycle takes 1.5 periods: the loop is always late
        time.sleep(1.5 * PERIOD)
        advance(dt)

    emulator._advance = slow_advance
    try:
        with gc_paused():  # a collection would stop the emulator's thread for up to a few hundred ms
            emulator.start()
            time.sleep(0.1)  # the loop is now late on every cycle
            latencies = []
            for _ in range(5):
                with emulator.locked() as firmware:
                    firmware.inject_fault("collision", 2)
                sent = time.monotonic()
                frame = encode(codec.JointConfig(7, clear_error=True))
                host_bus.send(can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False))
                while emulator.firmware.arm_status != ArmStatusCode.NORMAL and time.monotonic() - sent < 2.0:
                    time.sleep(0.001)
                latencies.append(time.monotonic() - sent)
                time.sleep(0.05)
    finally:
        emulator.stop()
        arm_bus.shutdown()
        host_bus.shutdown()
    # Handled within a cycle or two (~8 ms each; 0.25 s leaves room for a loaded machine's scheduling). The old
    # loop read frames only while its next cycle was still in the future, which a loop this slow never reaches
    # (every one waited the full 2 s).
    assert max(latencies) < 0.25, latencies


def test_a_real_time_loop_held_up_sends_the_cycles_it_owes():
    """Held up 30 ms in every 50 (a busy machine), the loop still sends one cycle per period on average, as a
    real arm fills the socket buffer of a host that stopped reading."""
    channel = unique_virtual_channel()
    arm_bus, host_bus = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    emulator = PiperEmulator(arm_bus, EmulatorConfig(profile="light"))
    try:
        with gc_paused():  # a collection would stop the emulator's thread for up to a few hundred ms
            emulator.start()
            time.sleep(0.05)
            while host_bus.recv(timeout=0) is not None:
                pass
            started = time.monotonic()
            for _ in range(20):
                with emulator.locked():
                    time.sleep(0.03)
                time.sleep(0.02)
            elapsed = time.monotonic() - started
            frames = list(iter(lambda: host_bus.recv(timeout=0), None))
    finally:
        emulator.stop()
        arm_bus.shutdown()
        host_bus.shutdown()
    cycles = sum(m.arbitration_id == 0x2A1 for m in frames)
    # 200 Hz over `elapsed` (≥ 1 s); a loop that skipped owed cycles sent 120 (measured with the resync at 0 s).
    assert cycles == pytest.approx(elapsed / PERIOD, rel=0.1)
