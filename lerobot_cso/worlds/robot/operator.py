"""The person at the robot: arranges each initial state and labels each episode.

A robot rollout (:mod:`lerobot_cso.worlds.robot.world`) asks its :class:`Operator`: during the arrange phase, whether
the scene is ready (:meth:`Operator.ready`); at every control tick of the policy, whether the episode has a
verdict yet (:meth:`Operator.verdict`): ``success``, ``failure`` or ``discard`` (not counted, the attempt is
repeated), no verdict by the time limit being a failure; and with ``--operator.on_fault=wait``, after a robot
fault, when the arm is recovered and may be connected again (:meth:`Operator.wait_for_recovery`).

* :class:`KeyboardOperator` (``--operator.type=keyboard``): LeRobot's key listener (the one ``lerobot-record``
  uses: pynput on a desktop, the terminal otherwise). Enter / space / n / right arrow: the scene is arranged,
  start (after a fault: the arm is recovered, reconnect); s: success; f: failure; d: discard; q / Esc: stop
  (the episode in flight is discarded, a rerun resumes at it). A verdict key pressed after the start key, while
  the arm returns to rest from a teleop reset, is kept and ends the episode at its first tick.
* :class:`ScriptedOperator` (``--operator.type=scripted --operator.script=FILE.json``): a stand-in for tests
  and dry runs. Arranging takes no time; key presses come from the script, keyed by
  ``"<state>/<attempt>/<retry>"`` (attempt from 1, retry = how many times this attempt was discarded before)
  as ``[tick, verdict]``; without a key, the last tick is judged by a rule on the measured pose: success when
  every value named in the state's target is within ``tolerance`` of it. ``gates`` hold an episode in its
  arrange phase until a file exists (a test stops or faults the command there); a gate keyed
  ``"recover/<state>/<attempt>/<retry>"`` holds the wait after a fault of that try (no such gate: stop).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

from lerobot_cso.errors import UsageError, check_number

Verdict = Literal["success", "failure", "discard"]
VERDICTS: tuple[str, ...] = ("success", "failure", "discard")
OPERATORS: tuple[str, ...] = ("keyboard", "scripted")
ON_FAULT: tuple[str, ...] = ("stop", "wait")
POLL_S = 0.05  # how often a waiting operator is polled


class OperatorQuit(SystemExit):
    """The operator asked to stop; the command ends with this one-line message (exit code 1)."""


@dataclass
class OperatorConfig:
    """``--operator.*``: who labels the episodes, and the timing of a robot episode."""

    type: str = "keyboard"  # keyboard | scripted
    script: Path | None = None  # scripted: the JSON file of targets and key presses
    episode_time_s: float = 30.0  # the policy's time limit per episode (no verdict by then: failure)
    rest_time_s: float = 3.0  # duration of the smooth move to the rest pose before each episode
    # The rest pose in the robot's action order (PiPER: joint_1..joint_6 in rad, gripper in m);
    # null: the pose the robot was in when it connected.
    rest_pose: list[float] | None = None
    # Control frequency; null: the fps of the dataset the policy was trained on (its train_config.json).
    fps: int | None = None
    # After a robot fault (the episode is discarded): "stop" ends the command (rerun it to resume); "wait" lets
    # go of the robot, waits for the operator to recover it, reconnects and repeats the attempt.
    on_fault: str = "stop"

    def validate(self) -> None:
        if self.type not in OPERATORS:
            raise UsageError(f"operator.type must be one of {', '.join(OPERATORS)}, got '{self.type}'")
        if self.type == "scripted" and (self.script is None or not Path(self.script).is_file()):
            raise UsageError(f"--operator.type=scripted needs --operator.script=<a JSON file>, got {self.script}")
        check_number("operator.episode_time_s", self.episode_time_s, gt=0)
        check_number("operator.rest_time_s", self.rest_time_s, ge=0)
        if self.fps is not None and self.fps < 1:
            raise UsageError(f"operator.fps must be >= 1, got {self.fps}")
        if self.on_fault not in ON_FAULT:
            raise UsageError(f"operator.on_fault must be one of {', '.join(ON_FAULT)}, got '{self.on_fault}'")


@dataclass(frozen=True)
class EpisodeInfo:
    """Which episode the operator is asked about."""

    state: int  # the arranged state's index
    attempt: int  # 1 .. attempts
    attempts: int  # episodes from this state in this request
    retry: int  # how many earlier tries of this attempt were discarded
    horizon: int  # control ticks before the time limit

    @property
    def key(self) -> str:
        """``<state>/<attempt>/<retry>``: how a script names this try."""
        return f"{self.state}/{self.attempt}/{self.retry}"

    def prompt(self) -> str:
        scene = "arrange a new scene" if self.attempt == 1 and self.retry == 0 else "arrange it as before"
        again = f" (try {self.retry + 1})" if self.retry else ""
        return f"state {self.state}, attempt {self.attempt} of {self.attempts}{again} — {scene}"


class Operator(Protocol):
    """Arranges scenes and labels episodes."""

    def ready(self, episode: EpisodeInfo) -> bool:
        """Polled every tick of the arrange phase: True once the scene is arranged."""

    def verdict(self, episode: EpisodeInfo, observation: dict[str, Any], tick: int) -> Verdict | None:
        """Polled every control tick while the policy runs (``tick`` from 0)."""

    def wait_for_recovery(self, episode: EpisodeInfo) -> None:
        """Block until the operator has recovered the arm after a fault of ``episode`` (nothing is connected)."""

    def close(self) -> None: ...


class KeyboardOperator:
    """Keys through LeRobot's listener (``lerobot.utils.keyboard_input.create_key_listener``)."""

    KEYS = {"enter": "ready", "space": "ready", "n": "ready", "right": "ready", "s": "success"}
    KEYS |= {"f": "failure", "d": "discard", "q": "quit", "esc": "quit"}
    HELP = "Enter/n = arranged, start; s = success, f = failure, d = discard; q/Esc = stop"

    def __init__(self) -> None:
        from lerobot.utils.keyboard_input import create_key_listener

        self._pending: str | None = None
        self._lock = threading.Lock()  # the listener thread writes _pending while the control loop takes it
        self._prompted: EpisodeInfo | None = None
        self.listener = create_key_listener(self._on_key, controls_help=self.HELP)
        if self.listener is None:
            raise UsageError(
                "no keyboard available (no display and stdin is not a terminal): run in a terminal, "
                "or use --operator.type=scripted"
            )

    def _on_key(self, name: str) -> None:
        with self._lock:
            self._pending = self.KEYS.get(name.lower(), self._pending)

    def _clear(self) -> None:
        with self._lock:
            self._pending = None

    def _take(self, wanted: tuple[str, ...]) -> str | None:
        with self._lock:
            key, self._pending = self._pending, None
        if key == "quit":
            raise OperatorQuit("stopped by the operator; rerun the same command to resume")
        return key if key in wanted else None

    def ready(self, episode: EpisodeInfo) -> bool:
        if self._prompted != episode:
            self._prompted = episode
            self._clear()
            print(f"\n>>> {episode.prompt()}; then press Enter ({self.HELP})", flush=True)
        return self._take(("ready",)) is not None

    def verdict(self, episode: EpisodeInfo, observation: dict[str, Any], tick: int) -> Verdict | None:
        return self._take(VERDICTS)  # type: ignore[return-value]

    def wait_for_recovery(self, episode: EpisodeInfo) -> None:
        self._prompted = None
        self._clear()
        print(">>> once the arm is safe and recovered, press Enter to reconnect (q/Esc = stop)", flush=True)
        while self._take(("ready",)) is None:
            time.sleep(POLL_S)

    def close(self) -> None:
        self.listener.stop()


class ScriptedOperator:
    """Deterministic labels for tests: scripted key presses, else a pose rule judged at the last tick.

    Script: ``{"tolerance": 0.05, "targets": {"<state>": {"joint_1.pos": 0.1, ...}, "default": {...}},
    "keys": {"<state>/<attempt>/<retry>": [tick, "success" | "failure" | "discard"]},
    "gates": {"<state>/<attempt>/<retry>": "<file that must exist before the episode starts>"}}``.
    """

    def __init__(self, script: Path) -> None:
        data = json.loads(Path(script).read_text())
        self.tolerance = float(data.get("tolerance", 0.05))
        self.targets: dict[str, dict[str, float]] = data.get("targets", {})
        self.keys: dict[str, tuple[int, str]] = {k: (int(t), v) for k, (t, v) in data.get("keys", {}).items()}
        self.gates: dict[str, str] = data.get("gates", {})
        bad = [v for _, v in self.keys.values() if v not in VERDICTS]
        if bad:
            raise UsageError(f"{script}: key verdicts must be one of {', '.join(VERDICTS)}, got {bad}")

    def ready(self, episode: EpisodeInfo) -> bool:
        gate = self.gates.get(episode.key)
        if gate is not None and not Path(gate).exists():
            return False
        print(f">>> {episode.prompt()} (scripted)", flush=True)
        return True

    def verdict(self, episode: EpisodeInfo, observation: dict[str, Any], tick: int) -> Verdict | None:
        key = self.keys.get(episode.key)
        if key is not None and key[0] == tick:
            return key[1]  # type: ignore[return-value]
        if tick < episode.horizon - 1:
            return None
        target = self.targets.get(str(episode.state), self.targets.get("default"))
        if target is None:
            return None
        close = all(abs(float(observation[k]) - v) <= self.tolerance for k, v in target.items())
        return "success" if close else None

    def wait_for_recovery(self, episode: EpisodeInfo) -> None:
        gate = self.gates.get(f"recover/{episode.key}")
        if gate is None:
            raise OperatorQuit(f"error: the operator script has no 'recover/{episode.key}' gate; rerun to resume")
        while not Path(gate).exists():
            time.sleep(POLL_S)
        print(">>> recovered (scripted)", flush=True)

    def close(self) -> None:
        pass


def make_operator(config: OperatorConfig) -> Operator:
    """The operator ``config`` names."""
    if config.type == "scripted":
        return ScriptedOperator(Path(config.script))
    return KeyboardOperator()
