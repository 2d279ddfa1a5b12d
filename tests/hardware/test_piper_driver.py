"""The driver against the emulated arm on a real python-can virtual bus (emulator in real time)."""

from __future__ import annotations

import itertools
import math
import random
import threading
import time

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from piper_can import codec, recover_cli
from piper_can.driver import PiperDriver
from piper_can.errors import (
    ArmNotReadyError,
    CanBusError,
    EmergencyStopError,
    EnableTimeoutError,
    Fault,
    FeedbackStaleError,
    FirmwareFaultError,
    HighFollowError,
    PartialCommandError,
    PiperConnectionError,
)
from piper_can.firmware import EmulatorConfig
from piper_can.safety import SDK_SOFT_LIMITS, JointLimits
from piper_can.settings import DisconnectPolicy, DriverConfig
from piper_rig import make_rig, unique_virtual_channel

PERIOD = 0.005
POSE = (0.3, 0.8, -0.6, 0.2, 0.1, -0.2)


def walk_to(driver: PiperDriver, joints, gripper=None, timeout: float = 5.0) -> None:
    """Command repeatedly (the step limit caps each command) until the arm is there."""
    deadline = driver.clock.monotonic() + timeout
    while driver.clock.monotonic() < deadline:
        driver.command(joints, gripper)
        there = driver.state().joint_positions_rad
        if all(abs(a - b) < 1e-3 for a, b in zip(there, joints, strict=True)):
            return
        driver.link.sleep(0.01)
    raise AssertionError(f"arm did not reach {joints}: {driver.state().joint_positions_rad}")


def motion_frames(frames):
    return [m for m in frames if m.arbitration_id in (*codec.ID_JOINT_COMMAND, 0x159)]


# ---------------------------------------------------------------------------- connect / enable
def test_enable_handshake_converges_and_rates_are_measured(rig):
    assert rig.arm.enabled == (True,) * 6 and rig.arm.gripper_enabled
    assert rig.arm.ctrl_mode == codec.CtrlMode.CAN and rig.arm.speed_percent == 50
    enables = [m for m in rig.drain() if m.arbitration_id == 0x471]
    assert len(enables) >= 2 and all(bytes(m.data) == bytes.fromhex("0702000000000000") for m in enables)
    rig.sleep(1.2)
    state = rig.driver.state()
    assert state.rates_hz[0x2A1] == pytest.approx(200, rel=0.15)
    assert state.rates_hz[0x2A5] == pytest.approx(200, rel=0.15)
    assert state.rates_hz[0x261] == pytest.approx(40, rel=0.15)
    assert state.firmware_version == "S-V1.8-2"
    assert state.joints_enabled == (True,) * 6 and state.gripper_enabled


def test_enable_survives_latency_and_a_firmware_that_wants_two_requests():
    config = EmulatorConfig(enable_latency_s=0.05, double_enable_after_reset=True)
    with make_rig(config) as rig:
        assert rig.arm.enabled == (True,) * 6
        walk_to(rig.driver, POSE)


def test_enable_timeout_is_one_clear_error_after_capped_backoff():
    with make_rig(EmulatorConfig(enable_latency_s=60.0), enable=False, enable_timeout_s=0.6) as rig:
        rig.drain()
        start = rig.now()
        with pytest.raises(EnableTimeoutError) as err:
            rig.driver.enable()
        message = str(err.value)
        assert "\n" not in message
        assert "did not report enabled within 0.6 s" in message
        assert "joint_1, joint_2, joint_3, joint_4, joint_5, joint_6" in message  # gripper enables at once
        assert rig.now() - start == pytest.approx(0.6, abs=0.0025)  # the timeout, to one poll
        requests = [m.timestamp - start for m in rig.drain() if m.arbitration_id == 0x471]
        # Backed off, not hammered: 10, 20, 40, 80, 160 ms, then capped at 200 ms (to one 2 ms poll).
        assert np.diff(requests) == pytest.approx([0.01, 0.02, 0.04, 0.08, 0.16, 0.2], abs=0.0025)


def test_connect_without_an_arm_is_one_clear_error():
    driver = PiperDriver(DriverConfig(interface="virtual", channel=unique_virtual_channel(), connect_timeout_s=0.2))
    with pytest.raises(PiperConnectionError, match=r"no PiPER heard on virtual:piper-test-\w+ within 0.2 s"):
        driver.connect()
    assert not driver.is_connected


def test_unknown_interface_is_one_clear_error():
    with pytest.raises(PiperConnectionError, match="cannot open CAN bus nosuch:can0"):
        PiperDriver(DriverConfig(interface="nosuch", channel="can0")).connect()
    with pytest.raises(PiperConnectionError, match="no CAN channel given"):
        PiperDriver(DriverConfig(interface="virtual", channel="")).connect()


# ---------------------------------------------------------------------------------- watchdog
def test_default_watchdog_is_three_feedback_periods():
    assert DriverConfig().feedback_timeout_s == pytest.approx(3 * PERIOD)


def test_watchdog_stays_quiet_while_feedback_flows():
    # The 15 ms default, on simulated time: flowing feedback never trips it (clock or timestamp mix-ups
    # would), while an exact simulation leaves no room for a stalled thread to excuse a trip.
    with make_rig(EmulatorConfig(profile="light")) as rig:
        assert rig.driver.config.feedback_timeout_s == pytest.approx(3 * PERIOD)
        for _ in range(100):
            rig.driver.command(POSE, 0.02)
            rig.sleep(0.02)
        assert rig.driver.link.stale_error is None


@pytest.mark.parametrize(("fault", "stale"), [("drop one joint frame", "0x2A6"), ("bus silence", "0x2A5")])
def test_watchdog_fires_within_three_periods_and_stops_commanding(fault, stale):
    with make_rig(EmulatorConfig(profile="light")) as rig:
        rig.driver.command(POSE[:1] + (0.0,) * 5)
        if fault == "bus silence":
            rig.arm.silent = True
        else:
            rig.arm.drop_ids = {0x2A6}
        assert rig.until(lambda: rig.driver.link.stale_error is not None, timeout=1.0)
        watchdog = rig.driver.link.watchdog
        last_frame = min(watchdog.last_seen[i] for i, limit in watchdog.timeouts.items() if limit == 3 * PERIOD)
        latency = rig.driver.link.stale_at - last_frame
        # No frame for more than 3 periods trips it, at the first look after that (the rig looks every ms).
        assert 3 * PERIOD < latency <= 3 * PERIOD + 0.001 + 1e-9, f"watchdog latency {latency * 1e3:.3f} ms"
        assert f"stale feedback: no feedback frame {stale}" in str(rig.driver.link.stale_error)
        rig.drain()
        with pytest.raises(FeedbackStaleError):
            rig.driver.command(POSE, 0.02)
        with pytest.raises(FeedbackStaleError):
            rig.driver.checked_state()
        rig.sleep(0.05)
        assert motion_frames(rig.drain()) == []


def test_stale_feedback_is_caught_on_the_next_command_without_waiting():
    # A polled link judges at each look: a command 16 ms after the last frame is refused at once.
    with make_rig(EmulatorConfig(profile="light")) as rig:
        rig.arm.silent = True
        rig.clock.sleep(0.016)  # time passes; nobody looks at the bus meanwhile
        rig.drain()
        with pytest.raises(FeedbackStaleError, match="for 1[6-9] ms"):
            rig.driver.command(POSE)
        assert motion_frames(rig.drain()) == []


def test_a_reader_that_falls_behind_cannot_pass_old_positions_off_as_fresh():
    # On the wall clock, with the reader thread: a CPU-starved reader (1 ms per frame while ~3000
    # frames/s arrive) must trip the watchdog rather than serve old positions.
    with make_rig(real_time=True) as rig:
        handle = rig.driver.link._handle

        def slow_handle(msg):
            time.sleep(0.001)
            handle(msg)

        rig.driver.link._handle = slow_handle
        deadline = time.monotonic() + 3.0
        with pytest.raises(FeedbackStaleError, match="stale feedback"):
            while time.monotonic() < deadline:
                rig.driver.command(POSE, 0.02)
                time.sleep(0.01)


# ------------------------------------------------------------------------ clamps and commands
def test_step_limit_follows_lerobot_max_relative_target(rig):
    sent = rig.driver.command([2.0, 2.0, -2.0, 1.5, 1.0, 2.0], 0.07)
    assert sent.joints_rad == pytest.approx((0.2, 0.2, -0.2, 0.2, 0.2, 0.2))
    assert sent.gripper_m == pytest.approx(0.02)
    sent = rig.driver.command([0.05, 0.0, 0.0, 0.0, 0.0, -0.1], 0.0)
    assert sent.joints_rad == pytest.approx((0.05, 0.0, 0.0, 0.0, 0.0, -0.1))


def test_soft_limits_clamp_even_without_a_step_limit():
    with make_rig(max_step_rad=None, max_gripper_step_m=None) as rig:
        sent = rig.driver.command([9.0, -1.0, 1.0, -9.0, 9.0, -9.0], 0.5)
        lower, upper = zip(*SDK_SOFT_LIMITS.joints_rad, strict=True)
        assert sent.joints_rad == (upper[0], 0.0, 0.0, lower[3], upper[4], lower[5])
        assert sent.gripper_m == 0.07


def test_non_finite_targets_are_refused_before_the_bus(rig):
    rig.drain()
    with pytest.raises(ValueError, match="joint target 4 must be a finite number"):
        rig.driver.command([0.0, 0.1, -0.1, math.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="gripper target"):
        rig.driver.command([0.0] * 6, math.inf)
    with pytest.raises(ValueError, match="expected 6 joint targets"):
        rig.driver.command([0.0] * 5)
    rig.sleep(0.02)
    assert motion_frames(rig.drain()) == []


def test_frames_of_concurrent_commands_never_interleave(rig):
    rig.drain()

    def spam(pose):
        for _ in range(100):
            rig.driver.command(pose, 0.01)

    threads = [threading.Thread(target=spam, args=(p,)) for p in ((0.1,) + (0.0,) * 5, (0.0,) * 5 + (0.1,))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    rig.sleep(0.02)
    ids = [m.arbitration_id for m in rig.drain() if m.arbitration_id in (0x151, *codec.ID_JOINT_COMMAND, 0x159)]
    assert len(ids) == 200 * 4  # no 0x151 in a command: only enable() selects the mode
    assert all(ids[i : i + 4] == [0x155, 0x156, 0x157, 0x159] for i in range(0, len(ids), 4))


# ------------------------------------------------------------------------------ e-stop / resume
def test_estop_refuses_motion_and_resume_re_enables(rig):
    walk_to(rig.driver, POSE)
    rig.driver.emergency_stop()
    assert rig.until(lambda: rig.arm.estopped)
    with pytest.raises(EmergencyStopError, match="emergency stop engaged"):
        rig.driver.command(POSE)
    assert rig.until(lambda: rig.driver.state().status.value.arm_status == codec.ArmStatusCode.EMERGENCY_STOP)
    with pytest.raises(FirmwareFaultError, match="arm: emergency stop"):
        rig.driver.checked_state()
    rig.sleep(0.2)
    assert rig.arm.joints_rad[1] < POSE[1]  # damped, sinking slowly
    rig.driver.resume()
    assert rig.arm.enabled == (True,) * 6 and rig.arm.ctrl_mode == codec.CtrlMode.CAN
    assert not rig.driver.estopped and rig.driver.checked_state().faults() == ()
    walk_to(rig.driver, POSE)


# ------------------------------------------------------------------------- firmware faults
@pytest.mark.parametrize(
    ("inject", "part", "fault"),
    [
        (lambda e: e.inject_fault("collision", 3), "joint_3", "collision protection triggered"),
        (lambda e: e.inject_fault("comm_error", 2), "joint_2", "communication error"),
        (lambda e: e.inject_fault("stall", 6), "joint_6", "stall protection triggered"),
        (lambda e: e.inject_fault("over_current", 7), "gripper", "over-current"),
    ],
)
def test_firmware_error_bits_become_exceptions_naming_joint_and_fault(rig, inject, part, fault):
    with rig.emulator.locked() as arm:
        inject(arm)
    assert rig.until(lambda: rig.driver.state().faults() != (), timeout=1.0)
    rig.sleep(0.05)  # let every frame kind report it
    with pytest.raises(FirmwareFaultError) as err:
        rig.driver.checked_state()
    assert any(f.part == part and f.fault == fault for f in err.value.faults), err.value.faults
    assert f"{part}: {fault}" in str(err.value)
    rig.drain()
    with pytest.raises(FirmwareFaultError):
        rig.driver.command(POSE)
    assert motion_frames(rig.drain()) == []


# ---------------------------------------------------------------------------- disconnect policy
def test_disconnect_hold_keeps_the_arm_enabled_where_it_is(rig):
    walk_to(rig.driver, POSE)
    rig.driver.disconnect()
    rig.sleep(0.1)
    assert rig.arm.enabled == (True,) * 6
    assert rig.arm.joints_rad == pytest.approx(POSE, abs=1e-3)


def test_disconnect_rest_walks_home_then_disables():
    config = EmulatorConfig(disabled_behaviour="drop")
    with make_rig(config, disconnect_policy=DisconnectPolicy.REST, rest_speed_rad_s=2.0) as rig:
        walk_to(rig.driver, POSE, 0.03)
        rig.drain()
        rig.driver.disconnect()
        assert rig.arm.enabled == (False,) * 6 and not rig.arm.gripper_enabled
        assert rig.arm.joints_rad == pytest.approx((0.0,) * 6, abs=0.011)
        assert rig.arm.gripper_m == pytest.approx(0.0, abs=0.0021)
        sent = [codec.decode_command(0x155, m.data) for m in rig.drain() if m.arbitration_id == 0x155]
        steps = [abs(b.positions_rad[1] - a.positions_rad[1]) for a, b in zip(sent, sent[1:], strict=False)]
        assert len(sent) > 10 and max(steps) < 0.05  # walked in small steps, did not jump


def test_disconnect_rest_holds_when_the_pose_cannot_be_reached():
    with make_rig(disconnect_policy=DisconnectPolicy.REST, rest_timeout_s=0.3) as rig:
        walk_to(rig.driver, POSE)
        with rig.emulator.locked() as arm:
            arm.inject_fault("collision", 2)
        assert rig.until(lambda: rig.driver.state().faults() != ())
        rig.driver.disconnect()
        assert rig.arm.enabled == (True,) * 6  # not dropped
        assert not rig.driver.is_connected


# ------------------------------------------------------------------ never command a limp arm (issue 12.1)
def test_resume_waits_out_the_firmwares_delayed_motor_off(rig):
    walk_to(rig.driver, POSE)
    rig.driver.emergency_stop()
    assert rig.until(lambda: rig.arm.estopped)
    rig.drain()
    rig.driver.resume()
    resets = [m.timestamp for m in rig.drain() if m.arbitration_id == 0x150 and m.data[0] == 0x02]
    # The firmware switches the motors off 0.727 s after the reset: an arm "enabled" before that goes limp.
    rig.sleep(max(0.0, resets[0] + 0.85 - rig.now()))
    assert rig.arm.enabled == (True,) * 6 and rig.arm.gripper_enabled
    walk_to(rig.driver, POSE)


def test_a_command_is_refused_when_feedback_shows_a_disabled_motor(rig):
    rig.sleep(0.1)  # the handshake's last enable request (20 ms latency) has been applied
    with rig.emulator.locked() as arm:
        arm.set_enabled(3, False)  # a driver that cut out, no host frame involved
    assert rig.until(lambda: rig.driver.state().joints_enabled[2] is False)
    rig.drain()
    with pytest.raises(ArmNotReadyError, match=r"feedback shows joint_3 disabled \(limp\); command refused"):
        rig.driver.command(POSE)
    rig.sleep(0.02)
    assert motion_frames(rig.drain()) == []


@pytest.mark.parametrize(
    ("mode", "reported"),
    [(bytes([0x00, 0x01, 50, 0]), "control mode STANDBY and move mode J"), (bytes([0x01, 0x00, 50, 0]), "move mode P")],
)
@pytest.mark.parametrize("by", ["another host", "the arm"])
def test_a_command_is_refused_when_the_arm_left_the_mode_we_set(rig, mode, reported, by):
    if by == "another host":  # its 0x151 is seen on the bus: refused for that, whatever the status shows
        rig.monitor.send(can.Message(arbitration_id=0x151, data=mode.ljust(8, b"\0"), is_extended_id=False))
        reported = "another host .* changed the arm's mode"
    else:  # no frame to see (a teach button, a pendant): the status frame shows it
        with rig.emulator.locked() as arm:
            arm.ctrl_mode, arm.move_mode = codec.CtrlMode(mode[0]), mode[1]
    assert rig.until(lambda: codec_mode(rig.driver.state()) == (mode[0], mode[1]))
    rig.drain()
    with pytest.raises(ArmNotReadyError, match=reported):
        rig.driver.command(POSE)
    assert motion_frames(rig.drain()) == []
    rig.driver.enable()  # the remedy the message names
    rig.driver.command(POSE)


def codec_mode(state):
    return state.status.value.ctrl_mode, state.status.value.mode_feed


# ----------------------------------------------------------- no motion frame after an e-stop (issue 12.2)
@settings(max_examples=6, deadline=None)
@given(commanders=st.integers(2, 8), delay_s=st.floats(0.0, 0.02), seed=st.integers(0, 2**16))
def test_no_motion_frame_leaves_the_driver_after_an_emergency_stop(commanders, delay_s, seed):
    rng = random.Random(seed)
    with make_rig(profile_light()) as rig:
        rig.drain()
        stopped_at: list[float] = []
        late_successes: list[float] = []

        def command_forever() -> None:
            while not stopped_at or time.monotonic() < stopped_at[0] + 0.05:
                started = time.monotonic()
                try:
                    rig.driver.command([rng.uniform(-0.1, 0.1)] + [0.0] * 5, 0.01)
                except EmergencyStopError:
                    continue
                if stopped_at and started > stopped_at[0]:
                    late_successes.append(started)

        threads = [threading.Thread(target=command_forever) for _ in range(commanders)]
        for t in threads:
            t.start()
        rig.sleep(delay_s)
        rig.driver.emergency_stop()
        stopped_at.append(time.monotonic())
        for t in threads:
            t.join()
        rig.sleep(0.02)
        frames = rig.drain()
    ids = [m.arbitration_id for m in frames if m.arbitration_id in (0x150, 0x151, *codec.ID_JOINT_COMMAND, 0x159)]
    estop = [i for i, m in enumerate(frames) if m.arbitration_id == 0x150 and m.data[0] == 0x01]
    assert len(estop) == 1 and ids.count(0x150) == 1
    motion = (0x151, *codec.ID_JOINT_COMMAND, 0x159)
    after = [hex(m.arbitration_id) for m in frames[estop[0] :] if m.arbitration_id in motion]
    assert after == [], f"motion frames after the e-stop: {after}"
    assert late_successes == []  # no command that began after emergency_stop() returned reported success


def profile_light() -> EmulatorConfig:
    return EmulatorConfig(profile="light")


# ------------------------------------------------------------------ mode changes confirmed (issue 12.3)
def test_position_mode_after_high_follow_resets_old_firmware_first():
    # An arm left in high-follow by a hardware-linked leader (firmware S-V1.8-2 ignores 0x151 until a reset).
    with make_rig(EmulatorConfig(start_enabled=True)) as rig:
        assert rig.arm.mit_mode == 0x00 and rig.arm.speed_percent == 50  # position mode really taken
        assert any(m.arbitration_id == 0x150 and m.data[0] == 0x02 for m in rig.drain())
        assert rig.arm.enabled == (True,) * 6
        rig.sleep(0.1)
        walk_to(rig.driver, POSE)


def test_refusing_to_leave_high_follow_is_one_clear_error():
    with make_rig(EmulatorConfig(start_enabled=True), enable=False, high_follow_exit="refuse") as rig:
        with pytest.raises(HighFollowError, match=r"may still be in high-follow \(0xAD\), and firmware S-V1.8-2"):
            rig.driver.enable()
        assert rig.arm.mit_mode == 0xAD and not any(m.arbitration_id == 0x150 for m in rig.drain())


def test_new_firmware_leaves_high_follow_without_a_reset():
    with make_rig(EmulatorConfig(start_enabled=True, firmware_text="S-V1.8-5")) as rig:
        assert rig.arm.mit_mode == 0x00 and rig.arm.speed_percent == 50
        assert not any(m.arbitration_id == 0x150 for m in rig.drain())


def test_enable_refuses_when_feedback_does_not_confirm_the_mode():
    with make_rig(EmulatorConfig(start_enabled=True), enable=False) as rig:
        with rig.emulator.locked() as arm:
            arm.move_mode = codec.MoveMode.P  # and high-follow, which this firmware keeps until a reset
        rig.driver._may_be_high_follow = False  # pretend the driver could not know
        with pytest.raises(EnableTimeoutError, match="reports control mode CAN and move mode P, not CAN command mode"):
            rig.driver.enable()


# -------------------------------------------------------------------- recoverable faults (issue 12.4)
def test_an_arm_just_past_a_limit_cannot_be_enabled_and_the_error_says_why():
    # A real arm does not enable a joint past its limit (issue 34, item 6): the error names it and the remedy.
    past = EmulatorConfig(initial_pose_rad=(0.0, -0.02, 0.0, 0.0, 0.0, 0.0))
    with make_rig(past, enable=False, enable_timeout_s=0.3) as rig:
        assert rig.driver.state().faults() == (codec_fault("joint_2", "angle limit exceeded"),)
        rig.driver.checked_state()  # logged, not raised
        with pytest.raises(EnableTimeoutError) as err:
            rig.driver.enable()
        message = str(err.value)
        assert "still disabled: joint_2)" in message and "check the e-stop" not in message
        assert "does not enable a joint past its limit (joint_2 at -0.0200 rad, limits [0.0000, 3.1416])" in message
        assert "move that joint back inside its limits by hand" in message
        assert rig.arm.ignored["joint past its limit"] > 0


def test_a_joint_pushed_past_a_limit_while_enabled_is_brought_back_by_commands():
    with make_rig() as rig:
        with rig.emulator.locked() as arm:
            arm.set_position(2, -0.02)  # pushed by hand while enabled
        assert rig.until(lambda: rig.driver.state().faults() == (codec_fault("joint_2", "angle limit exceeded"),))
        rig.driver.checked_state()  # logged, not raised: commands are what bring it back
        sent = rig.driver.command(POSE)
        assert sent.joints_rad[1] == pytest.approx(-0.02 + 0.2, abs=1e-5)  # toward (and into) the limits
        walk_to(rig.driver, POSE)
        assert rig.driver.state().faults() == ()


def codec_fault(part: str, fault: str) -> Fault:
    return Fault(part, fault)


def test_clear_errors_brings_a_collided_arm_back_without_cutting_the_motors(rig, caplog):
    with rig.emulator.locked() as arm:
        arm.inject_fault("collision", 3)
    assert rig.until(lambda: rig.driver.state().faults() != ())
    with pytest.raises(FirmwareFaultError, match="arm: collision"):
        rig.driver.command(POSE)
    assert rig.driver.clear_errors() == ()
    assert "clearing error codes" in caplog.text and "error codes cleared" in caplog.text
    assert rig.arm.enabled == (True,) * 6
    walk_to(rig.driver, POSE)


@pytest.mark.parametrize("recovery", ["none", "reset"])
def test_enable_brings_an_arm_e_stopped_by_someone_else_back_only_when_asked(recovery):
    with make_rig(connect=False, recovery=recovery) as rig:
        rig.monitor.send(can.Message(arbitration_id=0x150, data=bytes([1]).ljust(8, b"\0"), is_extended_id=False))
        assert rig.until(lambda: rig.arm.estopped)
        rig.driver.connect()
        if recovery == "none":
            with pytest.raises(FirmwareFaultError, match="arm: emergency stop"):
                rig.driver.enable()
        else:
            rig.driver.enable()
            assert not rig.arm.estopped and rig.arm.enabled == (True,) * 6
            walk_to(rig.driver, POSE)


def test_a_reset_counts_once_the_feedback_shows_its_effect(rig):
    # Frames the firmware sends after our reset frame but before it acts on it are fresh and still show the
    # fault (a loaded real-time run: piper-recover --reset exited on a stall the reset had just cleared).
    # Here the firmware acts on 0x150 ten cycles (50 ms, two low-speed periods) after it arrives.
    held: list[can.Message] = []
    cycles = itertools.count()
    receive, advance = rig.emulator._receive, rig.emulator._advance

    def receive_late(msg: can.Message) -> None:
        if msg.arbitration_id == 0x150:
            held.append(msg)
        else:
            receive(msg)

    def advance_then_release(dt: float) -> None:
        advance(dt)
        if held and next(cycles) >= 10:
            receive(held.pop(0))

    rig.emulator._receive, rig.emulator._advance = receive_late, advance_then_release
    with rig.emulator.locked() as arm:
        arm.inject_fault("stall", 2)
    assert rig.until(lambda: rig.driver.state().faults() != ())
    rig.driver.recover("reset")
    assert rig.driver.checked_state().faults() == ()
    assert rig.arm.enabled == (True,) * 6
    walk_to(rig.driver, POSE)


def test_a_reset_that_leaves_a_fault_is_one_clear_error(rig):
    with rig.emulator.locked() as arm:
        arm.inject_fault("stall", 2)
    assert rig.until(lambda: rig.driver.state().faults() != ())
    rig.emulator._receive = lambda msg: None  # the firmware hears nothing: the reset changes nothing
    with pytest.raises(FirmwareFaultError, match=r"joint_2: stall protection triggered"):
        rig.driver.reset()


def test_a_reset_without_fresh_driver_feedback_is_one_clear_error(rig):
    rig.arm.drop_ids = set(range(0x261, 0x267))  # the driver-info frames stop
    with pytest.raises(EnableTimeoutError, match="sent no fresh status and driver-info feedback after a reset"):
        rig.driver.reset()


HEALTHY = "faults: none; mode CAN/J; enabled joints 1-6 + gripper: 1111111"


def test_piper_recover_cli_reports_and_resets(capsys):
    with make_rig(real_time=True) as rig:  # piper-recover runs its own driver on the wall clock
        with rig.emulator.locked() as arm:
            arm.inject_fault("comm_error", 4)
        assert rig.until(lambda: rig.driver.state().faults() != ())
        args = ["--interface=virtual", f"--channel={rig.channel}", "--feedback-timeout-s=0.1"]
        assert recover_cli.main(args) == 0
        assert "joint_4: communication error" in capsys.readouterr().out
        assert recover_cli.main([*args, "--clear-errors"]) == 0
        out = capsys.readouterr().out.splitlines()
        assert "joint_4: communication error" in out[0] and out[1].endswith(HEALTHY)
        with rig.emulator.locked() as arm:
            arm.inject_fault("stall", 2)
        assert recover_cli.main([*args, "--reset"]) == 0
        assert capsys.readouterr().out.splitlines()[1].endswith(HEALTHY)
        assert rig.arm.enabled == (True,) * 6


def test_piper_recover_cli_errors_are_one_line(capsys):
    assert recover_cli.main(["--interface=virtual", f"--channel={unique_virtual_channel()}"]) == 1
    assert capsys.readouterr().err.startswith("piper-recover: error: no PiPER heard on virtual:")


# -------------------------------------------------------------------------- firmware limits (issue 12.5)
def test_firmware_limits_narrow_the_soft_limits_and_a_mismatch_is_reported(caplog):
    tight = math.radians(57.3)  # the firmware stores 0.1°
    flash = JointLimits(((-tight, tight), *SDK_SOFT_LIMITS.joints_rad[1:]))
    with make_rig(EmulatorConfig(limits=flash, limit_policy="reject"), max_step_rad=None) as rig:
        assert rig.driver.limits.joints_rad[0] == (-tight, tight)
        assert rig.driver.limits.joints_rad[1:] == SDK_SOFT_LIMITS.joints_rad[1:]
        assert "joint_1 firmware limits [-1.0001, 1.0001] rad differ from the soft limits [-2.6180, 2.6180]" in (
            caplog.text
        )
        assert rig.driver.command([2.0, 0.1, 0.0, 0.0, 0.0, 0.0]).joints_rad[0] == tight
        assert rig.until(lambda: rig.arm.joints_rad[0] == pytest.approx(tight, abs=1e-5))
        assert rig.arm.ignored["out of range"] == 0  # the firmware never had to reject a target


def test_missing_firmware_limits_are_reported_and_the_soft_limits_kept(caplog):
    with make_rig(connect=False, connect_timeout_s=0.3) as rig:
        rig.arm.drop_ids = {0x473}
        rig.driver.connect()
        assert rig.driver.limits == SDK_SOFT_LIMITS
        assert "sent no firmware limits (0x473) for joint_1, joint_2" in caplog.text


# ---------------------------------------------------- watchdog re-arm, error frames, partial sends (issue 12.6)
def test_the_watchdog_rearms_only_after_fresh_feedback(rig):
    rig.arm.silent = True
    assert rig.until(lambda: rig.driver.link.stale_error is not None)
    with pytest.raises(FeedbackStaleError, match="cannot re-arm the watchdog .*: still no fresh 0x2A5, 0x2A6"):
        rig.driver.rearm_watchdog()
    with pytest.raises(FeedbackStaleError):
        rig.driver.command(POSE)
    rig.arm.silent = False
    assert rig.until(lambda: _rearmed(rig.driver))
    # Nothing is known of the gap (a power cycle into high-follow?): this firmware needs enable()'s exit first.
    with pytest.raises(ArmNotReadyError, match="may have been put in high-follow meanwhile"):
        rig.driver.command(POSE)
    rig.driver.enable()
    walk_to(rig.driver, POSE)


def _rearmed(driver: PiperDriver) -> bool:
    try:
        driver.rearm_watchdog()
    except FeedbackStaleError:
        return False
    return True


@pytest.mark.parametrize("frame_id", [0x2A1, 0x2A8, 0x263])
def test_status_gripper_and_driver_info_frames_are_watched_too(rig, frame_id):
    rig.arm.drop_ids = {frame_id}
    assert rig.until(lambda: rig.driver.link.stale_error is not None)
    assert f"no feedback frame 0x{frame_id:X}" in str(rig.driver.link.stale_error)
    with pytest.raises(FeedbackStaleError):
        rig.driver.command(POSE)


def test_bus_off_is_an_error_and_other_error_frames_are_counted(rig, caplog):
    lost_arbitration = can.Message(arbitration_id=0x002, is_error_frame=True, data=bytes(8))
    rig.monitor.send(lost_arbitration)
    assert rig.until(lambda: rig.driver.link.error_frames["lost arbitration"] == 1)
    rig.driver.command(POSE)  # a warning, not a stop
    assert "CAN error frame: lost arbitration" in caplog.text
    rig.monitor.send(can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8)))
    assert rig.until(lambda: rig.driver.link.bus_error is not None)
    rig.drain()
    with pytest.raises(CanBusError, match=f"CAN bus-off on virtual:{rig.channel}"):
        rig.driver.command(POSE)
    assert motion_frames(rig.drain()) == []
    rig.driver.rearm_watchdog()  # the controller restarted and feedback flows again
    rig.driver.enable()  # the gap may hide a power cycle into high-follow (see the watchdog re-arm test)
    rig.driver.command(POSE)


def test_a_command_that_fails_half_way_is_reported_as_such(rig):
    bus = rig.driver.link._bus
    real_send, sent = bus.send, []

    def flaky_send(msg, timeout=None):
        if len(sent) == 2:
            raise can.CanOperationError("Transmit buffer full")
        sent.append(msg.arbitration_id)
        real_send(msg, timeout)

    bus.send = flaky_send
    with pytest.raises(PartialCommandError) as err:
        rig.driver.command(POSE, 0.01)
    assert (err.value.sent, err.value.unsent) == ((0x155, 0x156), (0x157, 0x159))
    assert "command stopped after 2 of 4 frames (sent 0x155, 0x156; not sent 0x157, 0x159)" in str(err.value)


def test_a_mode_frame_lost_on_the_firmwares_side_is_resent_until_the_status_confirms_it():
    # The frame is on the bus (every listener saw it) but the firmware never acts on it.
    with make_rig(enable=False) as rig:
        rig.arm.lose_next[0x151] = 1
        rig.drain()
        rig.driver.enable()
        assert rig.arm.ignored["lost"] == 1 and rig.arm.ctrl_mode == codec.CtrlMode.CAN
        modes = [m.timestamp for m in rig.drain() if m.arbitration_id == 0x151]
        assert len(modes) == 2 and modes[1] - modes[0] == pytest.approx(0.05, abs=0.0025)


def test_a_lost_mode_frame_is_resent_until_the_status_confirms_it():
    # A loaded bus (or a full TX queue) can lose the one 0x151 of the enable handshake.
    with make_rig(enable=False) as rig:
        bus = rig.driver.link._bus
        real_send, lost = bus.send, []

        def lossy_send(msg, timeout=None):
            if msg.arbitration_id == 0x151 and not lost:
                lost.append(msg)  # dropped on the wire
                return
            real_send(msg, timeout)

        bus.send = lossy_send
        rig.driver.enable()
        assert lost and rig.arm.ctrl_mode == codec.CtrlMode.CAN
        modes = [m.timestamp for m in rig.drain() if m.arbitration_id == 0x151]
        assert len(modes) == 1 and modes[0] - lost[0].timestamp == pytest.approx(0.05, abs=0.0025)


def test_an_arm_at_rest_on_its_limits_that_does_not_enable_is_not_blamed_on_the_limits():
    # The rest pose sits exactly on J2's and J3's limits: a withheld enable there is the e-stop or the power.
    with make_rig(EmulatorConfig(enable_latency_s=60.0), enable=False, enable_timeout_s=0.3) as rig:
        with pytest.raises(EnableTimeoutError, match="check the e-stop button and the arm's power") as err:
            rig.driver.enable()
        assert "past its limit" not in str(err.value)
