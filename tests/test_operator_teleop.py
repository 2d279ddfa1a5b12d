"""The keyboard operator and the teleoperated reset phase of a robot rollout (issue 11, "CSO on the real arm").

:class:`~lerobot_cso.worlds.robot.operator.KeyboardOperator` gets its keys from LeRobot's
``lerobot.utils.keyboard_input.create_key_listener(dispatch, controls_help=...)``: the unit tests replace that
factory by a fake listener whose ``press`` calls the operator's ``dispatch`` with the names LeRobot's backends
deliver ("enter", "space", "right", "esc", or a character); one test runs LeRobot's real terminal backend on a
pseudo-terminal instead, so the names the operator maps are the ones LeRobot really sends.

The :class:`~lerobot_cso.worlds.robot.backend.RobotBackend` tests run whole episodes in this process on the simulated
PiPER firmware (python-can ``virtual`` buses) with the real ``piper_follower`` robot and ``piper_leader``
teleoperator, all on one ``SimulatedClock`` (the backend's control-tick sleep moves that clock), so every tick
is exact and a loaded machine cannot make the feedback stale. A scripted person presses keys on the fake
keyboard at chosen polls of the real ``KeyboardOperator``.
"""

from __future__ import annotations

import json
import os
import pty
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import can
import lerobot.utils.keyboard_input as keyboard_input
import numpy as np
import pytest
from lerobot_robot_piper import PiperFollower, PiperFollowerConfig, PiperLeader, PiperLeaderConfig
from piper_can import codec
from piper_can.clock import SimulatedClock
from piper_can.emulator import PiperEmulator
from piper_can.firmware import EmulatorConfig, PiperFirmware
from robot_fixtures import REST, TASK

import lerobot_cso.worlds.robot.backend as robot_module
import lerobot_cso.worlds.robot.devices as devices_module
import lerobot_cso.worlds.robot.operator as operator_module
from lerobot_cso.durable import EpisodeJournal
from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.backend import Job
from lerobot_cso.worlds.robot.backend import RobotBackend
from lerobot_cso.worlds.robot.config import RobotWorldConfig
from lerobot_cso.worlds.robot.devices import ArmFault, Devices
from lerobot_cso.worlds.robot.operator import EpisodeInfo, KeyboardOperator, OperatorConfig, OperatorQuit, make_operator

HELP = KeyboardOperator.HELP
QUIT = "stopped by the operator; rerun the same command to resume"
FPS = 30
# What the fake policy commands: within 0.2 of the rest pose (not clamped), far from every leader pose.
POLICY = np.array(REST) + np.array([0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.01])


# ---------------------------------------------------------------------------------------------- the keyboard
class FakeListener:
    """Stands in for LeRobot's key listener: ``press`` delivers key names as its backends do."""

    def __init__(self, dispatch: Callable[[str], None], controls_help: str) -> None:
        self.dispatch, self.controls_help, self.stopped = dispatch, controls_help, False

    def press(self, *names: str) -> None:
        for name in names:
            self.dispatch(name)

    def stop(self) -> None:
        self.stopped = True


@pytest.fixture
def keys(monkeypatch) -> list[FakeListener]:
    """Every listener a ``KeyboardOperator`` made in the test (no real keyboard, no display)."""
    made: list[FakeListener] = []

    def create_key_listener(dispatch, *, controls_help: str = "") -> FakeListener:
        made.append(FakeListener(dispatch, controls_help))
        return made[-1]

    monkeypatch.setattr(keyboard_input, "create_key_listener", create_key_listener)
    return made


def test_keys_start_the_episode_and_label_it_as_documented(keys, capsys):
    operator = make_operator(OperatorConfig(type="keyboard"))
    assert isinstance(operator, KeyboardOperator) and len(keys) == 1
    keyboard = keys[0]
    assert keyboard.controls_help == HELP
    info = EpisodeInfo(state=3, attempt=2, attempts=4, retry=0, horizon=10)

    keyboard.press("enter")  # before the prompt (a stale press): does not start this try
    assert not operator.ready(info)
    assert (
        capsys.readouterr().out == f"\n>>> state 3, attempt 2 of 4 — arrange it as before; then press Enter ({HELP})\n"
    )
    for key in ("s", "f", "d", "x", "left"):  # verdict keys and unknown keys do not start it either
        keyboard.press(key)
        assert not operator.ready(info)
    for key in ("enter", "space", "n", "N", "right"):  # the documented start keys (Shift+n too)
        keyboard.press(key)
        assert operator.ready(info), key
        assert not operator.ready(info), f"one press of {key!r} started two episodes"
    assert capsys.readouterr().out == ""  # one prompt per try

    assert operator.verdict(info, {}, 0) is None  # no key yet: the policy goes on
    for key, verdict in [("s", "success"), ("S", "success"), ("f", "failure"), ("d", "discard")]:
        keyboard.press(key)
        assert operator.verdict(info, {}, 1) == verdict, key
        assert operator.verdict(info, {}, 2) is None, f"one press of {key!r} gave two verdicts"
    keyboard.press("enter")  # a start key while the policy runs is no verdict
    assert operator.verdict(info, {}, 3) is None
    keyboard.press("s", "x")  # an unknown key after a verdict key does not cancel it
    assert operator.verdict(info, {}, 4) == "success"

    # The next try of the same attempt, and a first attempt: their own prompts.
    assert not operator.ready(EpisodeInfo(3, 2, 4, 1, 10))
    assert not operator.ready(EpisodeInfo(0, 1, 2, 0, 10))
    assert capsys.readouterr().out.splitlines()[1::2] == [
        f">>> state 3, attempt 2 of 4 (try 2) — arrange it as before; then press Enter ({HELP})",
        f">>> state 0, attempt 1 of 2 — arrange a new scene; then press Enter ({HELP})",
    ]
    operator.close()
    assert keyboard.stopped


@pytest.mark.parametrize("key", ["q", "Q", "esc"])
def test_q_or_esc_stops_the_command_in_every_phase(keys, monkeypatch, key):
    operator = KeyboardOperator()
    keyboard = keys[0]
    info = EpisodeInfo(0, 1, 1, 0, 10)
    operator.ready(info)
    keyboard.press(key)
    with pytest.raises(OperatorQuit, match=f"^{QUIT}$") as stopped:  # arranging
        operator.ready(info)
    assert isinstance(stopped.value, SystemExit)  # the command ends with the message, exit code 1
    keyboard.press(key)
    with pytest.raises(OperatorQuit, match=f"^{QUIT}$"):  # while the policy runs
        operator.verdict(info, {}, 0)
    monkeypatch.setattr(operator_module, "time", SimpleNamespace(sleep=lambda s: keyboard.press(key)))
    with pytest.raises(OperatorQuit, match=f"^{QUIT}$"):  # waiting for the arm to be recovered
        operator.wait_for_recovery(info)


def test_wait_for_recovery_returns_on_enter_only_and_prompts_the_try_again(keys, monkeypatch, capsys):
    operator = KeyboardOperator()
    keyboard = keys[0]
    info = EpisodeInfo(1, 1, 2, 0, 10)
    operator.ready(info)
    presses = iter(["s", None, "f", "space"])  # the person's keys, one per poll of the wait
    slept: list[float] = []

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        if (key := next(presses)) is not None:
            keyboard.press(key)

    monkeypatch.setattr(operator_module, "time", SimpleNamespace(sleep=sleep))
    capsys.readouterr()
    keyboard.press("enter")  # pressed before the wait began (e.g. while the arm faulted): not a confirmation
    operator.wait_for_recovery(info)
    assert slept == [operator_module.POLL_S] * 4
    assert (
        capsys.readouterr().out == ">>> once the arm is safe and recovered, press Enter to reconnect (q/Esc = stop)\n"
    )
    assert not operator.ready(info)  # the same try again, with its prompt again
    assert "state 1, attempt 1 of 2 — arrange a new scene" in capsys.readouterr().out


def test_without_a_keyboard_the_keyboard_operator_is_a_usage_error(monkeypatch):
    """LeRobot's real ``create_key_listener``: no display (no pynput) and stdin not a terminal."""
    monkeypatch.setattr(keyboard_input, "pynput_can_capture", lambda: False)
    with open(os.devnull) as devnull:
        monkeypatch.setattr(sys, "stdin", devnull)
        with pytest.raises(UsageError, match=r"^no keyboard available .* or use --operator.type=scripted$"):
            make_operator(OperatorConfig(type="keyboard"))


def test_lerobots_terminal_listener_delivers_the_keys_the_operator_maps(monkeypatch):
    """LeRobot's real terminal backend (what ``lerobot-record`` uses without a display) on a pseudo-terminal:
    the bytes a terminal sends for Enter, space, n, the right arrow (both encodings), s, f, d and a bare Esc."""
    master, slave = pty.openpty()
    heard: list[str] = []
    on_key = KeyboardOperator._on_key

    def recording_on_key(self: KeyboardOperator, name: str) -> None:
        on_key(self, name)
        heard.append(name)  # after the operator has it

    monkeypatch.setattr(KeyboardOperator, "_on_key", recording_on_key)
    monkeypatch.setattr(keyboard_input, "pynput_can_capture", lambda: False)
    with os.fdopen(slave, "r") as terminal:
        monkeypatch.setattr(sys, "stdin", terminal)
        operator = KeyboardOperator()
        try:
            assert isinstance(operator.listener, keyboard_input.TerminalKeyListener)

            def type_key(data: bytes) -> str:
                count = len(heard)
                os.write(master, data)
                deadline = time.monotonic() + 10
                while len(heard) == count:
                    assert time.monotonic() < deadline, f"LeRobot's listener delivered nothing for {data!r}"
                    time.sleep(0.01)
                return heard[-1]

            info = EpisodeInfo(0, 1, 1, 0, 10)
            operator.ready(info)
            for data, name in [
                (b"\r", "enter"),
                (b" ", "space"),
                (b"n", "n"),
                (b"\x1b[C", "right"),
                (b"\x1bOC", "right"),
            ]:
                assert type_key(data) == name
                assert operator.ready(info), data
            for data, verdict in [(b"s", "success"), (b"f", "failure"), (b"d", "discard")]:
                type_key(data)
                assert operator.verdict(info, {}, 0) == verdict
            assert type_key(b"\x1b") == "esc"
            with pytest.raises(OperatorQuit):
                operator.ready(info)
        finally:
            operator.close()
            os.close(master)


# ---------------------------------------------------------------------------------------------- on the arm
class Person:
    """The person at the robot: presses keys on the fake keyboard at chosen polls of the real operator.

    ``script``: ``"<state>/<attempt>/<retry>"`` -> (the ready poll at which a start key is pressed, that key,
    the policy tick at which a verdict key is pressed or None, that key)."""

    def __init__(self, operator: KeyboardOperator, keyboard: FakeListener, script: dict, log: Timeline) -> None:
        self.operator, self.keyboard, self.script, self.log = operator, keyboard, script, log
        self.polls: dict[str, int] = {}

    def ready(self, info: EpisodeInfo) -> bool:
        poll = self.polls.get(info.key, 0)
        self.polls[info.key] = poll + 1
        start_at, start_key, *_ = self.script[info.key]
        self.log.note("poll", poll=poll)
        if poll == start_at:
            self.keyboard.press(start_key)
        ready = self.operator.ready(info)
        if ready:
            self.log.phase = "return"
        return ready

    def verdict(self, info: EpisodeInfo, observation: dict[str, Any], tick: int) -> str | None:
        *_, at, key = self.script[info.key]
        if tick == at:
            self.keyboard.press(key)
        return self.operator.verdict(info, observation, tick)

    def wait_for_recovery(self, info: EpisodeInfo) -> None:
        raise AssertionError("no fault is expected")

    def close(self) -> None:
        self.operator.close()


@dataclass
class Timeline:
    """What happened on the arm, with the emulated firmware's ground truth at each moment."""

    firmware: PiperFirmware
    phase: str = "before"  # before (the move to rest, arranging) | return (to rest, after Enter) | policy
    events: list[SimpleNamespace] = field(default_factory=list)

    def note(self, kind: str, **data: Any) -> None:
        fw = self.firmware
        truth = {"targets": np.array(fw.targets_rad), "joints": np.array(fw.joints_rad), "gripper": fw.gripper_m}
        self.events.append(SimpleNamespace(kind=kind, phase=self.phase, **truth, **data))

    def of(self, kind: str, phase: str | None = None) -> list[SimpleNamespace]:
        return [e for e in self.events if e.kind == kind and phase in (None, e.phase)]


class FakePolicy:
    """A controller that always commands ``POLICY`` (chunks of 8), noting when it is asked."""

    def __init__(self, log: Timeline) -> None:
        self.log, self.started = log, []

    def start(self, slot: int, job: Job) -> None:
        self.log.phase = "policy"
        self.log.note("start")
        self.started.append(job)

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        self.log.note("act")
        return np.tile(POLICY.astype(np.float32), (1, 8, 1))

    def finish(self, slot: int) -> None:
        return None

    def current_skill(self, slot: int) -> None:
        return None


def unique_virtual_channel() -> str:
    return f"operator-test-{uuid.uuid4().hex[:12]}"


def received_joint_commands(firmware: PiperFirmware) -> np.ndarray:
    """Every joint command (0x155..0x157) the emulated arm received, in order, as 6 angles (rad)."""
    latest: dict[int, tuple[float, ...]] = {}
    commands = []
    for frame in firmware.frame_log:
        if frame.direction == "rx" and frame.arbitration_id in codec.ID_JOINT_COMMAND:
            latest[frame.arbitration_id] = codec.decode_command(frame.arbitration_id, frame.data).positions_rad
            if frame.arbitration_id == codec.ID_JOINT_COMMAND[-1]:
                commands.append([p for i in codec.ID_JOINT_COMMAND for p in latest[i]])
    return np.array(commands)


def vector(action: dict[str, float]) -> np.ndarray:
    return np.array([action[f"joint_{j}.pos"] for j in range(1, 7)] + [action["gripper.pos"]])


@dataclass
class Bench:
    clock: SimulatedClock
    follower: PiperEmulator
    leader: PiperEmulator | None
    buses: list[can.BusABC]
    log: Timeline
    made: list[RobotBackend] = field(default_factory=list)


@pytest.fixture
def bench(monkeypatch, tmp_path, keys) -> Iterator[Callable[..., tuple[RobotBackend, Bench]]]:
    """``bench(teleop, script, rest_time_s, horizon, on_fault)`` -> a ``RobotBackend`` on the simulated arm(s), its
    operator the real ``KeyboardOperator`` played by a ``Person``, the robot and teleoperator recorded."""
    clock = SimulatedClock()
    monkeypatch.setattr(devices_module, "make_robot_from_config", lambda config: PiperFollower(config, clock))
    monkeypatch.setattr(devices_module, "make_teleoperator_from_config", lambda config: PiperLeader(config, clock))
    # The backend's control tick (``precise_sleep`` until 1/fps after ``time.perf_counter()`` at its start)
    # on the simulated clock: the arms move while it sleeps.
    monkeypatch.setattr(robot_module, "precise_sleep", clock.sleep)
    monkeypatch.setattr(robot_module, "time", SimpleNamespace(perf_counter=clock.monotonic))
    monkeypatch.setattr("sys.argv", ["pytest"])  # the follower looks for a recorded motion mode there
    follower_channel, leader_channel = unique_virtual_channel(), unique_virtual_channel()
    buses = [can.Bus(interface="virtual", channel=follower_channel)]
    follower = PiperEmulator(buses[0], EmulatorConfig(log_size=200_000), clock)
    clock.every(follower.firmware.config.period_s, follower.step)
    state = Bench(clock, follower, None, buses, Timeline(follower.firmware))

    def make(
        teleop: bool, script: dict, rest_time_s: float, horizon: int, on_fault: str = "stop"
    ) -> tuple[RobotBackend, Bench]:
        if teleop and state.leader is None:
            buses.append(can.Bus(interface="virtual", channel=leader_channel))
            state.leader = PiperEmulator(buses[-1], EmulatorConfig(role="leader"), clock)  # the default sines
            clock.every(state.leader.firmware.config.period_s, state.leader.step)
        config = RobotWorldConfig(
            robot=PiperFollowerConfig(
                interface="virtual", channel=follower_channel, calibration_dir=tmp_path, motion_mode="position"
            ),
            teleop=PiperLeaderConfig(interface="virtual", channel=leader_channel, calibration_dir=tmp_path)
            if teleop
            else None,
            operator=OperatorConfig(
                type="keyboard", fps=FPS, rest_time_s=rest_time_s, rest_pose=list(REST), on_fault=on_fault
            ),
            display_data=False,
        )
        world = config.build(TASK, None, tmp_path / "out")
        backend = RobotBackend(Devices(config.robot, config.teleop), config.operator, world.journal(), (), FPS, horizon)
        state.made.append(backend)
        backend.operator = Person(backend.operator, keys[-1], script, state.log)
        record_calls(backend, state.log)
        return backend, state

    yield make
    for backend in state.made:
        backend.close()
    for bus in buses:
        bus.shutdown()


def record_calls(backend: RobotBackend, log: Timeline) -> None:
    """Note every action sent to the follower and every action read from the leader (the devices' own
    methods run)."""
    send_action = backend.robot.send_action

    def send(action: dict[str, float]) -> dict[str, float]:
        log.note("send", action=vector(action))
        sent = send_action(action)
        log.events[-1].sent = vector(sent)
        return sent

    backend.robot.send_action = send
    if backend.teleop is not None:
        get_action = backend.teleop.get_action

        def read() -> dict[str, float]:
            action = get_action()
            log.note("leader", action=vector(action))
            return action

        backend.teleop.get_action = read


def journaled(out: Path) -> dict[str, dict[str, Any]]:
    return {p.stem: EpisodeJournal.load(p) for p in sorted((out / "robot_journal" / "episodes").glob("*/*.npz"))}


def test_the_keys_label_robot_episodes_and_q_stops_where_a_rerun_resumes(bench, capsys):
    """Discard (the attempt is repeated with its own prompt), failure, success, no verdict by the time limit
    (a failure), then q while the policy runs: the command stops, that episode is not kept, and a rerun of the
    same jobs replays the journaled episodes and runs only that one."""
    script = {
        "3/1/0": (2, "enter", 1, "d"),
        "3/1/1": (1, "space", 2, "f"),
        "3/2/0": (1, "n", 0, "s"),
        "5/1/0": (1, "right", None, None),
        "4/1/0": (1, "enter", 1, "q"),
    }
    horizon = 6
    backend, state = bench(teleop=False, script=script, rest_time_s=0.3, horizon=horizon)
    jobs = [Job(TASK, 3), Job(TASK, 3), Job(TASK, 5), Job(TASK, 4)]
    results = []
    with pytest.raises(OperatorQuit, match=f"^{QUIT}$"):
        for index, trace in backend.run(jobs, FakePolicy(state.log)):
            results.append((index, trace.job.init_seed, trace.success, trace.length))
    assert results == [(0, 3, False, 3), (1, 3, True, 1), (2, 5, False, horizon)]
    assert backend.operator.polls == {k: v[0] + 1 for k, v in script.items()}  # each started on its press
    out = capsys.readouterr().out
    prompts = [line.split(";")[0] for line in out.splitlines() if line.startswith(">>> ")]
    assert prompts == [
        ">>> state 3, attempt 1 of 2 — arrange a new scene",
        ">>> state 3, attempt 1 of 2 (try 2) — arrange it as before",
        ">>> state 3, attempt 2 of 2 — arrange it as before",
        ">>> state 5, attempt 1 of 1 — arrange a new scene",
        ">>> state 4, attempt 1 of 1 — arrange a new scene",
    ]
    assert "discarded: state 3, attempt 1 (operator)" in out
    assert "state 3, attempt 1: failure after 3 steps" in out and "state 3, attempt 2: success after 1 steps" in out
    out_dir = state.made[0].journal.root.parent
    episodes = journaled(out_dir)
    assert {k: (bool(v["success"]), int(v["length"])) for k, v in episodes.items()} == {
        "0000003_001": (False, 3),
        "0000003_002": (True, 1),
        "0000005_001": (False, horizon),
    }
    records = {p.stem: json.loads(p.read_text()) for p in (out_dir / "robot_journal" / "records").glob("*/*.json")}
    assert records == {"0000003_001": {"discarded": ["operator"]}}
    backend.close()

    rerun, _ = bench(teleop=False, script={**script, "4/1/0": (1, "enter", 2, "s")}, rest_time_s=0.3, horizon=6)
    policy = FakePolicy(state.log)
    replayed = [(i, t.job.init_seed, t.success, t.length) for i, t in rerun.run(jobs, policy)]
    assert replayed == [*results, (3, 4, True, 3)]
    assert policy.started == [Job(TASK, 4)]  # only the stopped episode ran on the arm again
    out = capsys.readouterr().out
    assert "resuming: 3 episodes on disk; next: state 4, attempt 1" in out
    assert [line.split(";")[0] for line in out.splitlines() if line.startswith(">>> ")] == [
        ">>> state 4, attempt 1 of 1 — arrange a new scene"
    ]
    assert rerun.operator.polls == {"4/1/0": 2}


def test_teleop_reset_the_arm_follows_the_leader_then_returns_to_rest_before_the_policy(bench):
    """With ``--teleop.type=piper_leader``: while the person arranges the scene (2 s, then Enter) the follower
    is commanded the leader's joints (read back from the emulated arm) and follows it; on Enter it is driven
    back to the rest pose over ``rest_time_s``; only then does the policy start and act; s ends the episode."""
    arrange_ticks, rest_time_s = 2 * FPS, 1.0
    rest_steps = round(rest_time_s * FPS)
    script = {"0/1/0": (arrange_ticks - 1, "enter", 2, "s")}
    backend, state = bench(teleop=True, script=script, rest_time_s=rest_time_s, horizon=30)
    [(_, trace)] = list(backend.run([Job(TASK, 0)], FakePolicy(state.log)))
    state.clock.sleep(0.02)  # the arm handles the frames of the last tick (the verdict ended it: no tick sleep)
    assert trace.success and trace.length == 3
    log, rest = state.log, np.array(REST)
    kinds = {phase: [e.kind for e in log.events if e.phase == phase] for phase in ("before", "return", "policy")}
    # Before Enter: the move to rest, then per tick one read of the leader, that action sent, one poll.
    assert kinds["before"] == ["send"] * rest_steps + ["leader", "send", "poll"] * arrange_ticks
    # After Enter: the move back to rest and nothing else (the leader is not read); then the policy.
    assert kinds["return"] == ["send"] * rest_steps
    assert kinds["policy"] == ["start", "act", "send", "send", "send"]

    sends = log.of("send")
    arranged = sends[rest_steps : rest_steps + arrange_ticks]
    leader = log.of("leader")
    for read, sent in zip(leader, arranged, strict=True):
        np.testing.assert_array_equal(sent.action, read.action)
    wanted, sent = np.array([e.action for e in leader]), np.array([e.sent for e in arranged])
    assert np.ptp(wanted[:, :6], axis=0).max() > 0.1, "the leader hardly moved"
    # The follower clamps each command to 0.2 around where it is, catches up, and from then on it is commanded
    # the leader's pose itself.
    assert np.abs(wanted[0] - rest).max() > 0.3 and np.abs(sent[0] - rest).max() <= 0.2 + 1e-4
    tracking = np.all(np.abs(sent - wanted) < 1e-4, axis=1)
    caught_up = int(np.argmax(tracking))
    assert 0 < caught_up <= FPS and tracking[caught_up:].all(), tracking.astype(int)
    # Read back from the emulated arm: it received exactly the commands sent, in order, and no others.
    received = received_joint_commands(state.follower.firmware)
    np.testing.assert_allclose(received, [e.sent[:6] for e in sends], atol=1e-4)
    last = log.of("poll")[-1]  # the arm when Enter was pressed: with the leader, well away from rest
    assert np.abs(last.joints - wanted[-1, :6]).max() < 0.05 and abs(last.gripper - wanted[-1, 6]) < 0.005
    assert np.abs(last.joints - rest[:6]).max() > 0.3

    # On Enter: a straight, even move from where the arm is to the rest pose, ending on it.
    back = np.array([e.action for e in log.of("send", "return")])
    steps = np.diff(back, axis=0)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[0], steps.shape), atol=1e-9)
    np.testing.assert_allclose(back[-1], rest, atol=1e-12)
    np.testing.assert_allclose(back[0] - steps[0], np.append(last.joints, last.gripper), atol=0.02)

    # The policy is asked only once the arm is at rest, and none of its actions reached the arm before.
    [act] = log.of("act")
    np.testing.assert_allclose(act.joints, rest[:6], atol=1e-3)
    assert abs(act.gripper - rest[6]) < 1e-3
    for e in sends[: rest_steps * 2 + arrange_ticks]:
        assert not np.allclose(e.action, POLICY, atol=1e-3) and not np.allclose(e.targets, POLICY[:6], atol=1e-3)
    for e in log.of("send", "policy"):
        np.testing.assert_allclose(e.sent, POLICY, atol=1e-6)
    np.testing.assert_allclose(state.follower.firmware.targets_rad, POLICY[:6], atol=1e-4)


def test_a_leader_that_goes_silent_while_arranging_ends_the_command_and_nothing_more_reaches_the_arm(bench):
    """The leader's firmware stops talking one second into arranging: its link trips, the episode in flight is
    discarded with the reason, the command ends with one line naming the teleoperator, the policy never
    starts, and the follower receives no command after the last pose read from the leader."""
    script = {"0/1/0": (10 * FPS, "enter", None, None)}  # Enter would come only after 10 s
    backend, state = bench(teleop=True, script=script, rest_time_s=0.3, horizon=30)
    person_ready = backend.operator.ready

    def ready(info: EpisodeInfo) -> bool:
        if backend.operator.polls.get(info.key, 0) == FPS:
            state.leader.firmware.silent = True
            state.log.note("silent")
        return person_ready(info)

    backend.operator.ready = ready
    fault = "^error: teleoperator fault in state 0, attempt 1: TeleopFault: PiperLeader: FeedbackStaleError"
    with pytest.raises(ArmFault, match=fault):
        list(backend.run([Job(TASK, 0)], FakePolicy(state.log)))
    received = len(received_joint_commands(state.follower.firmware))
    state.clock.sleep(1.0)  # the arms run on; nothing more is sent
    assert len(received_joint_commands(state.follower.firmware)) == received
    kinds = [e.kind for e in state.log.events]
    silent = kinds.index("silent")
    assert "start" not in kinds and "act" not in kinds
    # After the leader fell silent: three more ticks read its last pose and send it; the fourth read, 133 ms on
    # (the first past its link's 100 ms watchdog limit), trips, and nothing is sent. (Until d16bab7, which also
    # watches the leader's gripper frame, the third read tripped; left for the next session to explain.)
    after = kinds[silent + 1 :]
    assert after == ["poll"] + ["leader", "send", "poll"] * 3
    assert received == after.count("send") + kinds[:silent].count("send")  # every send reached the arm
    out_dir = state.made[0].journal.root.parent
    assert journaled(out_dir) == {}
    [record] = [json.loads(p.read_text()) for p in (out_dir / "robot_journal" / "records").glob("*/*.json")]
    [reason] = record["discarded"]
    assert reason.startswith("TeleopFault: PiperLeader: FeedbackStaleError"), reason


def test_with_on_fault_wait_a_silent_leader_is_reconnected_and_the_attempt_repeated(bench, capsys):
    """``--operator.on_fault=wait``: the same fault disconnects both devices; once the operator confirms (the
    leader talks again), both are connected anew and the attempt is repeated as its second try, to a verdict."""
    script = {"0/1/0": (10 * FPS, "enter", None, None), "0/1/1": (2, "enter", 1, "s")}
    backend, state = bench(teleop=True, script=script, rest_time_s=0.3, horizon=30, on_fault="wait")
    person, first_leader = backend.operator, backend.teleop

    def ready(info: EpisodeInfo) -> bool:
        if info.key == "0/1/0" and person.polls.get(info.key, 0) == FPS:
            state.leader.firmware.silent = True
        return Person.ready(person, info)

    def wait_for_recovery(info: EpisodeInfo) -> None:
        assert not backend.robot.is_connected and not first_leader.is_connected  # both let go
        state.leader.firmware.silent = False  # the operator fixed the leader's cable
        state.clock.sleep(0.1)

    person.ready, person.wait_for_recovery = ready, wait_for_recovery
    [(_, trace)] = list(backend.run([Job(TASK, 0)], FakePolicy(state.log)))
    assert trace.success and trace.length == 2
    assert backend.teleop is not first_leader and backend.teleop.is_connected
    out = capsys.readouterr().out
    assert "teleoperator fault in state 0, attempt 1: TeleopFault: PiperLeader: FeedbackStaleError" in out
    assert "reconnected; state 0, attempt 1 again" in out
    assert person.polls == {"0/1/0": FPS + 4, "0/1/1": 3}  # the first try: as in the test above


def test_a_malformed_operator_script_is_one_line_before_any_work(tmp_path):
    """A script that is not JSON, or not the operator's layout, is one ``UsageError`` from the settings' check,
    before a robot is touched (it was a traceback once the run reached the operator)."""
    for text in ("{not json", '{"keys": {"0/0/0": 5}}', '{"targets": ["joint_1.pos"]}', '{"tolerance": "wide"}'):
        script = tmp_path / "script.json"
        script.write_text(text)
        with pytest.raises(UsageError, match=f"^{script} is not an operator script"):
            OperatorConfig(type="scripted", script=script).validate()
    script.write_text(json.dumps({"keys": {"0/0/0": [5, "success"]}, "targets": {"default": {"joint_1.pos": 0.1}}}))
    OperatorConfig(type="scripted", script=script).validate()  # a well-formed one passes
