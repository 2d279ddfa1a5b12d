"""Cross-check with the vendor SDK (piper_sdk 0.6.2, test-only): it drives our emulated arm on one bus.

This keeps the emulator (and so the codec it shares with the driver) honest against an implementation
no one here wrote.
"""

from __future__ import annotations

import math
import statistics
import time

import can
import pytest
from piper_can.codec import JointCommand, JointConfig, decode_command, encode
from piper_can.emulator import PiperEmulator
from piper_rig import unique_virtual_channel, wait_until

piper_sdk = pytest.importorskip("piper_sdk")


@pytest.fixture
def sdk_and_arm():
    channel = unique_virtual_channel()  # unique: the SDK keeps one instance per channel name
    arm_bus = can.Bus(interface="virtual", channel=channel)
    monitor = can.Bus(interface="virtual", channel=channel)
    arm = PiperEmulator(arm_bus)
    arm.start()
    sdk = piper_sdk.C_PiperInterface_V2(channel, can_auto_init=False)
    sdk.CreateCanBus(channel, bustype="virtual", judge_flag=False)
    sdk.ConnectPort()
    yield sdk, arm, monitor
    sdk.DisconnectPort()
    arm.stop()
    arm_bus.shutdown()
    monitor.shutdown()


def test_vendor_sdk_reads_our_state_and_its_commands_move_the_arm(sdk_and_arm):
    sdk, arm, monitor = sdk_and_arm
    # The SDK's ConnectPort queries limits and firmware; it must understand our replies.
    assert wait_until(lambda: sdk.GetPiperFirmwareVersion() == "S-V1.8-2")
    limits = sdk.GetCurrentMotorAngleLimitMaxVel().current_motor_angle_limit_max_vel
    assert (limits.motor_num, limits.max_angle_limit, limits.min_angle_limit) == (6, 1200, -1200)
    assert wait_until(lambda: sdk.GetArmLowSpdInfoMsgs().motor_6.foc_status is not None)
    assert sdk.GetArmEnableStatus() == [False] * 6
    assert sdk.GetArmStatus().arm_status.ctrl_mode == 0

    # The vendor's enable loop converges on our enable state machine.
    deadline = time.monotonic() + 2.0
    while not sdk.EnablePiper():
        assert time.monotonic() < deadline, "EnablePiper never saw the enable bits"
        time.sleep(0.01)
    assert arm.firmware.enabled == (True,) * 6 and sdk.GetArmEnableStatus() == [True] * 6

    # Its commands move the emulated arm.
    sdk.MotionCtrl_2(0x01, 0x01, 100, 0x00)
    sdk.JointCtrl(10000, 20000, -30000, 0, 5000, -1000)
    sdk.GripperCtrl(50000, 1000, 0x01, 0)
    expected_rad = tuple(math.radians(d) for d in (10, 20, -30, 0, 5, -1))
    assert wait_until(lambda: arm.firmware.joints_rad == pytest.approx(expected_rad, abs=1e-6), timeout=3.0)
    assert wait_until(lambda: arm.firmware.gripper_m == pytest.approx(0.05, abs=1e-6), timeout=3.0)

    # It reads our joint angles, gripper, enable and status bits, in its own units.
    time.sleep(0.05)
    joints = sdk.GetArmJointMsgs().joint_state
    assert [joints.joint_1, joints.joint_2, joints.joint_3, joints.joint_4, joints.joint_5, joints.joint_6] == [
        10000,
        20000,
        -30000,
        0,
        5000,
        -1000,
    ]
    gripper = sdk.GetArmGripperMsgs().gripper_state
    assert (gripper.grippers_angle, gripper.grippers_effort) == (50000, 1000)
    assert gripper.foc_status.driver_enable_status and gripper.status_code == 0x40
    status = sdk.GetArmStatus().arm_status
    assert (status.ctrl_mode, status.arm_status, status.mode_feed, status.motion_status) == (1, 0, 1, 0)
    # The SDK counts frames between wake-ups of a thread it assumes wakes every 0.1 s; on a loaded machine one
    # late wake-up reads high (CI once read 310 Hz), so judge the median of seven of its windows. The emulator
    # thread shares this process (and its GIL) with the SDK's parser, so a loaded machine also lowers the rate
    # actually sent (135 Hz seen under three busy loops): compare with the joint frames sent meanwhile. The two
    # threads run late independently (the SDK read 200 Hz while 156 Hz were sent, hardware tests on two workers; in
    # the full suite on a Zen 3 VM 200 Hz while 104 Hz were sent: its thread woke every ~0.2 s and counted two
    # windows' frames as one), so only a reading far below what was sent is judged: what this catches is the SDK
    # counting only some of our frames (every other one: half).
    frames = list(iter(lambda: monitor.recv(timeout=0), None))
    rates, started = [], time.monotonic()
    for _ in range(7):
        rates.append(sdk.GetArmJointMsgs().Hz)
        time.sleep(0.11)
    window = list(iter(lambda: monitor.recv(timeout=0), None))
    sent_hz = sum(m.arbitration_id == 0x2A5 for m in window) / (time.monotonic() - started)
    assert sent_hz > 50 and statistics.median(rates) > 0.6 * sent_hz, (rates, sent_hz)

    # Our codec decodes the SDK's frames to the same angles.
    sent = [m for m in frames + window if m.arbitration_id == 0x155]
    assert decode_command(0x155, sent[-1].data) == JointCommand(1, (math.radians(10), math.radians(20)))

    # And it can switch our arm off.
    sdk.DisableArm(7)
    assert wait_until(lambda: arm.firmware.enabled == (False,) * 6)
    assert wait_until(lambda: sdk.GetArmEnableStatus() == [False] * 6)


def test_the_vendors_clear_error_frame_is_ours_and_clears_the_emulated_fault(sdk_and_arm):
    sdk, arm, monitor = sdk_and_arm
    with arm.locked() as firmware:
        firmware.inject_fault("collision", 2)
    sdk.JointConfig(7, 0, 0, 0x7FFF, 0xAE)
    assert wait_until(lambda: arm.firmware.arm_status == 0 and arm.firmware.ignored["invalid value"] == 0)
    time.sleep(0.05)
    frames = list(iter(lambda: monitor.recv(timeout=0), None))
    sent = [bytes(m.data) for m in frames if m.arbitration_id == 0x475]
    assert sent == [encode(JointConfig(7, clear_error=True)).data]
    assert any(m.arbitration_id == 0x476 and m.data[0] == 0x75 for m in frames)
