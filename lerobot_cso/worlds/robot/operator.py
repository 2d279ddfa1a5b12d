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
* :class:`TwinOperator` (``--operator.type=twin``): the PiPER's physics twin runs the collection unattended. It
  places the scene's objects for state ``i`` from seed ``scene_seed + i`` (every attempt of a state alike) and takes
  the scene's own success as the verdict; no success by the time limit is a failure. The twin is a
  ``piper-emulator --physics`` process, whose world state it reads on ``--operator.state_group`` /
  ``--operator.state_port``, or the robot itself when that holds it in process (``piper_twin_sim``: its ``plant``).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

from lerobot_cso.errors import UsageError, check_number

Verdict = Literal["success", "failure", "discard"]
VERDICTS: tuple[str, ...] = ("success", "failure", "discard")
OPERATORS: tuple[str, ...] = ("keyboard", "scripted", "twin")
ON_FAULT: tuple[str, ...] = ("stop", "wait")
POLL_S = 0.05  # how often a waiting operator is polled
TWIN_WAIT_S = 5.0  # how long the twin operator waits for the twin's first state and for a placement
TWIN_MAX_AGE_S = 1.0  # a twin state older than this: the emulator stopped
TWIN_SETTLE_S = 0.3  # the twin's time from placing the objects to the start (they come to rest, the arm settles)


class OperatorQuit(SystemExit):
    """The operator asked to stop; the command ends with this one-line message (exit code 1)."""


class TwinNotFound(SystemExit):
    """``--operator.type=twin`` heard no twin; the command ends with this one-line message (exit code 1)."""


@dataclass
class OperatorConfig:
    """``--operator.*``: who labels the episodes, and the timing of a robot episode."""

    type: str = "keyboard"  # keyboard | scripted | twin
    script: Path | None = None  # scripted: the JSON file of targets and key presses
    # twin: the world state of piper-emulator --physics (its --state-group / --state-port); state i is placed
    # from seed scene_seed + i.
    state_group: str = "239.74.1.1"
    state_port: int = 43200
    scene_seed: int = 0
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
        if self.type == "scripted":
            ScriptedOperator(Path(self.script))  # a malformed script is one line before any work
        check_number("operator.state_port", self.state_port, gt=0, lt=65535)
        check_number("operator.scene_seed", self.scene_seed, ge=0)
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
        try:
            data = json.loads(Path(script).read_text())
            self.tolerance = float(data.get("tolerance", 0.05))
            self.targets: dict[str, dict[str, float]] = {
                state: {name: float(v) for name, v in target.items()}
                for state, target in data.get("targets", {}).items()
            }
            self.keys: dict[str, tuple[int, str]] = {k: (int(t), v) for k, (t, v) in data.get("keys", {}).items()}
            self.gates: dict[str, str] = {k: str(v) for k, v in data.get("gates", {}).items()}
        except (OSError, ValueError, TypeError, AttributeError) as e:  # unreadable, not JSON, or not this layout
            raise UsageError(
                f"{script} is not an operator script ({type(e).__name__}: {e}); see its layout in "
                "lerobot_cso/worlds/robot/operator.py, ScriptedOperator"
            ) from None
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


class TwinOperator:
    """The PiPER twin's scene arranges and labels: objects placed by seed, the scene's success as the verdict.

    ``robot()`` is the robot being run: one that holds the twin (``plant``, a ``piper_twin.plant.TwinPlant``, and
    ``pass_time(seconds)``) is asked directly; otherwise the twin is another process, reached over its state channel
    (``piper_twin.state_channel``). The twin package is imported here, never by other worlds."""

    def __init__(self, group: str, port: int, scene_seed: int, robot: Callable[[], Any]) -> None:
        self.robot, self.scene_seed = robot, scene_seed
        self._seed: int | None = None  # the seed the episode being run was placed from
        self._recovering: EpisodeInfo | None = None  # the try whose fault was already answered by a reconnect
        self.receiver: Any = None
        if self._plant() is not None:
            return
        try:
            from piper_twin.state_channel import StateReceiver
        except ImportError as exc:
            raise UsageError(
                f"--operator.type=twin needs the twin extra: pip install -e './hardware[twin]' ({exc})"
            ) from None
        self.receiver = StateReceiver(group, port)
        if self.receiver.wait(TWIN_WAIT_S) is None:
            self.receiver.close()
            raise TwinNotFound(
                f"error: no PiPER twin state on {group}:{port} within {TWIN_WAIT_S:g} s; start piper-emulator "
                f"--physics --scene=<task> --state-group={group} --state-port={port}"
            )

    def _plant(self) -> Any:
        """The twin in this process, or None."""
        return getattr(self.robot(), "plant", None)

    def ready(self, episode: EpisodeInfo) -> bool:
        """Place the objects for the state's seed and let the twin run ``TWIN_SETTLE_S`` before the start."""
        seed, plant = self.scene_seed + episode.state, self._plant()
        if plant is not None:
            plant.place(seed)
            self.robot().pass_time(TWIN_SETTLE_S)
            scene = plant.scene.name
        else:
            placed = self.receiver.place(seed, timeout_s=TWIN_WAIT_S)
            deadline = time.monotonic() + TWIN_WAIT_S
            while self.receiver.latest().time_s < placed.time_s + TWIN_SETTLE_S:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the twin's time did not advance {TWIN_SETTLE_S} s in {TWIN_WAIT_S:g} s")
                time.sleep(0.005)
            scene = placed.scene
        self._seed = seed
        print(f">>> {episode.prompt()}: the twin placed {scene} from seed {seed}", flush=True)
        return True

    def verdict(self, episode: EpisodeInfo, observation: dict[str, Any], tick: int) -> Verdict | None:
        plant = self._plant()
        if plant is not None:
            return "success" if plant.succeeded() else None
        snapshot = self.receiver.latest()
        age = time.time() - snapshot.wall_time_s
        if age > TWIN_MAX_AGE_S:
            raise TimeoutError(f"no PiPER twin state for {age:.2f} s (limit {TWIN_MAX_AGE_S} s): the emulator stopped")
        if snapshot.seed != self._seed:  # (a repeat of our own request may place the same seed again)
            raise RuntimeError(
                f"the twin's objects were placed for seed {snapshot.seed} during this episode of seed {self._seed}: "
                "something else arranges the scene"
            )
        return "success" if snapshot.success else None

    def wait_for_recovery(self, episode: EpisodeInfo) -> None:
        """Nobody can recover the arm: reconnect once (``--robot.recovery`` says how a faulted arm is enabled),
        then stop."""
        if self._recovering == episode:
            raise OperatorQuit(
                f"error: the twin did not reconnect after the fault in state {episode.state}, attempt "
                f"{episode.attempt} (--robot.recovery=reset resets a faulted arm); rerun to resume"
            )
        self._recovering = episode
        print(">>> unattended: reconnecting once", flush=True)

    def close(self) -> None:
        if self.receiver is not None:
            self.receiver.close()


def make_operator(config: OperatorConfig, robot: Callable[[], Any] = lambda: None) -> Operator:
    """The operator ``config`` names; ``robot()`` is the robot being run (the twin operator may ask it)."""
    if config.type == "scripted":
        return ScriptedOperator(Path(config.script))
    if config.type == "twin":
        return TwinOperator(config.state_group, config.state_port, config.scene_seed, robot)
    return KeyboardOperator()
