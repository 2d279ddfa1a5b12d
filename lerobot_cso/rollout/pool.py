"""A pool of MetaWorld envs (a gymnasium vector env) that runs a queue of episodes under one controller.

The vector env runs with ``autoreset_mode=DISABLED``: when a slot's episode ends, the pool resets just that
slot (``reset_mask``) onto the next job of the queue, with the job's task and initial-state seed, or parks
it when no job may start now. Jobs only start on global steps that are multiples of ``start_every``; the
policy-driven engine sets it to the number of actions per decision, so every running episode takes its
decisions on the same steps and each decision round is one batched policy call. A parked slot costs no
simulation (in a ``SyncVectorEnv`` it costs nothing at all), so the alignment is free for state-only
rollouts. Jobs are handed out with task affinity (a slot stays on its task while that task has jobs left),
so that each env builds few MuJoCo models.

``vectorization="sync"`` (default) steps all envs in this process; ``"async"`` gives each env a worker
process (forkserver), which pays off with cameras or on machines with more cores than this one's two.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from tqdm import tqdm

from lerobot_cso.envs.constants import HORIZON, IMAGE_SIZE
from lerobot_cso.envs.metaworld_env import CSOMetaWorldEnv, check_cameras
from lerobot_cso.envs.tasks import check_task

Vectorization = Literal["sync", "async"]


@dataclass(frozen=True)
class Job:
    """One episode to run: a task, an initial-state seed, and the caller's handle for it."""

    task: str
    init_seed: int
    key: Any = None


@dataclass
class Trace:
    """What the pool records for a finished episode (``states[t]`` is the input of ``actions[t]``)."""

    job: Job
    success: bool
    length: int
    states: np.ndarray  # (length, 39) float32
    actions: np.ndarray  # (length, 4) float32, as executed (clipped to [-1, 1])
    images: dict[str, np.ndarray] = field(default_factory=dict)  # camera -> (length, H, W, 3) uint8
    record: Any = None  # whatever the controller returned from ``finish``


class Controller(Protocol):
    """Chooses the actions of every slot of a pool."""

    def start(self, slot: int, job: Job) -> None:
        """A new episode begins in ``slot``."""

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        """Actions ``(num_envs, 4)`` for the batched observation; rows where ``active`` is False are ignored."""

    def finish(self, slot: int) -> Any:
        """The episode in ``slot`` ended; return the controller's record of it (or None)."""


class _Recorder:
    """Per-slot step buffers of the running episode."""

    def __init__(self, cameras: Sequence[str]) -> None:
        self.cameras = cameras
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.images: dict[str, list[np.ndarray]] = {cam: [] for cam in cameras}

    def add(self, obs: dict[str, Any], slot: int, action: np.ndarray) -> None:
        self.states.append(obs["agent_pos"][slot].copy())
        self.actions.append(np.clip(action, -1.0, 1.0).astype(np.float32))
        for cam in self.cameras:
            self.images[cam].append(obs["pixels"][cam][slot].copy())

    def trace(self, job: Job, success: bool, record: Any) -> Trace:
        return Trace(
            job=job,
            success=success,
            length=len(self.actions),
            states=np.stack(self.states),
            actions=np.stack(self.actions),
            images={cam: np.stack(frames) for cam, frames in self.images.items()},
            record=record,
        )


class _Scheduler:
    """Hands out jobs with task affinity, so that each env builds few MuJoCo models.

    A slot keeps to the task it ran last while that task has jobs left, otherwise claims the first task
    no slot has started yet, and only when every task is claimed helps with the one with most jobs left.
    """

    def __init__(self, jobs: Sequence[Job]) -> None:
        self._queues: dict[str, deque[tuple[int, Job]]] = {}
        for index, job in enumerate(jobs):
            self._queues.setdefault(job.task, deque()).append((index, job))
        self._claimed: set[str] = set()

    def __bool__(self) -> bool:
        return bool(self._queues)

    def next(self, last_task: str | None) -> tuple[int, Job]:
        task = last_task if last_task in self._queues else None
        if task is None:
            task = next((t for t in self._queues if t not in self._claimed), None)
        if task is None:
            task = max(self._queues, key=lambda t: len(self._queues[t]))
        self._claimed.add(task)
        queue = self._queues[task]
        entry = queue.popleft()
        if not queue:
            del self._queues[task]
        return entry


class EnvPool:
    """``num_envs`` MetaWorld envs behind one gymnasium vector env, fed from a job queue."""

    def __init__(
        self,
        num_envs: int = 8,
        cameras: Sequence[str] = (),
        image_size: int = IMAGE_SIZE,
        max_steps: int = HORIZON,
        vectorization: Vectorization = "sync",
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if vectorization not in ("sync", "async"):
            raise ValueError(f"vectorization must be 'sync' or 'async', got '{vectorization}'")
        check_cameras(cameras)
        self.num_envs = num_envs
        self.cameras = tuple(cameras)
        self.max_steps = max_steps
        # The task given here is only the initial one; every job resets its slot onto its own task.
        make = partial(CSOMetaWorldEnv, "reach-v3", self.cameras, image_size, max_steps)
        fns: list[Callable[[], gym.Env]] = [make] * num_envs
        if vectorization == "async" and num_envs > 1:
            self.vec: gym.vector.VectorEnv = gym.vector.AsyncVectorEnv(
                fns, context="forkserver", autoreset_mode=AutoresetMode.DISABLED
            )
        else:
            self.vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED)
        self.vec.reset(options={"park": True})  # every slot starts parked; jobs reset slots individually
        self._tasks: list[str | None] = [None] * num_envs  # the task each slot ran last in this run
        self._parked = np.ones(num_envs, dtype=bool)  # persists across runs: a slot that ended must be parked

    def _reset(self, slots: list[int], options: dict[str, Any], seeds: list[int | None] | None = None) -> dict:
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[slots] = True
        seed_list: list[int | None] = [None] * self.num_envs
        for slot, seed in zip(slots, seeds or [None] * len(slots), strict=True):
            seed_list[slot] = seed
        obs, _ = self.vec.reset(seed=seed_list, options={**options, "reset_mask": mask})
        return obs

    def run(
        self,
        jobs: Sequence[Job],
        controller: Controller,
        start_every: int = 1,
        progress: str | None = None,
    ) -> Iterator[tuple[int, Trace]]:
        """Run every job to its end, yielding ``(job index, trace)`` as each episode finishes."""
        for task in {job.task for job in jobs}:
            check_task(task)
        scheduler = _Scheduler(jobs)
        # Forget the previous run's slot tasks: the same jobs then always get the same slots, hence the same
        # policy batches (float results can depend on a row's batch), and a call is reproducible.
        self._tasks = [None] * self.num_envs
        running: list[tuple[int, Job] | None] = [None] * self.num_envs
        recorders: list[_Recorder | None] = [None] * self.num_envs
        parked = self._parked
        obs: dict[str, Any] = {}
        bar = tqdm(total=len(jobs), desc=progress, disable=progress is None, leave=False)
        step = 0
        while scheduler or any(r is not None for r in running):
            if scheduler and step % start_every == 0:
                starting: dict[str, list[tuple[int, int, Job]]] = {}
                for slot in range(self.num_envs):
                    if running[slot] is None and scheduler:
                        index, job = scheduler.next(self._tasks[slot])
                        starting.setdefault(job.task, []).append((slot, index, job))
                for task, entries in starting.items():
                    slots = [slot for slot, _, _ in entries]
                    obs = self._reset(slots, {"task": task}, [job.init_seed for _, _, job in entries])
                    for slot, index, job in entries:
                        running[slot] = (index, job)
                        recorders[slot] = _Recorder(self.cameras)
                        parked[slot] = False
                        self._tasks[slot] = task
                        controller.start(slot, job)
            to_park = [slot for slot in range(self.num_envs) if running[slot] is None and not parked[slot]]
            if to_park:
                obs = self._reset(to_park, {"park": True})
                parked[to_park] = True
            active = np.array([r is not None for r in running])
            actions = controller.act(obs, active)
            for slot in np.flatnonzero(active):
                recorders[slot].add(obs, slot, actions[slot])
            obs, _, terminated, truncated, _ = self.vec.step(actions.astype(np.float32))
            step += 1
            for slot in np.flatnonzero(active & (terminated | truncated)):
                index, job = running[slot]
                trace = recorders[slot].trace(job, bool(terminated[slot]), controller.finish(slot))
                running[slot] = recorders[slot] = None
                bar.update()
                yield index, trace
        bar.close()

    def close(self) -> None:
        self.vec.close()

    def __enter__(self) -> EnvPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
