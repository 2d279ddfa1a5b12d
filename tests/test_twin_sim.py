"""``piper_twin_sim``: the follower on the PiPER's physics twin in this process, on simulated time; and an
unattended ``lerobot-cso eval`` on it, labelled by ``--operator.type=twin`` from the plant itself."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import numpy as np
import pytest
from lerobot.robots import make_robot_from_config
from lerobot_robot_piper import PiperTwinCameraConfig, PiperTwinSimConfig
from robot_fixtures import TASK, save_tiny_piper_policy
from twin_fixtures import button_xy, pressing_pose

from lerobot_cso import cli

KEYS = [*(f"joint_{j}.pos" for j in range(1, 7)), "gripper.pos"]
SEED = 8


def sim_config(**options) -> PiperTwinSimConfig:
    camera = PiperTwinCameraConfig(view="front", width=32, height=24)
    return PiperTwinSimConfig(
        channel=f"piper-twin-sim-{uuid.uuid4().hex[:12]}",
        cameras={"cam": camera},
        motion_mode="position",
        speed_percent=100,
        **options,
    )


def test_each_action_lets_one_control_period_of_simulated_time_pass_and_the_camera_sees_the_arm(tmp_path):
    robot = make_robot_from_config(sim_config(fps=20, calibration_dir=tmp_path))
    target = dict(zip(KEYS, (0.3, 1.2, -1.0, 0.2, 0.5, 0.1, 0.05), strict=True))
    robot.connect()
    try:
        clock = robot.driver.clock
        first, started, plant_started = robot.get_observation(), clock.time(), robot.plant.time_s
        assert first["cam"].shape == (24, 32, 3) and first["cam"].dtype == np.uint8
        for _ in range(40):
            robot.send_action(target)
            observation = robot.get_observation()
        assert clock.time() - started == pytest.approx(40 / 20)  # exactly 40 periods, whatever the wall clock did
        assert max(abs(observation[k] - target[k]) for k in KEYS) < 0.01  # the physical arm got there
        assert np.abs(observation["cam"].astype(int) - first["cam"]).sum() > 0
        assert robot.plant.time_s - plant_started == pytest.approx(40 / 20, abs=0.01)  # the physics kept pace
    finally:
        robot.disconnect()
    assert not robot.is_connected


def test_a_piper_twin_sim_renders_piper_twin_cameras_only():
    from lerobot.cameras.opencv import OpenCVCameraConfig

    with pytest.raises(ValueError, match="renders piper_twin cameras only; camera 'cam' is opencv"):
        PiperTwinSimConfig(cameras={"cam": OpenCVCameraConfig(index_or_path=0, fps=30, width=32, height=32)})


@pytest.fixture(scope="module")
def policy(tmp_path_factory) -> Path:
    return save_tiny_piper_policy(tmp_path_factory.mktemp("sim") / "policy", camera=(24, 32))


def eval_args(policy: Path, output: Path, fps: int) -> list[str]:
    config = sim_config()
    camera = "{cam: {type: piper_twin, view: front, width: 32, height: 24}}"
    rest = pressing_pose(SEED)
    return [
        "eval",
        f"--policy.path={policy}",
        "--robot.type=piper_twin_sim",
        f"--robot.channel={config.channel}",
        f"--robot.cameras={camera}",
        "--robot.motion_mode=position",
        "--robot.speed_percent=100",
        "--robot.scene=press_button",
        f"--robot.fps={fps}",
        "--operator.type=twin",
        f"--operator.scene_seed={SEED}",
        "--operator.fps=10",
        "--operator.episode_time_s=1",
        "--operator.rest_time_s=1.5",
        f"--operator.rest_pose=[{','.join(map(str, rest))}]",
        f"--tasks={TASK}",
        f"--output_dir={output}",
        "--episodes_per_task=2",
    ]


def test_an_unattended_eval_runs_on_the_twin_in_process(policy, tmp_path, monkeypatch, capsys):
    """State 0's button is placed under the resting fingers (pressed: success), state 1's elsewhere (the tiny
    policy only wanders near its rest pose: failure); the plant placed and judged both, in simulated time."""
    assert np.linalg.norm(button_xy(SEED) - button_xy(SEED + 1)) > 0.12
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    assert cli.main(eval_args(policy, tmp_path / "out", fps=10)) == 0
    out = capsys.readouterr().out
    assert f"the twin placed press_button from seed {SEED}\n" in out and f"from seed {SEED + 1}\n" in out
    episodes = sorted((tmp_path / "out" / "robot_journal" / "episodes").glob("*/*.npz"))
    labels = [bool(np.load(p)["success"]) for p in episodes]
    lengths = [int(np.load(p)["length"]) for p in episodes]
    assert labels == [True, False] and lengths[1] == 10, (labels, lengths)  # a failure runs its 1 s at 10 fps
    rate = json.loads((tmp_path / "out" / "eval.json").read_text())["success_rate"][TASK]["mean"]
    assert rate == 0.5


def test_a_simulated_robot_must_run_at_the_control_loops_fps(policy, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    assert cli.main(eval_args(policy, tmp_path / "out", fps=30)) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "error: robot piper_twin_sim runs on simulated time at 30 fps, the control loop at 10: give --robot.fps=10"
    )


def test_a_bad_twin_operator_setting_is_one_error_line(policy, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    assert cli.main([*eval_args(policy, tmp_path / "out", fps=10), "--operator.state_port=70000"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: operator.state_port must be a finite number > 0 and < 65535, got 70000"
    ]


def test_spo_with_a_state_pool_rolls_out_a_state_drawn_again_instead_of_replaying_it(
    policy, tmp_path, monkeypatch, capsys
):
    """SPO's state pool draws state 0 in both iterations; the robot journal named attempts by state alone, so the
    second iteration replayed the first one's episodes (an older policy's) instead of running the arm."""
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    out = tmp_path / "spo"
    robot = [a for a in eval_args(policy, out, fps=10)[1:] if not a.startswith("--episodes_per_task")]
    spo = ["--iterations=2", "--groups_per_iteration=1", "--group_size=2", "--max_draw_factor=1", "--state_pool=1"]
    assert cli.main(["spo", *robot, *spo, "--epochs=1", "--minibatch_trajectories=2"]) == 0
    stdout = capsys.readouterr().out
    assert stdout.count("state 0, attempt 1: ") == stdout.count("state 0, attempt 2: ") == 2  # both on the arm
    names = sorted(p.stem for p in (out / "robot_journal" / "episodes").glob("*/*.npz"))
    assert len(names) == 4 and len({n.rsplit("_", 1)[0] for n in names}) == 2  # two rounds of two attempts
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [row["episodes"] for row in log] == [2, 2]
