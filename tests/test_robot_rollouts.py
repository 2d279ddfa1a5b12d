"""R-SFT, SPO, evaluation and deployment on the PiPER with an operator in the loop, without a robot.

The real commands run as subprocesses against a ``piper-emulator`` process over udp_multicast, labelled by
a scripted operator (:class:`~lerobot_cso.rollout.operator.ScriptedOperator`): success is a rule on the emulated
arm's measured pose per arranged state, key presses are injected per (state, attempt, retry). The R-SFT
collection is killed with SIGKILL and resumed, then hit by an e-stop sent on the bus (the episode is discarded)
and resumed again with ``--robot.recovery=reset``; SPO is killed and resumed mid-iteration and its update may
change only the prior; ``lerobot-rollout`` drives the final checkpoint.
"""

from __future__ import annotations

import json
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from piper_can import codec
from robot_fixtures import (
    REST,
    TASK,
    ChannelRecorder,
    EmulatorProcess,
    explain,
    lerobot_cso,
    run_cli,
    save_tiny_piper_policy,
    start_emulator,
    unique_udp_channel,
    write_script,
)
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
    # A loaded 2-core machine: 300 ms of feedback jitter, and time to see the reset of an e-stop.
    return [
        "--robot.type=piper_follower",
        *arm.args("robot"),
        "--robot.feedback_timeout_s=0.3",
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


def emergency_stop_until_exit(arm: EmulatorProcess, process) -> tuple[str, str]:
    """Press the e-stop from another program on the bus (0x150 01) until ``process`` ends; returns its output.

    Repeated: on a loaded machine the emulator's socket may drop a datagram, and an e-stop is idempotent."""
    frame = codec.encode_emergency_stop(codec.EmergencyStop(codec.EStopAction.STOP))
    message = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
    deadline = time.monotonic() + TIMEOUT_S
    with can.Bus(interface="udp_multicast", channel=arm.group, port=arm.port) as bus:
        while process.poll() is None and time.monotonic() < deadline:
            bus.send(message)
            time.sleep(0.05)
    return process.communicate(timeout=30)


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
    faulted_out, faulted_err = emergency_stop_until_exit(arm, process)
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
        out = run_cli(
            "lerobot-rollout",
            [
                "--strategy.type=base",
                f"--policy.path={spo['out'] / 'pretrained_model'}",
                *robot_args(arm),
                f"--task={TASK}",
                "--duration=1",
                "--fps=30",
                "--device=cpu",
            ],
            home,
        )
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


@pytest.mark.parametrize(
    ("policy", "extra", "message"),
    [
        (
            "state39",
            [],
            "error: the policy reads observation.state of shape (39,), but robot piper_follower observes 7 values",
        ),
        ("camera", [], "error: the policy reads camera 'cam', but robot piper_follower has cameras: none"),
        ("camera", ["--operator.type=mouse"], "error: operator.type must be one of keyboard, scripted"),
    ],
)
def test_bad_input_is_one_error_line(other_policies, policy, extra, message, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    args = ["eval", f"--policy.path={other_policies[policy]}", "--robot.type=piper_follower", f"--tasks={TASK}"]
    assert cli.main([*args, f"--output_dir={tmp_path}", "--operator.fps=30", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(message), err[-1]
    assert sum(line.startswith("error:") for line in err) == 1


def test_an_unknown_robot_is_refused_by_the_parser(other_policies, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["eval", f"--policy.path={other_policies['camera']}", "--robot.type=nosuch", f"--tasks={TASK}"])
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error: argument --robot.type: invalid choice: 'nosuch'" in last
