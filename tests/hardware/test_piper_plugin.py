"""The LeRobot plugin in-process: registration, features, config checks, follower and leader modes."""

from __future__ import annotations

import ast
import json
import math
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import can
import lerobot_robot_piper
import numpy as np
import pytest
from lerobot.robots import make_robot_from_config
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators import make_teleoperator_from_config
from lerobot.teleoperators.config import TeleoperatorConfig
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError
from lerobot_robot_piper import PiperFollower, PiperFollowerConfig, PiperLeader, PiperLeaderConfig, record_cli
from lerobot_robot_piper.motion_metadata import MotionMode, read_motion_mode, write_motion_mode
from piper_can import codec
from piper_can.clock import SimulatedClock
from piper_can.emulator import PiperEmulator
from piper_can.errors import EnableTimeoutError, FeedbackStaleError, FirmwareFaultError, PiperConnectionError
from piper_can.firmware import EmulatorConfig
from piper_can.settings import DriverSettings
from piper_rig import unique_virtual_channel

KEYS = ["joint_1.pos", "joint_2.pos", "joint_3.pos", "joint_4.pos", "joint_5.pos", "joint_6.pos", "gripper.pos"]
LEADER_POSE = ((0.3, 0.5, -0.4, 0.1, 0.2, -0.3), 0.04)


class Arm:
    """An emulated PiPER on its own bus, stepped by the simulated clock every 5 ms."""

    def __init__(self, channel: str, clock: SimulatedClock, config: EmulatorConfig | None = None):
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.emulator = PiperEmulator(self.bus, config, clock)
        self.firmware = self.emulator.firmware
        clock.every(self.firmware.config.period_s, self.emulator.step)

    def close(self) -> None:
        self.bus.shutdown()


class Sim:
    """One simulated clock for the test's arms, robots and teleoperators (exact times, no threads)."""

    def __init__(self) -> None:
        self.clock = SimulatedClock()
        self.made: list[Arm] = []

    def __call__(self, channel: str, config: EmulatorConfig | None = None) -> Arm:
        self.made.append(Arm(channel, self.clock, config))
        return self.made[-1]

    def follower(self, config: PiperFollowerConfig) -> PiperFollower:
        return PiperFollower(config, self.clock)

    def leader(self, config: PiperLeaderConfig) -> PiperLeader:
        return PiperLeader(config, self.clock)

    def until(self, condition, timeout: float = 2.0) -> bool:
        """Let simulated time pass in 1 ms steps until ``condition()`` holds."""
        deadline = self.clock.time() + timeout
        while self.clock.time() < deadline:
            if condition():
                return True
            self.clock.sleep(0.001)
        return condition()


@pytest.fixture
def arms():
    sim = Sim()
    yield sim
    for arm in sim.made:
        arm.close()


def follower_config(channel: str, tmp_path, **kw) -> PiperFollowerConfig:
    return PiperFollowerConfig(interface="virtual", channel=channel, calibration_dir=tmp_path, **kw)


def leader_config(channel: str, tmp_path, **kw) -> PiperLeaderConfig:
    return PiperLeaderConfig(interface="virtual", channel=channel, calibration_dir=tmp_path, **kw)


def test_types_are_registered_and_lerobot_finds_the_classes(tmp_path):
    assert RobotConfig.get_choice_class("piper_follower") is PiperFollowerConfig
    assert TeleoperatorConfig.get_choice_class("piper_leader") is PiperLeaderConfig
    robot = make_robot_from_config(follower_config("x", tmp_path))
    teleop = make_teleoperator_from_config(PiperLeaderConfig(channel="y", calibration_dir=tmp_path))
    assert isinstance(robot, PiperFollower) and robot.name == "piper_follower"
    assert isinstance(teleop, PiperLeader) and teleop.name == "piper_leader"


def test_features_are_known_before_connecting(tmp_path):
    from lerobot.cameras.opencv import OpenCVCameraConfig

    cam = OpenCVCameraConfig(index_or_path=0, width=64, height=48, fps=30)
    robot = PiperFollower(follower_config("x", tmp_path, cameras={"cam_high": cam}))
    assert list(robot.action_features) == KEYS and all(v is float for v in robot.action_features.values())
    assert robot.observation_features == {**dict.fromkeys(KEYS, float), "cam_high": (48, 64, 3)}
    leader = PiperLeader(PiperLeaderConfig(channel="y", calibration_dir=tmp_path))
    assert leader.action_features == robot.action_features and leader.feedback_features == {}
    assert not robot.is_connected and robot.is_calibrated
    with pytest.raises(DeviceNotConnectedError):
        robot.get_observation()


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"motion_mode": "mit"}, "motion_mode"),
        ({"max_relative_target": {"joint_1.pos": 0.1}}, "max_relative_target"),
        ({"joint_limits": {"joint_1": (-1.0, 1.0)}}, "joint_limits"),
        ({"disconnect_policy": "drop"}, "drop"),
        ({"speed_percent": 150}, "speed_percent"),
        ({"gripper_max_relative_target": -0.01}, "max_gripper_step_m"),
        ({"max_relative_target": dict.fromkeys(KEYS, math.nan)}, "max_step_rad"),
        ({"max_relative_target": {**dict.fromkeys(KEYS, 0.1), "gripper.pos": -0.01}}, "max_gripper_step_m"),
        ({"rest_speed_rad_s": -0.5}, "rest_speed_rad_s"),
        ({"feedback_timeout_s": 1e9}, "feedback_timeout_s"),
        ({"rest_pose_rad": (0.0, -0.3, 0.0, 0.0, 0.0, 0.0)}, "rest_pose_rad joint_2"),
    ],
)
def test_bad_follower_settings_are_refused(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        follower_config("x", tmp_path, **kw)
    with pytest.raises(ValueError, match="source"):
        PiperLeaderConfig(source="both")


def test_follower_connects_observes_and_clamps_actions(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel)
    robot = arms.follower(follower_config(channel, tmp_path))
    robot.connect()
    try:
        with pytest.raises(DeviceAlreadyConnectedError):
            robot.connect()
        assert arm.firmware.enabled == (True,) * 6
        obs = robot.get_observation()
        assert list(obs) == KEYS and obs["joint_2.pos"] == 0.0
        far = dict(zip(KEYS, (2.0, 2.0, -2.0, 0.0, 0.0, 0.0, 0.07), strict=True))
        sent = robot.send_action(far)
        assert list(sent) == KEYS
        # 0.2 rad per joint, and the gripper's own 0.02 m (0.2 m would be no cap on a 0.07 m stroke)
        assert [sent[k] for k in KEYS] == pytest.approx([0.2, 0.2, -0.2, 0.0, 0.0, 0.0, 0.02])
        near = dict(zip(KEYS, (0.1, 0.1, -0.1, 0.0, 0.0, 0.0, 0.01), strict=True))
        assert robot.send_action(near) == pytest.approx(near)
        assert arms.until(lambda: arm.firmware.joints_rad[0] == pytest.approx(0.1, abs=1e-4))
        with pytest.raises(ValueError, match="missing gripper.pos"):
            robot.send_action({k: 0.0 for k in KEYS[:6]})
    finally:
        robot.disconnect()
    assert not robot.is_connected and arm.firmware.enabled == (True,) * 6  # "hold" by default


def test_per_key_max_relative_target(arms, tmp_path):
    channel = unique_virtual_channel()
    arms(channel)
    cap = dict(zip(KEYS, (0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.001), strict=True))
    robot = arms.follower(follower_config(channel, tmp_path, max_relative_target=cap))
    robot.connect()
    try:
        sent = robot.send_action(dict(zip(KEYS, (1.0, 1.0, -1.0, 1.0, 1.0, 1.0, 0.05), strict=True)))
        assert [sent[k] for k in KEYS] == pytest.approx([0.01, 0.02, -0.03, 0.04, 0.05, 0.06, 0.001])
    finally:
        robot.disconnect()


@pytest.mark.parametrize("bad", ["0.1", True, np.bool_(True), None, b"1"])
def test_an_action_value_that_is_not_a_real_number_is_refused(arms, tmp_path, bad):
    channel = unique_virtual_channel()
    arm = arms(channel)
    robot = arms.follower(follower_config(channel, tmp_path))
    robot.connect()
    try:
        targets = dict.fromkeys(KEYS, 0.0)
        with pytest.raises(ValueError, match="joint_2.pos must be a real number"):
            robot.send_action({**targets, "joint_2.pos": bad})
        assert arm.firmware.targets_rad == (0.0,) * 6
        sent = robot.send_action({**targets, "joint_1.pos": np.float32(0.05), "gripper.pos": np.float64(0.01)})
        assert sent["joint_1.pos"] == pytest.approx(0.05) and sent["gripper.pos"] == pytest.approx(0.01)
    finally:
        robot.disconnect()


def test_the_gripper_has_its_own_default_step_cap(tmp_path):
    # The joints' 0.2 (rad) as metres would be no cap on a 0.07 m stroke.
    driver = follower_config("x", tmp_path).driver_config()
    assert driver.max_step_rad == 0.2 and driver.max_gripper_step_m == 0.02
    tuned = follower_config("x", tmp_path, max_relative_target=0.1, gripper_max_relative_target=0.01).driver_config()
    assert tuned.max_step_rad == 0.1 and tuned.max_gripper_step_m == 0.01


def test_leader_on_its_own_channel_reads_the_leader_frames(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel, EmulatorConfig(role="leader"))
    arm.firmware.leader_pose = LEADER_POSE
    leader = arms.leader(leader_config(channel, tmp_path))
    leader.connect()
    try:
        action = leader.get_action()
        expected = [*LEADER_POSE[0], LEADER_POSE[1]]
        assert list(action) == KEYS and [action[k] for k in KEYS] == pytest.approx(expected, abs=1e-5)
        arm.firmware.silent = True  # unplugged
        assert arms.until(lambda: leader.link.stale_error is not None, timeout=1.0)
        with pytest.raises(FeedbackStaleError, match="no leader frame 0x15"):
            leader.get_action()
    finally:
        leader.disconnect()


@pytest.mark.parametrize(("source", "gripper_id"), [("control", 0x159), ("feedback", 0x2A8)])
def test_a_leader_whose_gripper_frame_stops_is_stale(arms, tmp_path, source, gripper_id):
    channel = unique_virtual_channel()
    arm = arms(channel, EmulatorConfig(role="leader") if source == "control" else None)
    leader = arms.leader(leader_config(channel, tmp_path, source=source))
    leader.connect()
    try:
        leader.get_action()
        arm.firmware.drop_ids = {gripper_id}  # the joints keep coming
        assert arms.until(lambda: leader.link.stale_error is not None, timeout=1.0)
        with pytest.raises(FeedbackStaleError, match=f"0x{gripper_id:X}"):
            leader.get_action()
    finally:
        leader.disconnect()


def test_leader_moved_by_hand_is_read_from_its_feedback(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel)  # an ordinary arm, disabled: it can be moved by hand
    leader = arms.leader(leader_config(channel, tmp_path, source="feedback"))
    leader.connect()
    try:
        with arm.emulator.locked() as firmware:
            firmware.set_position(1, 0.5)
        assert arms.until(lambda: leader.get_action()["joint_1.pos"] == pytest.approx(0.5, abs=1e-5))
    finally:
        leader.disconnect()


def test_hardware_linked_leader_drives_the_follower_and_the_pc_only_listens(arms, tmp_path):
    channel = unique_virtual_channel()
    follower_arm = arms(channel, EmulatorConfig(start_enabled=True))
    leader_arm = arms(channel, EmulatorConfig(role="leader"))
    leader_arm.firmware.leader_pose = LEADER_POSE
    monitor = can.Bus(interface="virtual", channel=channel)
    robot = arms.follower(follower_config(channel, tmp_path, hardware_linked_leader=True))
    teleop = arms.leader(leader_config(channel, tmp_path))
    try:
        teleop.connect()
        robot.connect()
        expected = pytest.approx([*LEADER_POSE[0], LEADER_POSE[1]], abs=1e-4)
        deadline = arms.clock.time() + 3.0
        while [robot.get_observation()[k] for k in KEYS] != expected:
            assert arms.clock.time() < deadline, robot.get_observation()
            action = teleop.get_action()
            assert robot.send_action(action) == action
            robot.send_action(dict.fromkeys(KEYS, 0.01))  # would be visible on the bus if it were sent
            arms.clock.sleep(0.01)
    finally:
        robot.disconnect()
        teleop.disconnect()
    frames = list(iter(lambda: monitor.recv(timeout=0), None))
    monitor.shutdown()
    host_ids = {m.arbitration_id for m in frames} & {0x150, 0x470, 0x471, 0x472, 0x4AF}
    assert host_ids == set()  # no enable, e-stop, role or query frame from the PC
    targets = [codec.decode_command(0x155, m.data).positions_rad for m in frames if m.arbitration_id == 0x155]
    assert targets and all(t == pytest.approx(LEADER_POSE[0][:2], abs=1e-5) for t in targets)
    assert follower_arm.firmware.joints_rad == pytest.approx(LEADER_POSE[0], abs=1e-4)


def test_connect_failure_releases_the_bus(tmp_path):
    robot = PiperFollower(follower_config(unique_virtual_channel(), tmp_path, connect_timeout_s=0.2))
    with pytest.raises(PiperConnectionError, match="no PiPER heard"):
        robot.connect()
    assert not robot.is_connected
    robot.disconnect()  # harmless when not connected


def test_importing_the_plugin_leaves_the_process_alone():
    check = "import sys; hook = sys.excepthook; import lerobot_robot_piper; print(sys.excepthook is hook)"
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "True"


def test_follower_config_inherits_every_driver_setting_with_its_default(tmp_path):
    config = PiperFollowerConfig(calibration_dir=tmp_path)
    recorded = {"motion_mode", "speed_percent"}  # None: as recorded, else position at 50 %
    for f in fields(DriverSettings):
        if f.name not in recorded:
            assert getattr(config, f.name) == getattr(DriverSettings(), f.name), f.name
    assert (config.motion_mode, config.speed_percent) == (None, None)
    driver = config.driver_config()
    assert (driver.motion_mode, driver.speed_percent) == (DriverSettings.motion_mode, DriverSettings.speed_percent)
    tuned = follower_config("x", tmp_path, recovery="reset", reset_settle_s=1.5, motion_mode="high_follow")
    driver = tuned.driver_config()
    assert (driver.recovery, driver.reset_settle_s, driver.high_follow) == ("reset", 1.5, True)
    with pytest.raises(ValueError, match="recovery must be one of"):
        follower_config("x", tmp_path, recovery="pray")


def test_no_assert_statements_in_the_hardware_packages():
    root = Path(lerobot_robot_piper.__file__).parents[1]
    found = [
        f"{path.relative_to(root)}:{node.lineno}"
        for path in sorted(root.glob("*/*.py"))
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Assert)
    ]
    assert found == []


def test_radians_are_the_unit(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel, EmulatorConfig(initial_pose_rad=(math.radians(30), 0.5, -0.5, 0.0, 0.0, 0.0)))
    robot = arms.follower(follower_config(channel, tmp_path))
    robot.connect()
    try:
        assert robot.get_observation()["joint_1.pos"] == pytest.approx(math.radians(30), abs=1e-5)
        assert arm.firmware.enabled == (True,) * 6
    finally:
        robot.disconnect()


class StubCamera:
    """Stands in for an OpenCV camera (none on the test machine): same calls, a fixed frame."""

    def __init__(self, height: int, width: int):
        self.frame = np.full((height, width, 3), 7, dtype=np.uint8)
        self.is_connected = False

    def connect(self) -> None:
        self.is_connected = True

    def read_latest(self, max_age_ms: int = 500):
        return self.frame

    def disconnect(self) -> None:
        self.is_connected = False


def test_camera_frames_join_the_observation(arms, tmp_path):
    from lerobot.cameras.opencv import OpenCVCameraConfig

    channel = unique_virtual_channel()
    arms(channel)
    cam = OpenCVCameraConfig(index_or_path=0, width=64, height=48, fps=30)
    robot = arms.follower(follower_config(channel, tmp_path, cameras={"cam_high": cam}))
    robot.cameras["cam_high"] = stub = StubCamera(48, 64)
    robot.connect()
    try:
        obs = robot.get_observation()
        assert obs["cam_high"] is stub.frame and obs["cam_high"].shape == robot.observation_features["cam_high"]
        assert list(obs) == [*KEYS, "cam_high"]
    finally:
        robot.disconnect()
    assert not stub.is_connected


def test_follower_refuses_an_arm_just_past_a_limit_until_it_is_moved_back(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel, EmulatorConfig(initial_pose_rad=(0.0, -0.02, 0.0, 0.0, 0.0, 0.0)))
    robot = arms.follower(follower_config(channel, tmp_path, enable_timeout_s=0.3))
    # J2 at -0.02 rad (limit 0): the firmware does not enable it, and the error says what to do.
    with pytest.raises(EnableTimeoutError, match="joint_2 at -0.0200 rad.*move that joint back inside"):
        robot.connect()
    assert not robot.is_connected
    with arm.emulator.locked() as firmware:
        firmware.set_position(2, 0.01)  # moved back by hand, motors off
    robot.connect()
    try:
        with arm.emulator.locked() as firmware:
            firmware.set_position(2, -0.02)  # pushed past it again while enabled: commands bring it back
        assert arms.until(lambda: robot.get_observation()["joint_2.pos"] == pytest.approx(-0.02, abs=1e-5))
        action = dict(zip(KEYS, (0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0), strict=True))
        assert arms.until(lambda: robot.send_action(action) and arm.firmware.joints_rad[1] > 0.05)
        assert robot.driver.state().faults() == ()
    finally:
        robot.disconnect()


def test_follower_recovery_setting_brings_an_e_stopped_arm_back_on_connect(arms, tmp_path):
    channel = unique_virtual_channel()
    arm = arms(channel)
    with arm.emulator.locked() as firmware:
        firmware.handle(codec.encode(codec.EmergencyStop(codec.EStopAction.STOP)))
    with pytest.raises(FirmwareFaultError, match="arm: emergency stop"):
        arms.follower(follower_config(channel, tmp_path)).connect()
    robot = arms.follower(follower_config(channel, tmp_path, recovery="reset"))
    robot.connect()
    try:
        assert not arm.firmware.estopped and arm.firmware.enabled == (True,) * 6
    finally:
        robot.disconnect()


def test_velocity_and_torque_observations_are_optional(arms, tmp_path):
    assert "joint_1.vel" not in arms.follower(follower_config("x", tmp_path)).observation_features
    channel = unique_virtual_channel()
    arm = arms(channel)
    robot = arms.follower(follower_config(channel, tmp_path, use_velocity_and_torque=True))
    extra = [f"joint_{j}.{kind}" for kind in ("vel", "torque") for j in range(1, 7)]
    assert list(robot.observation_features) == [*KEYS, *extra]
    robot.connect()
    try:
        action = dict(zip(KEYS, (0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), strict=True))
        assert arms.until(lambda: robot.send_action(action) and robot.get_observation()["joint_1.vel"] > 0.5)
        obs = robot.get_observation()
        assert list(obs) == [*KEYS, *extra]
        # The emulator draws 0.2 A + 0.5 A per rad/s; J4..J6 have the smaller torque constant.
        assert obs["joint_4.torque"] == pytest.approx(0.2 * 0.95844, abs=1e-3)
        assert arms.until(lambda: arm.firmware.joints_rad[0] == pytest.approx(0.2, abs=1e-4))
    finally:
        robot.disconnect()


def stamped_dataset(tmp_path: Path, mode: MotionMode | None) -> tuple[Path, Path]:
    """A dataset root (stamped with ``mode`` unless None) and a policy directory trained on it."""
    root = tmp_path / "dataset"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps({"robot_type": "piper_follower"}))
    if mode is not None:
        write_motion_mode(root, mode)
    policy = tmp_path / "pretrained_model"
    policy.mkdir()
    (policy / "train_config.json").write_text(json.dumps({"dataset": {"repo_id": "local/x", "root": str(root)}}))
    return root, policy


def test_the_recorded_motion_mode_round_trips_through_info_json(tmp_path):
    root, policy = stamped_dataset(tmp_path, None)
    assert read_motion_mode(root) is None
    write_motion_mode(root, MotionMode("high_follow", 100))
    assert read_motion_mode(root) == read_motion_mode(policy) == MotionMode("high_follow", 100)
    assert json.loads((root / "meta" / "info.json").read_text())["robot_type"] == "piper_follower"
    assert [p.name for p in (root / "meta").iterdir()] == ["info.json"]  # written atomically, no leftovers
    (policy / "train_config.json").write_text(json.dumps({"dataset": {"repo_id": "local/elsewhere", "root": None}}))
    assert read_motion_mode(policy) is None  # $HF_LEROBOT_HOME/local/elsewhere is not on this machine


@pytest.mark.parametrize(
    "command_line",
    [
        ["lerobot-replay", "--robot.type=piper_follower", "--dataset.repo_id=local/x", "--dataset.root={root}"],
        ["lerobot-rollout", "--robot.type=piper_follower", "--policy.path={policy}", "--duration=2"],
    ],
)
def test_deployment_defaults_to_the_recorded_motion_mode(arms, tmp_path, monkeypatch, command_line):
    root, policy = stamped_dataset(tmp_path, MotionMode("high_follow", 100))
    monkeypatch.setattr(sys, "argv", [a.format(root=root, policy=policy) for a in command_line])
    channel = unique_virtual_channel()
    arm = arms(channel, EmulatorConfig(firmware_text="S-V1.8-5"))
    robot = arms.follower(follower_config(channel, tmp_path))
    assert robot.motion_mode == MotionMode("high_follow", 100)
    robot.connect()
    try:
        assert arm.firmware.mit_mode == 0xAD and arm.firmware.speed_percent == 100
    finally:
        robot.disconnect()


def test_a_given_motion_mode_overrides_the_recorded_one(arms, tmp_path, monkeypatch, caplog):
    root, _ = stamped_dataset(tmp_path, MotionMode("high_follow", 100))
    monkeypatch.setattr(sys, "argv", ["lerobot-replay", f"--dataset.root={root}", "--robot.motion_mode=position"])
    robot = arms.follower(follower_config("x", tmp_path, motion_mode="position"))
    assert robot.motion_mode == MotionMode("position", 50)
    assert "moving in position at 50 %, not in the recorded high_follow at 100 %" in caplog.text
    assert arms.follower(follower_config("x", tmp_path, speed_percent=30)).motion_mode == MotionMode("high_follow", 30)


def test_an_unstamped_dataset_deploys_in_position_mode_with_a_warning(tmp_path, monkeypatch, caplog):
    root, _ = stamped_dataset(tmp_path, None)
    monkeypatch.setattr(sys, "argv", ["lerobot-replay", f"--dataset.root={root}"])
    assert PiperFollower(follower_config("x", tmp_path)).motion_mode == MotionMode("position", 50)
    assert f"no PiPER motion mode recorded for {root} (record with piper-record); moving in position at 50 %" in (
        caplog.text
    )


def test_motion_mode_from_names_the_recording_and_must_have_one(arms, tmp_path):
    _, policy = stamped_dataset(tmp_path, MotionMode("high_follow", 100))
    channel = unique_virtual_channel()
    arm = arms(channel)
    robot = arms.follower(follower_config(channel, tmp_path, motion_mode_from=str(policy)))
    assert robot.motion_mode == MotionMode("high_follow", 100)
    robot.connect()
    try:
        assert arm.firmware.mit_mode == 0xAD and arm.firmware.speed_percent == 100
    finally:
        robot.disconnect()
    with pytest.raises(ValueError, match="no PiPER motion mode recorded for"):
        PiperFollower(follower_config(channel, tmp_path, motion_mode_from=str(tmp_path)))


def test_a_hardware_linked_follower_reports_the_leaders_motion_mode(arms, tmp_path):
    channel = unique_virtual_channel()
    arms(channel, EmulatorConfig(start_enabled=True))
    leader = arms(channel, EmulatorConfig(role="leader"))
    leader.firmware.silent = True  # no 0x151 heard yet: the mode is unknown, not ours
    robot = arms.follower(follower_config(channel, tmp_path, hardware_linked_leader=True))
    robot.connect()
    try:
        assert robot.motion_mode is None
        robot.get_observation()
        assert robot.modes_seen == ()
        leader.firmware.silent = False
        assert arms.until(lambda: robot.motion_mode == MotionMode("high_follow", 100))
        robot.get_observation()
        assert robot.modes_seen == (MotionMode("high_follow", 100),)
    finally:
        robot.disconnect()


def test_piper_record_stamps_one_known_mode_or_explains_why_not(tmp_path):
    root, _ = stamped_dataset(tmp_path, None)
    info = root / "meta" / "info.json"
    info.write_text(json.dumps({"total_episodes": 2}))

    class Seen:
        def __init__(self, *modes: MotionMode):
            self.modes_seen = modes

    high, position = MotionMode("high_follow", 100), MotionMode("position", 50)
    with pytest.raises(record_cli.StampError, match="no linked leader's 0x151 mode frame was heard"):
        record_cli._stamp(root, [Seen()], 0, None)
    with pytest.raises(record_cli.StampError, match=r"changed while recording \(high_follow at 100 %, position"):
        record_cli._stamp(root, [Seen(high, position)], 0, None)
    with pytest.raises(record_cli.StampError, match="already holds 1 episodes recorded in position at 50 %, now high"):
        record_cli._stamp(root, [Seen(high)], 1, position)
    assert read_motion_mode(root) is None
    record_cli._stamp(root, [Seen(high)], 0, None)
    assert read_motion_mode(root) == high
