"""Issue 34: the driver under races and foreign frames, each interleaving forced by a gate, on simulated time.

Every test runs firmware, bus and driver in one thread on a ``SimulatedClock``; a gate (a wrapped driver
method, or a clock callback) makes "the other thread" act at exactly the moment the review found unsafe.
The passive monitor records every frame in the order it reached the bus. ``benchmarks/piper_races.py``
runs the same races with real threads on the wall clock.
"""

from __future__ import annotations

from dataclasses import replace

import can
import pytest
from piper_can import codec
from piper_can.driver import PiperDriver
from piper_can.errors import (
    ArmNotReadyError,
    CollisionProtectionOffError,
    EmergencyStopError,
    PiperConnectionError,
)
from piper_can.firmware import EmulatorConfig
from piper_rig import Rig, make_rig, stale_after

POSE = (0.3, 0.8, -0.6, 0.2, 0.1, -0.2)
NEXT = (0.35, 0.85, -0.65, 0.25, 0.15, -0.15)
MOTION_IDS = (0x151, *codec.ID_JOINT_COMMAND, 0x159)
MOTOR_OFF_S = 0.727  # the emulator's reset_motor_off_delay_s (measured on a real arm)


def walk_to(rig: Rig, joints, gripper=None) -> None:
    for _ in range(200):
        rig.driver.command(joints, gripper)
        if all(abs(a - b) < 1e-3 for a, b in zip(rig.arm.joints_rad, joints, strict=True)):
            return
        rig.sleep(0.01)
    raise AssertionError(f"arm did not reach {joints}: {rig.arm.joints_rad}")


def is_reset(m: can.Message) -> bool:
    return m.arbitration_id == 0x150 and m.data[0] == 0x02


def is_estop(m: can.Message) -> bool:
    return m.arbitration_id == 0x150 and m.data[0] == 0x01


def ids_after(frames: list[can.Message], first: int, wanted=MOTION_IDS) -> list[str]:
    return [hex(m.arbitration_id) for m in frames[first + 1 :] if m.arbitration_id in wanted]


def send_foreign(rig: Rig, frame_id: int, payload: bytes) -> None:
    """A frame from another host (or a plugged-in leader) on the same bus; the monitor records it too."""
    other = can.Bus(interface="virtual", channel=rig.channel, preserve_timestamps=True)
    rig.buses.append(other)
    data = payload.ljust(8, b"\0")
    other.send(can.Message(timestamp=rig.now(), arbitration_id=frame_id, data=data, is_extended_id=False))


# ------------------------------------------------------------------ 1. a command racing reset()
@pytest.mark.parametrize("gripper", [0.02, None], ids=["with-gripper", "joints-only"])
def test_a_command_racing_a_reset_sends_no_frame_after_the_reset(gripper):
    with make_rig(EmulatorConfig(profile="light")) as rig:
        driver = rig.driver
        walk_to(rig, POSE)
        send = driver.link.send
        raced: list[bool] = []

        def gate(*frames, guard=None):
            # Thread B's command has passed its readiness check; thread A's reset reaches the bus first.
            if frames[0].arbitration_id == 0x155 and not raced:
                raced.append(True)
                driver.reset()
            send(*frames, guard=guard)

        driver.link.send = gate
        rig.drain()
        with pytest.raises(ArmNotReadyError, match="the arm was reset"):
            driver.command(NEXT, gripper)
        driver.link.send = send
        rig.sleep(MOTOR_OFF_S + 0.1)
        frames = rig.drain()
        reset = [i for i, m in enumerate(frames) if is_reset(m)]
        assert raced and len(reset) == 1
        assert ids_after(frames, reset[0]) == []  # the latch under the send lock: nothing follows the reset
        assert rig.arm.ctrl_mode == codec.CtrlMode.STANDBY and rig.arm.targets_rad == pytest.approx(POSE, abs=1e-3)
        with pytest.raises(ArmNotReadyError, match="the arm was reset"):
            driver.command(NEXT)  # latched until an enable confirms
        driver.enable()
        walk_to(rig, NEXT)


# ------------------------------------------------------------------ 2. an e-stop during resume()
def test_an_estop_after_resume_began_aborts_it_before_the_reset_frame():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        driver = rig.driver
        walk_to(rig, POSE)
        driver.emergency_stop()
        assert rig.until(lambda: rig.arm.estopped)
        state = driver.link.state
        raced: list[bool] = []

        def gate():
            if not raced:  # the first look of resume(): another thread's e-stop lands now
                raced.append(True)
                driver.emergency_stop()
            return state()

        driver.link.state = gate
        rig.drain()
        with pytest.raises(EmergencyStopError, match="emergency stop requested during the reset"):
            driver.resume()
        driver.link.state = state
        rig.sleep(MOTOR_OFF_S + 0.1)
        frames = rig.drain()
        estop = [i for i, m in enumerate(frames) if is_estop(m)]
        assert raced and len(estop) == 1
        assert ids_after(frames, estop[0], (0x150, 0x471, *MOTION_IDS)) == []
        assert driver.estopped and rig.arm.estopped
        with pytest.raises(EmergencyStopError):
            driver.command(POSE)
        driver.resume()  # the e-stop's own remedy still works
        assert not driver.estopped and not rig.arm.estopped
        walk_to(rig, POSE)


def test_an_estop_during_resumes_motor_off_wait_wins():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        driver = rig.driver
        walk_to(rig, POSE)
        driver.emergency_stop()
        assert rig.until(lambda: rig.arm.estopped)
        raced: list[float] = []

        def gate() -> None:  # 0.3 s into the firmware's motor-off countdown, another thread e-stops
            if rig.arm.motor_off_pending and not raced and rig.arm.time_s >= reset_seen[0] + 0.3:
                raced.append(rig.now())
                driver.emergency_stop()

        reset_seen: list[float] = []
        handle = rig.arm.handle

        def handle_and_note(frame, extended_id=False):
            if frame.arbitration_id == 0x150 and frame.data[0] == 0x02:
                reset_seen.append(rig.arm.time_s)
            return handle(frame, extended_id)

        rig.arm.handle = handle_and_note
        rig.clock.every(0.001, gate)
        rig.drain()
        with pytest.raises(EmergencyStopError, match="emergency stop requested during the wait for a reset"):
            driver.resume()
        rig.sleep(MOTOR_OFF_S)
        frames = rig.drain()
        estop = [i for i, m in enumerate(frames) if is_estop(m)]
        assert raced and len(estop) == 1
        assert ids_after(frames, estop[0], (0x150, 0x471, *MOTION_IDS)) == []  # no 0x471, 0x159 or 0x151
        assert driver.estopped and rig.arm.estopped
        with pytest.raises(EmergencyStopError):
            driver.command(POSE)


def test_enable_is_refused_while_the_estop_is_engaged():
    with make_rig(EmulatorConfig(profile="light"), recovery="reset") as rig:
        rig.driver.emergency_stop()
        assert rig.until(lambda: rig.arm.estopped)
        rig.drain()
        with pytest.raises(EmergencyStopError, match="emergency stop engaged; call resume"):
            rig.driver.enable()  # with recovery=reset it would otherwise reset the e-stop away
        assert not any(is_reset(m) for m in rig.drain()) and rig.arm.estopped


# ------------------------------------------------------------------ 3. a reset the driver did not send
def test_enable_waits_out_a_reset_sent_by_another_host():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        send_foreign(rig, 0x150, bytes([0x02]))
        reset_at = rig.now()
        rig.sleep(0.05)
        with pytest.raises(ArmNotReadyError, match="another host reset the arm"):
            rig.driver.command(POSE)
        rig.driver.enable()
        assert rig.now() >= reset_at + MOTOR_OFF_S
        rig.sleep(max(0.0, reset_at + MOTOR_OFF_S + 0.1 - rig.now()))
        assert rig.arm.enabled == (True,) * 6 and rig.arm.gripper_enabled  # not limp after "success"
        walk_to(rig, NEXT)


def test_a_reset_seen_mid_stream_latches_motion():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        send = rig.driver.link.send
        foreign: list[bool] = []

        def gate(*frames, guard=None):  # the foreign reset arrives between our check and our frames
            if frames[0].arbitration_id == 0x155 and not foreign:
                foreign.append(True)
                send_foreign(rig, 0x150, bytes([0x02]))
                rig.driver.link.poll()
            send(*frames, guard=guard)

        rig.driver.link.send = gate
        rig.drain()
        with pytest.raises(ArmNotReadyError, match="another host reset the arm"):
            rig.driver.command(NEXT)
        frames = rig.drain()
        reset = [i for i, m in enumerate(frames) if is_reset(m)]
        assert len(reset) == 1 and ids_after(frames, reset[0]) == []


@pytest.mark.parametrize("gripper", [None, 0.02], ids=["joints-only", "with-gripper"])
def test_a_foreign_reset_our_reader_has_not_seen_is_not_undone_by_our_frames(gripper):
    # Another host's 0x150 02 reaches the bus after our command passed its readiness check and before its
    # frames, and our reader has not handled it yet: the frames reach a firmware in standby with its
    # motor-off pending. Joint frames are ignored there; a 0x151 in front of them would put the firmware
    # back into CAN command mode and the arm would move until the delayed motor-off.
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        send = rig.driver.link.send
        landed: list[bool] = []

        def gate(*frames, guard=None):
            if not landed:
                landed.append(True)
                send_foreign(rig, 0x150, bytes([0x02]))  # not polled: our reader has not seen it
            send(*frames, guard=guard)

        rig.driver.link.send = gate
        ignored = rig.arm.ignored["wrong mode"]
        rig.driver.command(NEXT, gripper)  # nothing has told the driver of the reset yet
        rig.driver.link.send = send
        rig.sleep(0.02)
        assert landed and rig.arm.motor_off_pending
        assert rig.arm.ctrl_mode == codec.CtrlMode.STANDBY  # not put back into CAN command mode
        assert rig.arm.targets_rad == pytest.approx(POSE, abs=1e-3)
        assert rig.arm.ignored["wrong mode"] - ignored == 3  # 0x155..0x157 reached it and were ignored
        if gripper is not None:  # the residual: the gripper takes targets in standby (the vendor's demo does)
            assert rig.arm.gripper_m > 0.0
        with pytest.raises(ArmNotReadyError, match="another host reset the arm"):
            rig.driver.command(NEXT)
        rig.sleep(MOTOR_OFF_S)
        assert rig.arm.enabled == (False,) * 6 and not rig.arm.gripper_enabled
        rig.driver.enable()
        walk_to(rig, NEXT)


def test_a_fresh_driver_waits_out_a_reset_it_did_not_see():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        rig.drain()
        rig.driver.reset()  # a previous process resets and exits at once
        rig.driver.close()
        reset_at = next(m.timestamp for m in rig.drain() if is_reset(m))
        rig.sleep(0.1 - (rig.now() - reset_at))
        fresh = PiperDriver(rig.driver.config, rig.clock)
        try:
            fresh.connect()
            fresh.enable()
            assert rig.now() >= reset_at + MOTOR_OFF_S
            rig.clock.sleep(max(0.0, reset_at + MOTOR_OFF_S + 0.1 - rig.now()))
            assert rig.arm.enabled == (True,) * 6 and rig.arm.gripper_enabled
            fresh.command(NEXT)
        finally:
            fresh.close()


# ------------------------------------------------------------------ 4. an ignored mode change
def max_speed_of_a_step(rig: Rig, target) -> float:
    """The fastest joint speed the firmware moved at while stepping to ``target``."""
    rig.driver.command(target)
    fastest, before = 0.0, rig.arm.joints_rad
    for _ in range(60):
        rig.clock.sleep(0.005)
        now = rig.arm.joints_rad
        fastest = max(fastest, *(abs(a - b) / 0.005 for a, b in zip(now, before, strict=True)))
        before = now
    return fastest


def test_a_leader_plugged_in_mid_session_is_not_commanded_through():
    # Firmware S-V1.8-2 keeps high-follow once a leader's 0x151 ... AD put it there: our position-mode 0x151
    # is ignored, so steps run at 3 rad/s instead of at most 50 % of it.
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        send_foreign(rig, 0x151, bytes([0x01, 0x01, 0x64, 0xAD]))
        rig.sleep(0.02)
        assert rig.arm.mit_mode == 0xAD
        with pytest.raises(ArmNotReadyError, match="put the arm in high-follow"):
            rig.driver.command(NEXT)
        rig.driver.enable()  # the exit: a reset on this firmware
        assert rig.arm.mit_mode == 0x00 and rig.arm.speed_percent == 50
        stepped = (POSE[0] + 0.2, *POSE[1:])
        walk_to(rig, POSE)
        assert max_speed_of_a_step(rig, stepped) <= 1.5 + 1e-6


@pytest.mark.parametrize(
    ("firmware", "mode"),
    [("S-V1.8-2", bytes([0x01, 0x01, 0x64, 0x00])), ("S-V1.8-5", bytes([0x01, 0x01, 0x64, 0xAD]))],
    ids=["position-at-100-percent", "high-follow-on-new-firmware"],
)
def test_another_hosts_mode_change_latches_motion_until_enable(firmware, mode):
    # Commands send no 0x151, so nothing puts our mode back after another host's: a faster speed, or
    # high-follow on firmware that would leave it on our 0x151, must not be commanded through.
    config = EmulatorConfig(profile="light", firmware_text=f"H-V1.2-1 {firmware} P-V1.0.0 PiPER emulator")
    with make_rig(config) as rig:
        walk_to(rig, POSE)
        send_foreign(rig, 0x151, mode)
        rig.sleep(0.02)
        assert (rig.arm.speed_percent, rig.arm.mit_mode) == (0x64, mode[3])
        rig.drain()
        with pytest.raises(ArmNotReadyError, match="changed the arm's mode"):
            rig.driver.command(NEXT)
        assert [m for m in rig.drain() if m.arbitration_id in MOTION_IDS] == []
        rig.driver.enable()  # selects (and confirms) ours again, without a reset on either firmware
        assert (rig.arm.speed_percent, rig.arm.mit_mode) == (50, 0x00)
        assert [m for m in rig.drain() if m.arbitration_id == 0x150] == []
        walk_to(rig, POSE)
        assert max_speed_of_a_step(rig, (POSE[0] + 0.2, *POSE[1:])) <= 1.5 + 1e-6


def test_a_power_cycle_into_high_follow_during_a_feedback_gap_is_exited():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        rig.arm.silent = True
        assert rig.until(lambda: rig.driver.link.stale_error is not None)
        with rig.emulator.locked() as arm:  # power-cycled and enabled in high-follow by a linked leader
            arm.config.start_enabled = True
            arm.power_cycle()
        rig.arm.silent = False
        rig.sleep(0.05)
        rig.driver.rearm_watchdog()
        with pytest.raises(ArmNotReadyError, match="high-follow"):
            rig.driver.command(POSE)
        rig.driver.enable()
        assert rig.arm.mit_mode == 0x00 and rig.arm.speed_percent == 50
        assert max_speed_of_a_step(rig, (0.2, 0.0, 0.0, 0.0, 0.0, 0.0)) <= 1.5 + 1e-6


# ------------------------------------------------------------------ 6. smaller ones
def test_a_late_frame_with_an_older_stamp_does_not_hide_a_disabled_joint():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        with rig.emulator.locked() as arm:
            arm.set_enabled(3, False)  # a driver that cut out
        assert rig.until(lambda: rig.driver.state().joints_enabled[2] is False)
        kept = rig.driver.state().low_speed[2].timestamp
        stale = codec.encode(codec.LowSpeedInfo(3, 24.0, 30, 28, 1 << codec.ENABLED_BIT, 0.3))
        other = can.Bus(interface="virtual", channel=rig.channel, preserve_timestamps=True)
        rig.buses.append(other)  # delivered late, stamped before the frame the driver keeps
        late = can.Message(
            timestamp=kept - 0.03, arbitration_id=stale.arbitration_id, data=stale.data, is_extended_id=False
        )
        other.send(late)
        rig.driver.link.poll()
        rig.drain()
        with pytest.raises(ArmNotReadyError, match="joint_3 disabled"):
            rig.driver.command(NEXT)
        assert [m for m in rig.drain() if m.arbitration_id in MOTION_IDS] == []


@pytest.mark.parametrize("refusals", [2, 1000])
def test_the_estop_frame_is_retried_when_the_bus_refuses_it(refusals):
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        bus = rig.driver.link._bus
        real_send, refused = bus.send, []

        def full_queue(msg, timeout=None):
            if msg.arbitration_id == 0x150 and len(refused) < refusals:
                refused.append(msg)
                raise can.CanOperationError("Transmit buffer full")
            real_send(msg, timeout)

        bus.send = full_queue
        rig.drain()
        if refusals > 100:  # refused for longer than the retry window: an error, and the latch holds
            with pytest.raises(PiperConnectionError, match="Transmit buffer full"):
                rig.driver.emergency_stop()
        else:
            rig.driver.emergency_stop()
            assert rig.until(lambda: rig.arm.estopped)
            assert [m.data[0] for m in rig.drain() if m.arbitration_id == 0x150] == [0x01]
        assert rig.driver.estopped
        with pytest.raises(EmergencyStopError):
            rig.driver.command(NEXT)


def test_disconnect_rest_is_not_fought_by_another_commanding_thread():
    with make_rig(EmulatorConfig(profile="light"), disconnect_policy="rest", rest_speed_rad_s=2.0) as rig:
        walk_to(rig, POSE)
        outcomes: list[str] = []

        def other_thread() -> None:  # still commanding POSE every 5 ms while the disconnect walks home
            if rig.driver.is_connected:  # time passes only inside disconnect() from here on
                try:
                    rig.driver.command(POSE)
                    outcomes.append("sent")
                except ArmNotReadyError:
                    outcomes.append("refused")

        rig.clock.every(0.005, other_thread)
        rig.drain()
        rig.driver.disconnect()
        walk = [codec.decode_command(0x155, m.data).positions_rad[0] for m in rig.drain() if m.arbitration_id == 0x155]
        assert outcomes and set(outcomes) == {"refused"}
        assert all(b <= a + 1e-9 for a, b in zip(walk, walk[1:], strict=False)), "targets alternated"
        assert rig.arm.enabled == (False,) * 6 and rig.arm.joints_rad == pytest.approx((0.0,) * 6, abs=0.011)


def test_feedback_that_flows_with_frozen_values_stops_commanding():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        assert stale_after(rig, NEXT, "keeps arriving with the same angles") <= 0.25 + 0.02
        assert rig.driver.link.stale_error is None  # the frame watchdog alone never saw it


def test_a_holding_arm_with_constant_feedback_is_not_called_frozen():
    with make_rig(EmulatorConfig(profile="light")) as rig:
        walk_to(rig, POSE)
        for _ in range(100):  # commanding where it already is, one second
            rig.driver.command(POSE)
            rig.sleep(0.01)


def test_our_own_frames_delivered_back_are_not_another_hosts(caplog):
    # udp_multicast (the emulator across processes) loops our own frames back to us: our reset and our
    # 0x151 must not pass for a foreign reset or a leader's mode change.
    with make_rig(EmulatorConfig(profile="light"), connect=False) as rig:
        options = {"preserve_timestamps": True, "receive_own_messages": True}
        echoing = PiperDriver(replace(rig.driver.config, bus_options=options), rig.clock)
        try:
            echoing.connect()
            echoing.enable()
            echoing.reset()
            echoing.enable()
            echoing.command(NEXT)
            state = echoing.state()  # nothing of ours was kept as another host's frame
            assert (state.foreign_estop, state.leader_mode, state.leader_gripper) == (None, None, None)
            assert "another host" not in caplog.text
            send_foreign(rig, 0x150, bytes([0x02]))  # a real foreign reset is still seen
            echoing.link.poll()
            with pytest.raises(ArmNotReadyError, match="another host reset the arm"):
                echoing.command(NEXT)
        finally:
            echoing.close()


# ------------------------------------------------------------------ 7. the firmware's own safety settings
def test_collision_protection_off_is_refused_or_warned_about_on_connect(caplog):
    off = EmulatorConfig(profile="light", collision_levels=(1, 0, 1, 1, 1, 1))
    with make_rig(off, connect=False, collision_off="refuse") as rig:
        rig.drain()
        with pytest.raises(CollisionProtectionOffError, match=r"collision protection OFF \(level 0\) on joint_2"):
            rig.driver.connect()
        queries = [m for m in rig.drain() if m.arbitration_id == 0x477]
        assert [bytes(m.data) for m in queries] == [bytes([0x02, 0, 0, 0, 0x03, 0, 0, 0])]  # piper_sdk's query
        assert not rig.driver.is_connected
    with make_rig(off) as rig:  # default: warn loudly, go on
        assert "collision protection OFF (level 0) on joint_2" in caplog.text
        walk_to(rig, POSE)
    caplog.clear()
    with make_rig(EmulatorConfig(profile="light")):
        assert "collision" not in caplog.text


def test_the_firmwares_joint_speed_and_acceleration_caps_are_settings():
    with make_rig(
        EmulatorConfig(profile="light"), speed_percent=100, max_joint_speed_rad_s=0.6, max_joint_accel_rad_s2=2.5
    ) as rig:
        assert rig.arm.joint_max_speed_rad_s == [0.6] * 6 and rig.arm.joint_max_accel_rad_s2 == [2.5] * 6
        assert all(limit.max_speed_raw == 60 for limit in rig.driver.state().motor_limits.values())
        walk_to(rig, POSE)
        assert max_speed_of_a_step(rig, (POSE[0] + 0.2, *POSE[1:])) <= 0.6 + 1e-6  # not 3 rad/s at 100 %
