"""The robot's rollout backend: the job queue over the episode journal, and the control loop of one episode.

One episode (:meth:`RobotBackend.run`): the arm moves smoothly to the rest pose; the operator arranges the
scene (with a teleoperator the arm follows it meanwhile, then returns to the rest pose); the policy runs at
the world's fps, one action of its 8-action chunk per control tick, until the operator's verdict or the time
limit (a failure). A discarded episode is repeated. A fault of the robot (e-stop, driver or firmware fault,
stale feedback, a camera that fails) or of the teleoperator while it drives the arm discards the episode in
flight, and nothing more is sent to the arm: the command ends with one line naming the device
(:class:`~lerobot_cso.worlds.robot.devices.ArmFault`), or with ``--operator.on_fault=wait`` both devices are
disconnected, the operator recovers the faulted one, and both are connected again
(:meth:`~lerobot_cso.worlds.robot.devices.Devices.recover`) before the attempt is repeated. A robot or
teleoperator that does not connect ends the command with one line too.

**Simulated time.** A robot with a ``simulated_fps`` attribute (the PiPER twin in process, ``piper_twin_sim``) lets
one control period of its own time pass in each ``send_action``; the rest moves and the episodes then do not wait
for the wall clock (faster than real time), while the arrange phase still does (a person arranges in real time).

**Durability.** Every finished episode is written to the journal (:class:`~lerobot_cso.rollout.journal.TraceJournal`,
one ``.npz`` per episode with the controller's record) the moment it ends, before the stage sees it; discarded
tries are recorded there too. A rerun of the same command replays the journaled episodes of each request instead
of running them, so R-SFT, SPO and evaluation resume at the state and attempt that come next, with nothing lost or
duplicated.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from lerobot.robots import Robot
from lerobot.teleoperators import Teleoperator
from lerobot.utils.robot_utils import precise_sleep

from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.backend import ActiveSkill, Controller, Job, Trace
from lerobot_cso.rollout.journal import TraceJournal, numbered
from lerobot_cso.worlds.robot.devices import ArmFault, Devices, TeleopFault, reason
from lerobot_cso.worlds.robot.operator import EpisodeInfo, Operator, OperatorConfig, make_operator


def state_keys(robot: Robot) -> list[str]:
    """The scalar observations of ``robot`` in order: ``observation.state`` as ``lerobot-record`` writes it."""
    return [k for k, v in robot.observation_features.items() if not isinstance(v, tuple)]


class RobotBackend:
    """One robot (``num_envs`` = 1) and an operator; episodes journaled as they end (see the module doc).

    ``devices`` are the robot and teleoperator (not connected yet), ``timing`` the operator's settings, ``display``
    whether to show the episodes in rerun."""

    num_envs = 1

    def __init__(
        self,
        devices: Devices,
        timing: OperatorConfig,
        journal: TraceJournal,
        cameras: Sequence[str],
        fps: int,
        horizon: int,
        display: bool = False,
    ) -> None:
        self.fps, self.horizon, self.cameras = fps, horizon, tuple(cameras)
        self.timing, self.display, self.journal, self.devices = timing, display, journal, devices
        # A robot on simulated time (PiPER: piper_twin_sim) lets one control period pass in each send_action.
        simulated = getattr(self.robot, "simulated_fps", None)
        if simulated is not None and simulated != fps:
            raise UsageError(
                f"robot {self.robot.name} runs on simulated time at {simulated} fps, the control loop at {fps}: "
                f"give --robot.fps={fps}"
            )
        self.simulated = simulated is not None
        self.operator: Operator = make_operator(timing, lambda: self.robot)
        self.state_keys, self.action_keys = state_keys(self.robot), list(self.robot.action_features)
        try:
            measured = self.devices.connect()
        except BaseException:
            self.operator.close()
            raise
        rest = timing.rest_pose
        if rest is not None and len(rest) != len(self.action_keys):
            self.close()
            raise UsageError(f"operator.rest_pose needs {len(self.action_keys)} values ({', '.join(self.action_keys)})")
        self.rest = np.array(rest if rest is not None else [measured[k] for k in self.action_keys], dtype=np.float64)
        if self.display:
            from lerobot.utils.visualization_utils import init_visualization

            init_visualization("rerun", session_name="lerobot_cso_robot")

    @property
    def robot(self) -> Robot:
        return self.devices.robot

    @property
    def teleop(self) -> Teleoperator | None:
        return self.devices.teleop

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
        attempts = numbered(jobs)
        done = [a for a in attempts if self.journal.has(a[1], a[2])]
        todo = [a for a in attempts if not self.journal.has(a[1], a[2])]
        for index, job, attempt, _ in done:
            yield index, self.journal.load(job, attempt)
        resuming = bool(done)
        for index, job, attempt, of in todo:
            if skip is not None and skip(job):
                continue
            if resuming:  # named once the replays are in: a skipped attempt is not the next one
                next_one = f"state {job.init_seed}, attempt {attempt}"
                print(f"resuming: {len(done)} episodes on disk; next: {next_one}", flush=True)
                resuming = False
            yield index, self._run_until_kept(job, attempt, of, controller)

    def _discard(self, job: Job, attempt: int, why: str) -> None:
        self.journal.discard(job, attempt, why)
        print(f"discarded: state {job.init_seed}, attempt {attempt} ({why})", flush=True)

    def _run_until_kept(self, job: Job, attempt: int, attempts: int, controller: Controller) -> Trace:
        """Run the attempt until it gets a success or failure (discarded tries are repeated), journal it."""
        while True:
            tries = len(self.journal.discards(job, attempt))
            info = EpisodeInfo(job.init_seed, attempt, attempts, tries, self.horizon)
            try:
                trace = self._episode(job, info, controller)
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # e-stop, driver or firmware fault, stale feedback, a camera: never silent
                fault, device = reason(exc), "teleoperator" if isinstance(exc, TeleopFault) else "robot"
                self._discard(job, attempt, fault)
                if self.timing.on_fault == "stop":
                    raise ArmFault(
                        f"error: {device} fault in state {job.init_seed}, attempt {attempt}: {fault}. The episode was "
                        f"discarded and nothing more was sent to the arm; recover the {device}"
                        f"{self.devices.hint(device)}, then rerun the same command to resume there"
                    ) from exc
                self.devices.recover(self.operator, info, fault, device)
                continue
            if trace is not None:
                break
            self._discard(job, attempt, "operator")
        self.journal.save(attempt, trace)
        verdict = "success" if trace.success else "failure"
        print(f"state {job.init_seed}, attempt {attempt}: {verdict} after {trace.length} steps", flush=True)
        return trace

    # ------------------------------------------------------------------ the control loop of one episode
    def _observe(self) -> tuple[dict[str, Any], np.ndarray]:
        obs = self.robot.get_observation()
        return obs, np.array([obs[k] for k in self.state_keys], dtype=np.float32)

    def _send(self, action: np.ndarray) -> dict[str, Any]:
        return self.robot.send_action(dict(zip(self.action_keys, map(float, action), strict=True)))

    def _wait(self, started: float) -> None:
        """Wait on the wall clock until one control period has passed since ``started``."""
        precise_sleep(max(0.0, 1 / self.fps - (time.perf_counter() - started)))

    def _tick(self, started: float) -> None:
        """The next control tick of a move or an episode: on simulated time the robot's ``send_action`` already let
        the period pass."""
        if not self.simulated:
            self._wait(started)

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
            raise TeleopFault(f"{type(self.teleop).__name__}: {reason(exc)}") from exc

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
            self._wait(started)  # a person arranges in real time, also on simulated time
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
        self.devices.close()
