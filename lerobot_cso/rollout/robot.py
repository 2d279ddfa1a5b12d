"""Rollouts on a LeRobot robot with an operator in the loop: the robot world and its backend.

``--robot.type=...`` (any LeRobot ``Robot``, cameras included; optional ``--teleop.type=...`` for the reset
phase) makes a rollout stage run here instead of in simulation. Initial states are the arranged-state indices
the operator is prompted with (R-SFT: 0, 1, ...; SPO: the group cursor; evaluation: trial 0 .. N-1).

One episode (:meth:`RobotBackend.run`): the arm moves smoothly to the rest pose; the operator arranges the
scene (with a teleoperator the arm follows it meanwhile, then returns to the rest pose); the policy runs at
the world's fps, one action of its 8-action chunk per control tick, until the operator's verdict or the time
limit (a failure). A discarded episode is repeated. A fault of the robot (e-stop, driver or firmware fault,
stale feedback, a camera that fails) or of the teleoperator while it drives the arm discards the episode in
flight, and nothing more is sent to the arm: the command ends with one line naming the device
(:class:`ArmFault`), or with ``--operator.on_fault=wait`` both devices are disconnected, the operator recovers
the faulted one, and both are connected again (their own ``connect``, as a rerun would) before the attempt is
repeated. A robot or teleoperator that does not connect ends the command with one line too.

**Durability.** Every finished episode is written to ``<output_dir>/robot_journal`` (an
:class:`~lerobot_cso.durable.EpisodeJournal`, one ``.npz`` per episode with the controller's record) the moment
it ends, before the stage sees it; discarded tries are recorded there too. A rerun of the same command replays
the journaled episodes of each request instead of running them, so R-SFT, SPO and evaluation resume at the
state and attempt that come next, with nothing lost or duplicated.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType
from lerobot.robots import Robot, make_robot_from_config
from lerobot.teleoperators import Teleoperator, make_teleoperator_from_config
from lerobot.utils.constants import OBS_IMAGES, OBS_STATE
from lerobot.utils.robot_utils import precise_sleep

from lerobot_cso.durable import EpisodeJournal, read_json
from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.backend import ActiveSkill, Controller, Job, Trace
from lerobot_cso.rollout.operator import EpisodeInfo, Operator, make_operator

if TYPE_CHECKING:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.robots.config import RobotConfig

    from lerobot_cso.rollout_stage import RolloutStageConfig

log = logging.getLogger(__name__)

JOURNAL_DIR = "robot_journal"
EVAL_STATES = 1000  # evaluation trials per run are numbered 0 .. N-1 (the paper: 20)


class ArmFault(SystemExit):
    """The robot did not connect or failed during an episode; the command ends with this one-line message
    (exit code 1)."""


class TeleopFault(RuntimeError):
    """The teleoperator failed while the arm followed it (the scene-arranging phase)."""


def _reason(exc: BaseException) -> str:
    """``exc`` as one line: its type and message."""
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")


def state_keys(robot: Robot) -> list[str]:
    """The scalar observations of ``robot`` in order: ``observation.state`` as ``lerobot-record`` writes it."""
    return [k for k, v in robot.observation_features.items() if not isinstance(v, tuple)]


def camera_shapes(robot: Robot) -> dict[str, tuple[int, ...]]:
    """Camera name → (H, W, 3) of ``robot``."""
    return {k: v for k, v in robot.observation_features.items() if isinstance(v, tuple)}


def check_policy_fits(robot_config: RobotConfig, policy: PreTrainedConfig) -> None:
    """Raise ``UsageError`` unless the policy reads exactly what the robot observes and commands what it takes."""
    quiet = logging.root.manager.disable
    logging.disable(logging.WARNING)  # what a robot logs when built is logged again by the one that connects
    try:
        robot = make_robot_from_config(robot_config)  # builds the object only: nothing is connected
    finally:
        logging.disable(quiet)
    name = robot_config.type
    inputs, outputs = policy.input_features, policy.output_features
    states, actions, cameras = state_keys(robot), list(robot.action_features), camera_shapes(robot)
    if OBS_STATE in inputs and tuple(inputs[OBS_STATE].shape) != (len(states),):
        raise UsageError(
            f"the policy reads {OBS_STATE} of shape {tuple(inputs[OBS_STATE].shape)}, but robot {name} observes "
            f"{len(states)} values ({', '.join(states)}): it was trained on other features"
        )
    if "action" in outputs and tuple(outputs["action"].shape) != (len(actions),):
        raise UsageError(
            f"the policy outputs actions of shape {tuple(outputs['action'].shape)}, but robot {name} takes "
            f"{len(actions)} ({', '.join(actions)}): it was trained on other features"
        )
    for key, feature in inputs.items():
        if feature.type != FeatureType.VISUAL:
            continue
        cam = key.removeprefix(f"{OBS_IMAGES}.")
        if cam not in cameras:
            have = ", ".join(cameras) or "none"
            raise UsageError(f"the policy reads camera '{cam}', but robot {name} has cameras: {have} (--robot.cameras)")
        c, h, w = feature.shape
        if tuple(cameras[cam]) != (h, w, c):
            raise UsageError(
                f"the policy reads camera '{cam}' as {h}x{w}x{c}, but robot {name} gives {cameras[cam]} "
                f"(set --robot.cameras.{cam}.height/width)"
            )


def policy_fps(policy: PreTrainedConfig) -> int | None:
    """The control fps a policy was trained at: its ``lerobot-train`` dataset's (``train_config.json``), or for
    an R-SFT / SPO checkpoint the fps its robot rollouts ran at (``../robot_journal/spec.json``)."""
    path = getattr(policy, "pretrained_path", None)
    if not path:
        return None
    train = read_json(Path(path) / "train_config.json")
    root = ((train or {}).get("dataset") or {}).get("root")
    info = read_json(Path(root) / "meta" / "info.json") if root else None
    spec = read_json(Path(path).parent / JOURNAL_DIR / "spec.json")
    return (info or {}).get("fps") or (spec or {}).get("fps")


class RobotWorld:
    """A LeRobot robot on a table: one task (the instruction the policy was trained with), arranged states."""

    name = "robot"
    eval_seeds = 1
    eval_states_per_seed = EVAL_STATES

    def __init__(self, settings: RolloutStageConfig) -> None:
        self.robot_type = settings.robot.type
        fps = settings.operator.fps or (policy_fps(settings.policy) if settings.policy else None)
        if fps is None:
            raise UsageError(
                "give --operator.fps=<the fps of the dataset the policy was trained on> (--policy.path has no "
                "train_config.json naming a local dataset, and no robot_journal beside it)"
            )
        self.fps = fps
        self.horizon = max(1, round(settings.operator.episode_time_s * fps))

    def resolve_tasks(self, spec: str) -> list[str]:
        if not spec.strip():
            raise ValueError("--tasks must be the task instruction the policy was trained with")
        return [spec.strip()]

    def task_description(self, task: str) -> str:
        return task

    def training_states(self, task: str, purpose: str, start: int, count: int) -> list[int]:
        return list(range(start, start + count))

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        return list(range(count))

    def backend(self, settings: RolloutStageConfig, cameras: Sequence[str]) -> RobotBackend:
        return RobotBackend(settings, cameras, self.fps, settings.horizon())


def _slug(task: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", task).strip("_") or "task"


class RobotBackend:
    """One robot (``num_envs`` = 1) and an operator; episodes journaled as they end (see the module doc)."""

    num_envs = 1

    def __init__(self, settings: RolloutStageConfig, cameras: Sequence[str], fps: int, horizon: int) -> None:
        self.fps, self.horizon, self.cameras = fps, horizon, tuple(cameras)
        self.timing = settings.operator
        self.display = settings.display_data
        spec = {"robot": settings.robot.type, "tasks": settings.tasks, "policy": str(settings.policy.pretrained_path)}
        spec["fps"] = fps
        self.journal = EpisodeJournal(settings.output_dir / JOURNAL_DIR, spec, what="a robot rollout journal")
        self.operator: Operator = make_operator(settings.operator)
        self.robot_config, self.teleop_config = settings.robot, settings.teleop
        self.robot: Robot = make_robot_from_config(settings.robot)
        self.teleop: Teleoperator | None = None
        self.state_keys, self.action_keys = state_keys(self.robot), list(self.robot.action_features)
        device = f"robot {settings.robot.type}"
        try:
            self.robot.connect()
            measured = self.robot.get_observation()
            if settings.teleop is not None:
                device = f"teleoperator {settings.teleop.type}"
                self.teleop = make_teleoperator_from_config(settings.teleop)
                self.teleop.connect()
        except Exception as exc:  # not on the bus, a camera that does not open, ...: one line, not a traceback
            self.close()
            raise ArmFault(f"error: {device} did not connect: {_reason(exc)}") from exc
        except BaseException:
            self.close()
            raise
        rest = settings.operator.rest_pose
        if rest is not None and len(rest) != len(self.action_keys):
            self.close()
            raise UsageError(f"operator.rest_pose needs {len(self.action_keys)} values ({', '.join(self.action_keys)})")
        self.rest = np.array(rest if rest is not None else [measured[k] for k in self.action_keys], dtype=np.float64)
        if self.display:
            from lerobot.utils.visualization_utils import init_visualization

            init_visualization("rerun", session_name="lerobot_cso_robot")

    # ------------------------------------------------------------------ the job queue
    def run(
        self,
        jobs: Sequence[Job],
        controller: Controller,
        start_every: int = 1,
        progress: str | None = None,
        skip: Callable[[Job], bool] | None = None,
    ) -> Iterator[tuple[int, Trace]]:
        """Run the jobs in order; journaled ones are replayed from disk, the others (but those ``skip`` rejects,
        asked after the replays) run on the robot."""
        attempts: dict[tuple[str, int], int] = {}
        numbered = []
        for index, job in enumerate(jobs):
            attempts[job.task, job.init_seed] = attempts.get((job.task, job.init_seed), 0) + 1
            numbered.append((index, job, attempts[job.task, job.init_seed]))
        done = [n for n in numbered if self._path(n[1], n[2]).is_file()]
        todo = [n for n in numbered if not self._path(n[1], n[2]).is_file()]
        for index, job, attempt in done:
            yield index, self._replay(job, self._path(job, attempt))
        resuming = bool(done)
        for index, job, attempt in todo:
            if skip is not None and skip(job):
                continue
            if resuming:  # named once the replays are in: a skipped attempt is not the next one
                next_one = f"state {job.init_seed}, attempt {attempt}"
                print(f"resuming: {len(done)} episodes on disk; next: {next_one}", flush=True)
                resuming = False
            trace = self._run_until_kept(job, attempt, attempts[job.task, job.init_seed], controller)
            yield index, trace

    def _name(self, job: Job, attempt: int) -> tuple[str, str]:
        return _slug(job.task), f"{job.init_seed:07d}_{attempt:03d}"

    def _path(self, job: Job, attempt: int) -> Path:
        return self.journal.episode_path(*self._name(job, attempt))

    def _replay(self, job: Job, path: Path) -> Trace:
        data = EpisodeJournal.load(path)
        return Trace(
            job=job,
            success=bool(data["success"]),
            length=int(data["length"]),
            states=data["states"],
            actions=data["actions"],
            images={k.removeprefix("image_"): v for k, v in data.items() if k.startswith("image_")},
            record={k.removeprefix("record_"): torch.from_numpy(v) for k, v in data.items() if k.startswith("record_")},
        )

    def _discards(self, job: Job, attempt: int) -> list[str]:
        group, name = self._name(job, attempt)
        return self.journal.records(group).get(name, {}).get("discarded", [])

    def _discard(self, job: Job, attempt: int, reason: str) -> None:
        group, name = self._name(job, attempt)
        self.journal.save_record(group, name, {"discarded": [*self._discards(job, attempt), reason]})
        print(f"discarded: state {job.init_seed}, attempt {attempt} ({reason})", flush=True)

    def _run_until_kept(self, job: Job, attempt: int, attempts: int, controller: Controller) -> Trace:
        """Run the attempt until it gets a success or failure (discarded tries are repeated), journal it."""
        while True:
            info = EpisodeInfo(job.init_seed, attempt, attempts, len(self._discards(job, attempt)), self.horizon)
            try:
                trace = self._episode(job, info, controller)
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # e-stop, driver or firmware fault, stale feedback, a camera: never silent
                reason, device = _reason(exc), "teleoperator" if isinstance(exc, TeleopFault) else "robot"
                self._discard(job, attempt, reason)
                if self.timing.on_fault == "stop":
                    hint = "" if device == "teleoperator" else " (PiPER: piper-recover, or --robot.recovery=reset)"
                    raise ArmFault(
                        f"error: {device} fault in state {job.init_seed}, attempt {attempt}: {reason}. The episode was "
                        f"discarded and nothing more was sent to the arm; recover the {device}{hint}, then rerun "
                        f"the same command to resume there"
                    ) from exc
                self._reconnect(info, reason, device)
                continue
            if trace is not None:
                break
            self._discard(job, attempt, "operator")
        arrays = {"states": trace.states, "actions": trace.actions, "success": np.bool_(trace.success)}
        arrays |= {"length": np.int64(trace.length)}
        arrays |= {f"image_{cam}": frames for cam, frames in trace.images.items()}
        arrays |= {f"record_{k}": v.numpy() for k, v in (trace.record or {}).items()}
        self.journal.save_episode(*self._name(job, attempt), arrays)
        verdict = "success" if trace.success else "failure"
        print(f"state {job.init_seed}, attempt {attempt}: {verdict} after {trace.length} steps", flush=True)
        return trace

    def _reconnect(self, info: EpisodeInfo, fault: str, device: str) -> None:
        """``--operator.on_fault=wait``: let go of the devices, wait for the operator, connect them again as a
        rerun would (their own ``connect``: for the PiPER the enable handshake with ``--robot.recovery``), until
        they do."""
        self._let_go()
        hint = "" if device == "teleoperator" else " (PiPER: release the e-stop, piper-recover)"
        print(
            f"{device} fault in state {info.state}, attempt {info.attempt}: {fault}. The episode was discarded and "
            f"the devices disconnected; recover the {device}{hint}",
            flush=True,
        )
        while True:
            self.operator.wait_for_recovery(info)
            self.robot = make_robot_from_config(self.robot_config)
            try:
                self.robot.connect()
                self._observe()
                if self.teleop_config is not None:
                    self.teleop = make_teleoperator_from_config(self.teleop_config)
                    self.teleop.connect()
            except Exception as exc:  # still faulted: nothing was commanded
                self._let_go()
                print(f"the devices did not reconnect: {_reason(exc)}; recover them and confirm again", flush=True)
                continue
            print(f"reconnected; state {info.state}, attempt {info.attempt} again", flush=True)
            return

    def _let_go(self) -> None:
        """Disconnect the teleoperator and the robot (its own disconnect policy) where still connected; a failure
        is only logged."""
        for device in (self.teleop, self.robot):
            try:
                if device is not None and device.is_connected:
                    device.disconnect()
            except Exception as exc:
                log.warning("%s did not disconnect cleanly: %s", type(device).__name__, _reason(exc))

    # ------------------------------------------------------------------ one episode on the robot
    def _observe(self) -> tuple[dict[str, Any], np.ndarray]:
        obs = self.robot.get_observation()
        return obs, np.array([obs[k] for k in self.state_keys], dtype=np.float32)

    def _send(self, action: np.ndarray) -> dict[str, Any]:
        return self.robot.send_action(dict(zip(self.action_keys, map(float, action), strict=True)))

    def _tick(self, started: float) -> None:
        precise_sleep(max(0.0, 1 / self.fps - (time.perf_counter() - started)))

    def _move_to_rest(self) -> None:
        """Interpolate from the measured pose to the rest pose over ``rest_time_s``."""
        obs, _ = self._observe()
        start = np.array([obs[k] for k in self.action_keys], dtype=np.float64)
        steps = max(1, round(self.timing.rest_time_s * self.fps))
        for step in range(1, steps + 1):
            started = time.perf_counter()
            self._send(start + (self.rest - start) * step / steps)
            self._tick(started)
        self._observe()  # raises if the move ended in a fault

    def _teleop_action(self) -> dict[str, float]:
        """The teleoperator's action; any failure of it is a :class:`TeleopFault`."""
        assert self.teleop is not None
        try:
            return self.teleop.get_action()
        except Exception as exc:
            raise TeleopFault(f"{type(self.teleop).__name__}: {_reason(exc)}") from exc

    def _arrange(self, info: EpisodeInfo) -> None:
        """Wait for the operator; with a teleoperator the arm follows it meanwhile, then returns to rest."""
        while True:
            started = time.perf_counter()
            obs, _ = self._observe()
            sent = None if self.teleop is None else self.robot.send_action(self._teleop_action())
            if self.display:
                self._show(obs, sent, None)
            if self.operator.ready(info):
                break
            self._tick(started)
        if self.teleop is not None:
            self._move_to_rest()

    def _episode(self, job: Job, info: EpisodeInfo, controller: Controller) -> Trace | None:
        """One try on the robot: rest, arrange, the policy until a verdict; None when discarded."""
        self._move_to_rest()
        self._arrange(info)
        controller.start(0, job)
        states, actions = [], []
        images: dict[str, list[np.ndarray]] = {cam: [] for cam in self.cameras}
        chunk = np.zeros((0, len(self.action_keys)), dtype=np.float32)
        verdict = None
        for tick in range(self.horizon):
            started = time.perf_counter()
            obs, state = self._observe()
            if not len(chunk):
                batch: dict[str, Any] = {"agent_pos": state[None]}
                if self.cameras:
                    batch["pixels"] = {cam: np.asarray(obs[cam])[None] for cam in self.cameras}
                chunk = np.asarray(controller.act(batch, np.ones(1, dtype=bool)), dtype=np.float32)
                chunk = chunk.reshape(-1, chunk.shape[-1])
            sent = self._send(chunk[0])
            states.append(state)
            actions.append(np.array([sent[k] for k in self.action_keys], dtype=np.float32))
            for cam in self.cameras:
                images[cam].append(np.asarray(obs[cam], dtype=np.uint8))
            if self.display:
                self._show(obs, sent, controller.current_skill(0))
            chunk = chunk[1:]
            verdict = self.operator.verdict(info, obs, tick)
            if verdict is not None:
                break
            self._tick(started)
        if verdict == "discard":
            controller.finish(0)
            return None
        return Trace(
            job=job,
            success=verdict == "success",
            length=len(actions),
            states=np.stack(states),
            actions=np.stack(actions),
            images={cam: np.stack(frames) for cam, frames in images.items()},
            record=controller.finish(0),
        )

    def _show(self, obs: dict[str, Any], sent: dict[str, Any] | None, skill: ActiveSkill | None) -> None:
        """``--display_data``: the cameras and measured joints, the action sent, the skill being executed."""
        from lerobot.utils.visualization_utils import log_visualization_data

        observation = dict(obs)
        if skill is not None:
            observation["skill.index"] = float(skill.index)
            observation["skill.tokens"] = np.asarray(skill.tokens, dtype=np.float64)
        action = None if sent is None else {k: float(sent[k]) for k in self.action_keys}
        log_visualization_data("rerun", observation=observation, action=action)

    def close(self) -> None:
        """Disconnect (the robot's own disconnect policy applies); never sends anything else."""
        self.operator.close()
        for device in (self.teleop, self.robot):
            if device is not None and device.is_connected:
                device.disconnect()
