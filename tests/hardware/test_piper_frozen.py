"""The frozen-feedback check against an arm held still by contact: the simulated firmware's motor currents
under load, and the driver telling a stuck feed from a healthy arm pushing (simulated clock; the last test on
the physics twin)."""

from __future__ import annotations

import numpy as np
import pytest
from piper_can import codec
from piper_can.codec import MIT_MODE_POSITION_VELOCITY, MOTOR_ALL_JOINTS, CtrlMode, ModeControl, MotorEnable, MoveMode
from piper_can.driver import FROZEN_AFTER_S, FROZEN_MIN_MOVE_RAD
from piper_can.firmware import EmulatorConfig, PiperFirmware
from piper_rig import Rig, make_rig, stale_after
from piper_twin.demo import ScriptedDemo, Waypoint, plan
from piper_twin.plant import TwinPlant

POSE = (0.3, 0.8, -0.6, 0.2, 0.1, -0.2)
INTO = (0.8, 0.8, -0.6, 0.2, 0.1, -0.2)  # J1 0.5 rad on, past what the step limit lets one command ask
STEP_RAD = 0.2  # DriverConfig.max_step_rad's default
COMMAND_PERIOD_S = 0.01
FRAME_S = 0.005
FROZEN_MESSAGE = "keeps arriving with the same angles and motor currents"


def high_speed(frames: list[codec.Frame], joint: int) -> codec.HighSpeedInfo:
    (frame,) = [f for f in frames if f.arbitration_id == 0x250 + joint]
    info = codec.decode_feedback(frame.arbitration_id, frame.data)
    assert isinstance(info, codec.HighSpeedInfo)
    return info


def walk_to(rig: Rig, joints) -> None:
    for _ in range(200):
        rig.driver.command(joints)
        if all(abs(a - b) < 1e-3 for a, b in zip(rig.arm.joints_rad, joints, strict=True)):
            return
        rig.sleep(COMMAND_PERIOD_S)
    raise AssertionError(f"arm did not reach {joints}: {rig.arm.joints_rad}")


def test_a_blocked_joint_reports_the_current_it_pushes_with_and_its_sensor_noise():
    arm = PiperFirmware(EmulatorConfig())
    arm.handle(codec.encode(ModeControl(CtrlMode.CAN, MoveMode.J, 50, MIT_MODE_POSITION_VELOCITY)))
    arm.handle(codec.encode(MotorEnable(MOTOR_ALL_JOINTS, True)))
    arm.tick(0.05)
    arm.block_joint(1)
    for frame in codec.encode_joint_targets((0.3, 0.0, 0.0, 0.0, 0.0, 0.0)):
        arm.handle(frame)
    cycles = [arm.tick(FRAME_S) for _ in range(100)]  # 0.5 s; the setpoint reaches 0.3 rad at 1.5 rad/s in 0.2 s
    pushing = [high_speed(frames, 1) for frames in cycles[50:]]
    # Held at 0 while driven toward 0.3 rad: 0.2 A holding + 10 A/rad × 0.3 rad, ± the sensor's 1 mA.
    assert arm.joints_rad[0] == 0.0 and {i.position_rad for i in pushing} == {0.0}
    assert {i.speed_rad_s for i in pushing} == {0.0}
    assert all(abs(i.current_a - 3.2) <= 0.001 + 1e-9 for i in pushing)
    assert len({i.current_a for i in pushing}) > 1  # a live sensor: the frames do not repeat
    idle = [high_speed(frames, 2) for frames in cycles[50:]]
    assert all(abs(i.current_a - 0.2) <= 0.001 + 1e-9 for i in idle)  # not driven against anything
    arm.block_joint(1, blocked=False)
    for _ in range(100):
        arm.tick(FRAME_S)
    assert arm.joints_rad[0] == pytest.approx(0.3, abs=1e-5)  # 0x155 carries 0.001°
    assert abs(high_speed(arm.tick(FRAME_S), 1).current_a - 0.2) <= 0.001 + 1e-9  # released: holding again


def test_an_arm_held_by_contact_keeps_being_commanded_with_clamped_targets():
    with make_rig(EmulatorConfig()) as rig:
        walk_to(rig, POSE)
        rig.arm.block_joint(1)  # pressing on something: J1 cannot move on
        held = rig.arm.joints_rad[0]
        sent = []
        for _ in range(100):  # one second of commands into the block
            sent.append(rig.driver.command(INTO))
            rig.sleep(COMMAND_PERIOD_S)
        assert rig.arm.joints_rad[0] == held
        # Clamped as before: one step on from where J1 is, the other joints where they are.
        assert [s.joints_rad[0] for s in sent] == pytest.approx([POSE[0] + STEP_RAD] * len(sent), abs=1e-4)
        assert all(s.joints_rad[1:] == pytest.approx(POSE[1:], abs=1e-4) for s in sent)
        pushed = rig.driver.state().high_speed[0].value.current_a
        assert pushed == pytest.approx(0.2 + 10.0 * STEP_RAD, abs=0.002)  # the motor pushes against the block


def test_a_stuck_feed_with_motor_frames_still_trips_within_the_window():
    with make_rig(EmulatorConfig()) as rig:
        walk_to(rig, POSE)
        assert stale_after(rig, INTO, FROZEN_MESSAGE) <= FROZEN_AFTER_S + COMMAND_PERIOD_S + 1e-9


def test_a_feed_frozen_while_a_joint_pushes_still_trips():
    # Its currents show effort toward the target, so "a motor pushes" alone would take it for contact.
    with make_rig(EmulatorConfig()) as rig:
        walk_to(rig, POSE)
        rig.arm.block_joint(1)
        for _ in range(20):
            rig.driver.command(INTO)
            rig.sleep(COMMAND_PERIOD_S)
        assert rig.driver.state().high_speed[0].value.current_a > 2.0
        assert stale_after(rig, INTO, FROZEN_MESSAGE) <= FROZEN_AFTER_S + COMMAND_PERIOD_S + 1e-9


def press_through(scene, model, data, close_s):
    """The press demonstration's approach, then a grasp point 3 cm below its press: never reached, the arm
    keeps pushing the button against its base."""
    waypoints, yaw = plan(scene, model, data, close_s)
    return [waypoints[0], Waypoint(waypoints[1].position + [0.0, 0.0, -0.03], 0.0)], yaw


def test_the_twin_pressing_a_button_keeps_being_commanded():
    plant = TwinPlant("press_button", seed=0)
    demo = ScriptedDemo(plant.scene, plant.model, noise_m=0.0, planner=press_through)
    with make_rig(plant=plant, speed_percent=100) as rig:
        demo.start(plant.data, rig.arm.joints_rad, np.random.default_rng(0))
        start, held = rig.now(), []
        while rig.now() - start < 6.0:  # down by ~2.5 s, then pressing: the old check refused at ~4.7 s
            present = rig.driver.checked_state().joint_positions_rad
            joints, gripper = demo.step(1 / 30, present)
            sent = rig.driver.command(joints, gripper)
            if rig.now() - start > 4.0:
                held.append((present, np.abs(np.subtract(sent.joints_rad, present)).max()))
            rig.sleep(1 / 30)
        assert plant.scene.depth(plant.model, plant.data) >= plant.scene.press_depth_m
        poses = np.array([p for p, _ in held])
        assert np.ptp(poses, axis=0).max() < 1e-3  # held still by the button for the last 2 s
        assert min(gap for _, gap in held) >= FROZEN_MIN_MOVE_RAD  # while commanded on: the check judged it
