"""R-SFT, SPO, evaluation and deployment on the PiPER with an operator in the loop, without a robot.

The real commands run as subprocesses against a ``piper-emulator`` process over udp_multicast, labelled by
a scripted operator (:class:`~lerobot_cso.worlds.robot.operator.ScriptedOperator`): success is a rule on the emulated
arm's measured pose per arranged state, key presses are injected per (state, attempt, retry). The R-SFT
collection is killed with SIGKILL and resumed, then hit by an e-stop sent on the bus (the episode is discarded)
and resumed again with ``--robot.recovery=reset``; SPO is killed and resumed mid-iteration and its update may
change only the prior; ``lerobot-rollout`` drives the final checkpoint. ``--display_data`` is checked on an eval
with rerun kept in memory, bad input as one error line of the real CLI, and the in-place recovery of
``--operator.on_fault=wait`` against the frames on the bus, R-SFT's ``--stop_state_at_cap``, and
``--operator.type=keyboard`` through LeRobot's pynput listener on a virtual X display (Xvfb).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot_robot_piper.cli_processes import cli_env, explain, rollout_args, run_cli
from piper_can import codec
from piper_can.channel_recorder import ChannelRecorder
from piper_can.emulator_process import BIN, EmulatorProcess, start_emulator, unique_udp_channel
from robot_fixtures import REST, TASK, lerobot_cso, save_tiny_piper_policy, write_script
from safetensors.torch import load_file

from lerobot_cso import cli

pytestmark = pytest.mark.slow

TIMEOUT_S = 300
# Rest moves of 1 s: time to reach the rest pose also from where an e-stop let the arm sink.
# The tiny policy keeps the arm within 0.05 of the rest pose (joint_2 at 0.3 rad): "reached" for a target
# there, never for a target at 1.5 rad.
NEAR, FAR = {"joint_2.pos": REST[1]}, {"joint_2.pos": 1.5}
EPISODE = ["--operator.fps=30", "--operator.episode_time_s=0.5", "--operator.rest_time_s=1.0"]
EPISODE += [f"--operator.rest_pose=[{','.join(map(str, REST))}]", f"--tasks={TASK}"]


@pytest.fixture(scope="module")
def home(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("robot_home")


@pytest.fixture(scope="module")
def arm() -> Iterator[EmulatorProcess]:
    emulator = start_emulator(*unique_udp_channel())
    yield emulator
    assert emulator.stop() == 0


@pytest.fixture(scope="module")
def il_policy(home) -> Path:
    return save_tiny_piper_policy(home / "il")


def robot_args(arm: EmulatorProcess) -> list[str]:
    # A loaded 2-core machine: up to 1 s of feedback jitter (the driver's most; a 372 ms gap failed a suite run at
    # 0.3 s), and time to see the reset of an e-stop. No test here waits for a stale-feedback fault.
    return [
        "--robot.type=piper_follower",
        *arm.args("robot"),
        "--robot.feedback_timeout_s=1.0",
        "--robot.enable_timeout_s=5",
    ]


def journal_episodes(output: Path) -> set[str]:
    """``<state>_<attempt>`` of every journaled robot episode."""
    return {p.stem for p in (output / "robot_journal" / "episodes").glob("*/*.npz")}


def live_episodes(stdout: str) -> list[str]:
    """``<state>_<attempt>`` of the episodes a run ran on the arm (from its console lines)."""
    found = re.findall(r"^state (\d+), attempt (\d+): (?:success|failure)", stdout, flags=re.M)
    return [f"{int(s):07d}_{int(a):03d}" for s, a in found]


def wait_for_episodes(output: Path, count: int, process) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while len(journal_episodes(output)) < count:
        assert process.poll() is None, process.communicate()[1][-3000:]
        assert time.monotonic() < deadline, "no episode was journaled in time"
        time.sleep(0.02)


def kill_after(args: list[str], home: Path, output: Path, count: int) -> set[str]:
    """Run ``lerobot-cso ARGS``, SIGKILL it once ``count`` episodes are journaled; returns those on disk."""
    process = lerobot_cso(args, home)
    wait_for_episodes(output, count, process)
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=30)
    return journal_episodes(output)


def finish(args: list[str], home: Path) -> tuple[int, str, str]:
    process = lerobot_cso(args, home)
    out, err = process.communicate(timeout=TIMEOUT_S)
    return process.returncode, out, err


def emergency_stop_until(arm: EmulatorProcess, done: Callable[[], bool]) -> None:
    """Press the e-stop from another program on the bus (0x150 01) until ``done()``.

    Repeated: on a loaded machine the emulator's socket may drop a datagram, and an e-stop is idempotent."""
    frame = codec.encode_emergency_stop(codec.EmergencyStop(codec.EStopAction.STOP))
    message = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
    deadline = time.monotonic() + TIMEOUT_S
    with can.Bus(interface="udp_multicast", channel=arm.group, port=arm.port) as bus:
        while not done() and time.monotonic() < deadline:
            bus.send(message)
            time.sleep(0.05)


@pytest.fixture(scope="module")
def rsft(arm, home, il_policy, tmp_path_factory) -> dict:
    """R-SFT with 2 strikes per state until 4 successes: states 0 and 2 succeed, state 1 is struck out.

    Run 1 is killed while state 1, attempt 2 waits to start (3 episodes on disk); run 2 gets an e-stop while
    state 2, attempt 1 waits; run 3 opens that gate, recovers the arm and ends.
    """
    out, ops = home / "rsft", tmp_path_factory.mktemp("ops")
    gates = {"1/2/0": str(ops / "gate_kill"), "2/1/0": str(ops / "gate_fault")}
    script = write_script(ops / "rsft.json", {"default": NEAR, "1": FAR}, {}, 0.1, gates)
    args = ["rsft", f"--policy.path={il_policy}", *robot_args(arm), *EPISODE, f"--output_dir={out}"]
    args += ["--operator.type=scripted", f"--operator.script={script}", "--n_strikes=2", "--successes_per_task=4"]
    args += ["--states_per_round=1", "--epochs=1", "--batch_size=8"]
    killed = kill_after(args, home, out, 3)
    Path(gates["1/2/0"]).touch()
    process = lerobot_cso(args, home)
    wait_for_episodes(out, len(killed) + 1, process)
    emergency_stop_until(arm, lambda: process.poll() is not None)
    faulted_out, faulted_err = process.communicate(timeout=30)
    faulted = {"rc": process.returncode, "out": faulted_out, "err": faulted_err, "on_disk": journal_episodes(out)}
    Path(gates["2/1/0"]).touch()
    rc, final_out, final_err = finish([*args, "--robot.recovery=reset"], home)
    assert rc == 0, final_err[-3000:]
    return {"out": out, "killed": killed, "faulted": faulted, "final_out": final_out}


def test_rsft_resumes_after_kill_and_fault_with_no_episode_lost_or_duplicated(rsft):
    every = {f"{s:07d}_{a:03d}" for s in range(3) for a in (1, 2)}
    assert journal_episodes(rsft["out"]) == every
    killed, faulted = rsft["killed"], rsft["faulted"]
    assert killed == {"0000000_001", "0000000_002", "0000001_001"}
    assert faulted["on_disk"] == killed | {"0000001_002"}
    # Each run ran on the arm exactly the episodes that were not on disk yet, in order.
    second, third = live_episodes(faulted["out"]), live_episodes(rsft["final_out"])
    assert sorted(killed) + second + third == sorted(every)
    assert second == ["0000001_002"] and "resuming: 1 episodes on disk; next: state 1, attempt 2" in faulted["out"]
    report = json.loads((rsft["out"] / "collection.json").read_text())[TASK]
    assert report == {"rollouts": 6, "successes": 4, "kept": 4, "states_tried": 3, "states_struck_out": 1}


def test_an_emergency_stop_discards_the_episode_in_flight_and_ends_the_command_with_one_line(rsft):
    faulted = rsft["faulted"]
    assert faulted["rc"] == 1
    last = faulted["err"].strip().splitlines()[-1]
    assert last.startswith("error: robot fault in state ") and "emergency stop" in last, last
    records = list((rsft["out"] / "robot_journal" / "records").glob("*/*.json"))
    assert len(records) == 1  # the e-stopped try: recorded as discarded, then rerun and kept
    discarded = json.loads(records[0].read_text())["discarded"]
    assert len(discarded) == 1 and "emergency stop" in discarded[0]
    assert records[0].stem == "0000002_001" and records[0].stem in live_episodes(rsft["final_out"])


def test_rsft_buffer_holds_exactly_the_successes_with_their_skills(rsft):
    out = rsft["out"]
    ds = LeRobotDataset("local/cso_rsft_buffer", root=out / "buffer")
    assert ds.num_episodes == 4 and ds.meta.robot_type == "piper_follower" and ds.meta.fps == 30
    seeds = np.asarray(ds.hf_dataset["rsft.init_seed"]).reshape(-1)
    assert sorted(set(seeds.tolist())) == [0, 2]
    assert "observation.skill_tokens" in ds.features
    lengths = [int(np.load(p)["length"]) for p in sorted((out / "robot_journal" / "episodes").glob("*/000000[02]_*"))]
    assert ds.num_frames == sum(lengths)
    config = json.loads((out / "pretrained_model" / "config.json").read_text())
    assert config["freeze_encoders"] is True


@pytest.fixture(scope="module")
def spo(arm, home, rsft, tmp_path_factory) -> dict:
    """One SPO iteration of 2 groups of K=2 (attempt 1 of each state succeeds by key, attempt 2 fails), killed
    while state 1 waits to start (2 episodes on disk) and resumed."""
    out, ops = home / "spo", tmp_path_factory.mktemp("ops")
    keys = {f"{state}/1/0": [2, "success"] for state in (0, 1)}
    gate = ops / "gate_kill"
    script = write_script(ops / "spo.json", {"default": FAR}, keys, 0.1, {"1/1/0": str(gate)})
    policy = rsft["out"] / "pretrained_model"
    args = ["spo", f"--policy.path={policy}", *robot_args(arm), *EPISODE, f"--output_dir={out}"]
    args += ["--operator.type=scripted", f"--operator.script={script}", "--iterations=1"]
    args += ["--groups_per_iteration=2", "--group_size=2", "--epochs=2", "--lr=1e-3", "--max_draw_factor=1"]
    killed = kill_after(args, home, out, 2)
    gate.touch()
    rc, final_out, err = finish(args, home)
    assert rc == 0, err[-3000:]
    return {"out": out, "killed": killed, "final_out": final_out, "before": policy}


def test_spo_resumes_mid_iteration_and_its_update_changes_only_the_prior(spo):
    every = {f"{s:07d}_{a:03d}" for s in range(2) for a in (1, 2)}
    assert journal_episodes(spo["out"]) == every
    assert spo["killed"] == {"0000000_001", "0000000_002"}
    assert live_episodes(spo["final_out"]) == ["0000001_001", "0000001_002"]
    log = [json.loads(line) for line in (spo["out"] / "log.jsonl").read_text().splitlines()]
    assert len(log) == 1 and log[0]["success_rate"] == 0.5 and log[0]["rejection_rate"] == 0 and log[0]["updates"] > 0
    before = load_file(spo["before"] / "model.safetensors")
    after = load_file(spo["out"] / "pretrained_model" / "model.safetensors")
    assert before.keys() == after.keys()
    changed = {k for k in before if not np.array_equal(before[k].numpy(), after[k].numpy())}
    assert changed and all(k.startswith("prior.") for k in changed), sorted(changed)[:5]


def test_lerobot_rollout_drives_the_final_checkpoint_on_the_arm(spo, arm, home):
    recorder = ChannelRecorder(arm.group, arm.port)
    try:
        policy = spo["out"] / "pretrained_model"
        out = run_cli("lerobot-rollout", rollout_args(policy, robot_args(arm), TASK, 1, 30), home)
    finally:
        recorder.stop()
    assert out.returncode == 0, explain(out)
    commands = np.array([c.joints_rad for c in recorder.commands.joints])
    assert len(commands) > 10
    assert np.abs(commands - np.array(REST[:6])).max() < 0.2  # the policy's actions, near its training range


@pytest.fixture(scope="module")
def other_policies(home) -> dict[str, Path]:
    return {
        "state39": save_tiny_piper_policy(home / "state39", state_dim=39),
        "camera": save_tiny_piper_policy(home / "camera", camera=(32, 32)),
    }


def camera_args(path: int | str) -> str:
    """``--robot.cameras`` with one 32x32 OpenCV camera ``cam`` at ``path``."""
    return f"--robot.cameras={{cam: {{type: opencv, index_or_path: {path}, width: 32, height: 32, fps: 30}}}}"


class CountingCamera:
    """Stands in for the OpenCV camera ``cam`` (none on the test machine): every read is a new frame."""

    def __init__(self, height: int, width: int) -> None:
        self.shape, self.reads, self.is_connected = (height, width, 3), 0, False

    def connect(self) -> None:
        self.is_connected = True

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        self.reads += 1
        return np.full(self.shape, self.reads % 256, dtype=np.uint8)

    def disconnect(self) -> None:
        self.is_connected = False


def test_display_data_logs_cameras_joints_sent_actions_and_the_current_skill(
    arm, other_policies, monkeypatch, tmp_path
):
    """``--display_data=true`` on a real eval in this process: rerun gets no viewer (a memory sink instead of
    ``spawn``), and every policy tick logs the frame and joints it decided from, the action sent and the skill
    being executed, exactly as journaled."""
    import lerobot.utils.visualization_utils as visualization
    import lerobot_robot_piper.piper_follower as piper_follower
    import rerun

    monkeypatch.setattr(rerun, "spawn", lambda **kw: rerun.memory_recording())
    paths: set[str] = set()
    shown: list[tuple[dict, dict | None]] = []
    rerun_log, log_data = rerun.log, visualization.log_visualization_data

    def log(path: str, *args, **kwargs) -> None:
        paths.add(path)
        rerun_log(path, *args, **kwargs)

    def capture(mode: str, observation: dict, action: dict | None) -> None:
        shown.append((dict(observation), action))
        log_data(mode, observation=observation, action=action)

    def cameras(configs: dict) -> dict[str, CountingCamera]:
        return {name: CountingCamera(c.height, c.width) for name, c in configs.items()}

    monkeypatch.setattr(rerun, "log", log)
    monkeypatch.setattr(visualization, "log_visualization_data", capture)
    monkeypatch.setattr(piper_follower, "make_cameras_from_configs", cameras)
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    script = write_script(tmp_path / "eval.json", {"default": FAR}, {"1/1/0": [10, "success"]}, 0.1, {})
    args = ["eval", f"--policy.path={other_policies['camera']}", *robot_args(arm), camera_args(0), *EPISODE]
    args += [f"--output_dir={tmp_path / 'out'}", "--operator.type=scripted", f"--operator.script={script}"]
    assert cli.main([*args, "--episodes_per_task=2", "--display_data=true"]) == 0

    policy_ticks = [(obs, action) for obs, action in shown if action is not None]
    assert all("skill.index" not in obs for obs, action in shown if action is None)  # the arrange phase
    episodes = sorted((tmp_path / "out" / "robot_journal" / "episodes").glob("*/*.npz"))
    journal = [np.load(p) for p in episodes]
    assert [int(e["length"]) for e in journal] == [15, 11]
    assert len(policy_ticks) == 26
    joints, ticks = [f"joint_{j}.pos" for j in range(1, 7)] + ["gripper.pos"], iter(policy_ticks)
    for episode in journal:
        decisions = episode["record_decision_steps"].tolist()
        assert decisions == [0, 8]
        for t in range(int(episode["length"])):
            obs, action = next(ticks)
            skill = sum(step <= t for step in decisions) - 1
            np.testing.assert_array_equal(obs["cam"], episode["image_cam"][t])
            np.testing.assert_allclose([obs[k] for k in joints], episode["states"][t], rtol=0, atol=1e-6)
            np.testing.assert_allclose([action[k] for k in joints], episode["actions"][t], rtol=0, atol=1e-6)
            assert obs["skill.index"] == skill
            np.testing.assert_array_equal(obs["skill.tokens"], episode["record_tokens"][skill])
    expected = {"observation.cam", "observation.skill.index", "observation.skill.tokens"}
    expected |= {f"observation.{k}" for k in joints} | {f"action.{k}" for k in joints}
    assert expected <= paths, sorted(expected - paths)


@pytest.fixture(scope="module")
def bad_input(arm, il_policy, other_policies, home, tmp_path_factory) -> dict[str, tuple[int, str]]:
    """Each bad command line of the real CLI, all started at once: case -> (exit code, stderr)."""
    out, ops = tmp_path_factory.mktemp("bad"), tmp_path_factory.mktemp("bad_ops")
    script = write_script(ops / "none.json", {}, {}, 0.1, {})
    common = [f"--tasks={TASK}", "--operator.fps=30", "--operator.type=scripted", f"--operator.script={script}"]
    piper = ["--robot.type=piper_follower", "--robot.motion_mode=position"]  # a mode: no warning about it
    nobody = unique_udp_channel()
    cases = {
        "unknown robot": [f"--policy.path={other_policies['camera']}", "--robot.type=nosuch"],
        "other features": [f"--policy.path={other_policies['state39']}", *piper],
        "camera not on the robot": [f"--policy.path={other_policies['camera']}", *piper],
        "camera that does not open": [
            f"--policy.path={other_policies['camera']}",
            *piper,
            *robot_args(arm)[1:],
            camera_args(ops / "no_cam"),
        ],
        "motion mode from a missing dataset": [
            f"--policy.path={il_policy}",
            "--robot.type=piper_follower",
            f"--robot.motion_mode_from={out / 'no_such_dataset'}",
        ],
        "arm not on the bus": [
            f"--policy.path={il_policy}",
            *piper,
            "--robot.interface=udp_multicast",
            f"--robot.channel={nobody[0]}",
            f"--robot.port={nobody[1]}",
        ],
    }
    processes = {
        case: lerobot_cso(["eval", *args, *common, f"--output_dir={out / str(i)}"], home)
        for i, (case, args) in enumerate(cases.items())
    }
    errors = {case: p.communicate(timeout=TIMEOUT_S)[1] for case, p in processes.items()}
    return {case: (processes[case].returncode, err) for case, err in errors.items()}


@pytest.mark.parametrize(
    ("case", "code", "message"),
    [
        ("unknown robot", 2, "error: argument --world.robot.type: invalid choice: 'nosuch' (choose from "),
        (
            "other features",
            2,
            "error: the policy reads observation.state of shape (39,), but robot piper_follower observes 7 values",
        ),
        (
            "camera not on the robot",
            2,
            "error: the policy reads camera 'cam', but robot piper_follower has cameras: none",
        ),
        (
            "camera that does not open",
            1,
            "error: robot piper_follower did not connect: ConnectionError: Failed to open OpenCVCamera(",
        ),
        (
            "motion mode from a missing dataset",
            2,
            "error: robot piper_follower cannot be made: no PiPER motion mode recorded for ",
        ),
        ("arm not on the bus", 1, "error: robot piper_follower did not connect: PiperConnectionError: no PiPER heard"),
    ],
)
def test_bad_input_is_one_error_line_and_a_non_zero_exit(bad_input, case, code, message):
    """One ``error:`` line, last; before it at most what the robot logged while it tried to connect."""
    rc, err = bad_input[case]
    *before, last = err.strip().splitlines()
    assert rc == code, err[-3000:]
    assert last.startswith(message), err[-3000:]
    connecting = code == 1
    assert all(connecting and line.startswith(("WARNING:", "INFO:")) for line in before), err[-3000:]


def test_an_unknown_operator_is_one_error_line(other_policies, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    args = ["eval", f"--policy.path={other_policies['camera']}", "--robot.type=piper_follower", f"--tasks={TASK}"]
    assert cli.main([*args, f"--output_dir={tmp_path}", "--operator.fps=30", "--operator.type=mouse"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: operator.type must be one of keyboard, scripted, twin, got 'mouse'"
    ]


class FrameLog:
    """Every frame on a udp channel as (kernel receive time, id, data), from a thread."""

    def __init__(self, arm: EmulatorProcess) -> None:
        self.frames: list[tuple[float, int, bytes]] = []
        self._bus = can.Bus(interface="udp_multicast", channel=arm.group, port=arm.port)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self._bus.recv(timeout=0.05)
            if msg is not None:
                self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._bus.shutdown()


def test_with_on_fault_wait_the_operator_recovers_the_arm_in_place_and_nothing_reaches_it_meanwhile(
    arm, il_policy, home, tmp_path
):
    """An eval of 2 trials with ``--operator.on_fault=wait``: trial 1 is e-stopped while it waits to start; the
    command discards it, disconnects and waits for the operator (a gate), sends no motion frame until it has
    reconnected with a reset, then repeats trial 1 and ends normally."""
    out, recovered = tmp_path / "out", tmp_path / "recovered"
    gates = {"1/1/0": str(tmp_path / "never"), "recover/1/1/0": str(recovered)}
    script = write_script(tmp_path / "eval.json", {"default": NEAR}, {}, 0.1, gates)
    args = ["eval", f"--policy.path={il_policy}", *robot_args(arm), *EPISODE, f"--output_dir={out}"]
    args += ["--operator.type=scripted", f"--operator.script={script}", "--episodes_per_task=2"]
    args += ["--operator.on_fault=wait", "--robot.recovery=reset"]
    records = out / "robot_journal" / "records"
    frames = FrameLog(arm)
    try:
        process = lerobot_cso(args, home)
        wait_for_episodes(out, 1, process)
        emergency_stop_until(arm, lambda: any(records.glob("*/0000001_001.json")) or process.poll() is not None)
        assert process.poll() is None, process.communicate()[1][-3000:]
        waiting_since = time.time()
        time.sleep(1.0)  # the operator recovers the arm
        recovered.touch()
        stdout, stderr = process.communicate(timeout=TIMEOUT_S)
    finally:
        frames.stop()
    assert process.returncode == 0, stderr[-3000:]
    assert journal_episodes(out) == {"0000000_001", "0000001_001"}
    discarded = json.loads(next(records.glob("*/0000001_001.json")).read_text())["discarded"]
    assert len(discarded) == 1 and "emergency stop" in discarded[0], discarded
    assert "robot fault in state 1, attempt 1: FirmwareFaultError" in stdout
    assert "reconnected; state 1, attempt 1 again" in stdout and live_episodes(stdout)[-1] == "0000001_001"
    resets = [t for t, i, data in frames.frames if i == codec.ID_EMERGENCY_STOP and data[0] == codec.EStopAction.RESUME]
    reset_at = min(t for t in resets if t > waiting_since)
    motion = [t for t, i, _ in frames.frames if i in codec.ID_JOINT_COMMAND and waiting_since < t < reset_at]
    assert not motion, f"{len(motion)} joint commands reached the e-stopped arm"
    assert any(i in codec.ID_JOINT_COMMAND and t > reset_at for t, i, _ in frames.frames)


def test_with_stop_state_at_cap_no_attempt_past_a_states_cap_reaches_the_arm(arm, il_policy, home, tmp_path):
    """R-SFT with 3 strikes, a cap of 1 and ``--stop_state_at_cap=true``: state 0 fails attempt 1 (a key) and
    succeeds attempt 2, state 1 succeeds attempt 1; the other three attempts are never run."""
    out = tmp_path / "rsft"
    script = write_script(tmp_path / "cap.json", {"default": NEAR}, {"0/1/0": [2, "failure"]}, 0.1, {})
    args = ["rsft", f"--policy.path={il_policy}", *robot_args(arm), *EPISODE, f"--output_dir={out}"]
    args += ["--operator.type=scripted", f"--operator.script={script}", "--n_strikes=3", "--successes_per_task=2"]
    args += ["--max_successes_per_state=1", "--stop_state_at_cap=true", "--states_per_round=2"]
    args += ["--epochs=1", "--batch_size=8", "--robot.recovery=reset"]
    rc, stdout, stderr = finish(args, home)
    assert rc == 0, stderr[-3000:]
    assert live_episodes(stdout) == ["0000000_001", "0000000_002", "0000001_001"]
    assert journal_episodes(out) == {"0000000_001", "0000000_002", "0000001_001"}
    report = json.loads((out / "collection.json").read_text())[TASK]
    assert report == {"rollouts": 3, "successes": 2, "kept": 2, "states_tried": 2, "states_struck_out": 0}


@pytest.fixture(scope="module")
def x_display() -> Iterator[str]:
    """A virtual X display for LeRobot's pynput key listener (``./run.sh test`` installs Xvfb where it can)."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("no Xvfb here: the pynput keyboard backend needs an X display")
    read, write = os.pipe()
    command = [xvfb, "-displayfd", str(write), "-screen", "0", "320x240x24", "-nolisten", "tcp"]
    server = subprocess.Popen(command, pass_fds=(write,), stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as pipe:
        display = f":{pipe.readline().strip()}"
    yield display
    server.terminate()
    server.wait(timeout=10)


def type_key(display: str, keysym: str) -> None:
    """Press and release the key of X keysym ``keysym`` ("Return", "s") on ``display`` through XTest, from
    another X client, as a keyboard would (python-xlib, which pynput's X backend is built on)."""
    code = "import sys; from Xlib import X, XK, display; from Xlib.ext import xtest; d = display.Display(); "
    code += "k = d.keysym_to_keycode(XK.string_to_keysym(sys.argv[1])); "
    code += "xtest.fake_input(d, X.KeyPress, k); xtest.fake_input(d, X.KeyRelease, k); d.sync()"
    env = {**os.environ, "DISPLAY": display}
    subprocess.run([sys.executable, "-c", code, keysym], env=env, check=True, timeout=60)


def test_the_keyboard_operator_takes_its_keys_from_lerobots_pynput_listener_on_a_display(
    arm, il_policy, home, tmp_path, x_display
):
    """``lerobot-cso eval --operator.type=keyboard`` with a display and no terminal: LeRobot's listener is the
    pynput one, and keys typed on the display start each trial (Enter) and label it (s, then f)."""
    out = tmp_path / "out"
    args = ["eval", f"--policy.path={il_policy}", *robot_args(arm), "--operator.type=keyboard"]
    args += ["--operator.fps=30", "--operator.episode_time_s=30", "--operator.rest_time_s=0.5", f"--tasks={TASK}"]
    args += [f"--operator.rest_pose=[{','.join(map(str, REST))}]", "--episodes_per_task=2", f"--output_dir={out}"]
    with open(tmp_path / "stderr.txt", "w") as stderr:
        process = subprocess.Popen(
            [str(BIN / "lerobot-cso"), *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            env={**cli_env(home), "DISPLAY": x_display},
            cwd=home,
        )
        lines: list[str] = []
        try:
            for trial, verdict in ((0, "s"), (1, "f")):
                prompt = f">>> state {trial}, attempt 1 of 1 — arrange a new scene; then press Enter"
                while not any(line.startswith(prompt) for line in lines):
                    line = process.stdout.readline()
                    assert line, (tmp_path / "stderr.txt").read_text()[-3000:]
                    lines.append(line)
                type_key(x_display, "Return")
                time.sleep(1.0)  # the trial starts at the next poll; a verdict before it would be dropped
                type_key(x_display, verdict)
            rest, _ = process.communicate(timeout=TIMEOUT_S)
        finally:
            process.kill()
    stdout = "".join(lines) + rest
    assert process.returncode == 0, (tmp_path / "stderr.txt").read_text()[-3000:]
    assert re.search(r"^state 0, attempt 1: success after \d+ steps", stdout, flags=re.M), stdout
    assert re.search(r"^state 1, attempt 1: failure after \d+ steps", stdout, flags=re.M), stdout
    assert json.loads((out / "eval.json").read_text())["success_rate"][TASK]["mean"] == 0.5
