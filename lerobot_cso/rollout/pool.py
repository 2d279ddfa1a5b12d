"""The simulated-world rollout backend: a pool of envs (a gymnasium vector env) that runs a queue of episodes
under one controller (:class:`~lerobot_cso.rollout.backend.RolloutBackend`). Its envs come from a world's env
factory and speak the pool's env protocol, :class:`~lerobot_cso.rollout.env.PoolEnv` (reset ``options``:
``task``, ``park``, ``render_every``).

The vector env runs with ``autoreset_mode=DISABLED``: a slot whose episode ended is parked at once, then reset
(``reset_mask``) onto the next job of the queue, with the job's task and initial-state seed, when one may
start. The controller returns one action per slot, or a chunk of L actions that the pool executes open-loop.
The slots form lanes (:class:`~lerobot_cso.rollout.sharded.ChunkLanes`): one, or two for the ``processes``
vectorization, which take turns so that one lane's chunk simulates in its workers while the controller decides
the other's. Jobs only start on steps of their lane that are multiples of ``start_every``; the policy-driven
engine sets it to the number of actions per decision and returns chunks of that length, so every running
episode of a lane takes its decisions on the same steps and each decision round of a lane is one batched
policy call. Which slot runs which job does not depend on the lanes (only ``skip`` may see fewer finished
episodes of the other lane when a job's turn comes). A new episode takes its first decision on its lane's turn
after the one that reset it: the reset travels with the lane's chunk. A parked slot costs no
simulation (in a ``SyncVectorEnv`` it costs nothing at all), so the alignment is free for state-only
rollouts. Jobs are handed out with task affinity (a slot stays on its task while that task has jobs left),
so that each env builds few MuJoCo models.

``vectorization="processes"`` (default) splits the envs into ``workers`` processes (one per core by default),
each stepping its shard in a ``SyncVectorEnv`` (:class:`~lerobot_cso.rollout.sharded.ShardedVectorEnv`);
``"sync"`` steps all envs in this process; ``"async"`` is gymnasium's ``AsyncVectorEnv``, one process per env.

Inside :func:`kept_pools` (the pipeline's rollout stages run there), :func:`open_pool` hands out one pool per set
of arguments and keeps it open when a stage closes it: the stages then start their worker processes and build
their MuJoCo models once instead of once each.

``frames="decisions"`` asks the envs to render cameras only on the steps where episodes take decisions
(``render_every=start_every``) and records no images in the traces (but those of jobs marked ``keep_frames``,
where the frames between decisions repeat the decision's): what evaluation and SPO need, which keep only the
policy's contexts. ``"all"`` (default) records every frame, as an R-SFT buffer needs.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from tqdm import tqdm

from lerobot_cso.rollout.backend import Controller, Job, RolloutBackend, Trace
from lerobot_cso.rollout.env import PoolEnv
from lerobot_cso.rollout.sharded import ChunkLanes, Reset, ShardedVectorEnv

Vectorization = Literal["processes", "sync", "async"]
VECTORIZATIONS: tuple[str, ...] = ("processes", "sync", "async")
Frames = Literal["all", "decisions"]


def default_workers() -> int:
    """Worker processes of the ``processes`` vectorization: one per core this process may run on."""
    return len(os.sched_getaffinity(0))


class _Recorder:
    """Per-slot step buffers of the running episode."""

    def __init__(self, cameras: Sequence[str]) -> None:
        self.cameras = cameras
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.images: dict[str, list[np.ndarray]] = {cam: [] for cam in cameras}

    def add(self, before: dict[str, Any], after: dict[str, Any], slot: int, row: int, actions: np.ndarray) -> None:
        """Record ``actions`` (n, A) executed from observation ``before`` (batched over all slots); ``after``
        holds the observations (L, lane envs, ...) after each step of the chunk, the slot at ``row``, so step
        j's input is ``after[j - 1]``."""
        n = len(actions)
        self.states.append(before["agent_pos"][slot][None])
        self.states.append(after["agent_pos"][: n - 1, row])
        self.actions.append(np.clip(actions, -1.0, 1.0).astype(np.float32))
        for cam in self.cameras:
            self.images[cam].append(before["pixels"][cam][slot][None])
            self.images[cam].append(after["pixels"][cam][: n - 1, row])

    def trace(self, job: Job, success: bool, record: Any) -> Trace:
        actions = np.concatenate(self.actions)
        return Trace(
            job=job,
            success=success,
            length=len(actions),
            states=np.concatenate(self.states),
            actions=actions,
            images={cam: np.concatenate(frames) for cam, frames in self.images.items()},
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

    def next(self, last_task: str | None, skip: Callable[[Job], bool] | None = None) -> tuple[int, Job] | None:
        """The next job for a slot that ran ``last_task``, passing over those ``skip`` rejects; None when
        no job is left."""
        while self._queues:
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
            if skip is None or not skip(entry[1]):
                return entry
        return None


class _Run:
    """One :meth:`EnvPool.run` call: which job each slot runs, what each lane has in flight, and the turn of a lane
    (:meth:`receive` its results, then :meth:`advance` it: decide, start and park slots, send)."""

    def __init__(
        self,
        pool: EnvPool,
        jobs: Sequence[Job],
        controller: Controller,
        start_every: int,
        skip: Callable[[Job], bool] | None,
    ) -> None:
        self.pool, self.controller, self.start_every, self.skip = pool, controller, start_every, skip
        self.start_options = {} if pool.frames == "all" else {"render_every": start_every}
        self.scheduler = _Scheduler(jobs)
        self.running: list[tuple[int, Job] | None] = [None] * pool.num_envs
        self.starting = np.zeros(pool.num_envs, dtype=bool)  # reset onto its job, not yet observed
        self.recorders: list[_Recorder | None] = [None] * pool.num_envs
        self.parked = pool._parked
        self.lanes = ChunkLanes(pool.vec)
        lanes = len(self.lanes.slots)
        self.steps = [0] * lanes  # env steps each lane has run in this call
        self.in_flight = [False] * lanes
        self.chunks: list[np.ndarray | None] = [None] * lanes  # the chunk each lane runs
        self.before: list[dict[str, Any]] = [{} for _ in range(lanes)]  # the observation it was chosen from
        self.obs: list[dict[str, Any]] = [{} for _ in range(lanes)]  # the lane's latest observation

    def done(self) -> bool:
        return not self.scheduler and not any(self.in_flight)

    def receive(self, lane: int) -> list[tuple[int, Trace]]:
        """The lane's results, if it has a chunk in flight: the episodes that ended in it."""
        self.obs[lane] = self.before[lane]
        if not self.in_flight[lane]:
            return []
        result, chunk = self.lanes.receive(lane), self.chunks[lane]
        self.in_flight[lane] = False
        self.obs[lane] = self.lanes.observation()
        slots = self.lanes.slots[lane]
        ended = [] if chunk is None else self._record(lane, slots, chunk, result)
        self.starting[slots] = False
        return ended

    def _record(self, lane: int, slots: np.ndarray, chunk: np.ndarray, result: Any) -> list[tuple[int, Trace]]:
        """Record the chunk's steps of each running slot; the traces of the episodes that ended."""
        after, terminated, truncated = result
        self.steps[lane] += chunk.shape[1]
        ended = terminated | truncated
        traces = []
        for row, slot in enumerate(slots):
            if self.running[slot] is None or self.starting[slot]:
                continue
            finished = bool(ended[:, row].any())
            end = int(np.argmax(ended[:, row])) + 1 if finished else chunk.shape[1]
            self.recorders[slot].add(self.before[lane], after, slot, row, chunk[row, :end])
            if finished:
                index, job = self.running[slot]
                success = bool(terminated[:, row].any())
                traces.append((index, self.recorders[slot].trace(job, success, self.controller.finish(slot))))
                self.running[slot] = self.recorders[slot] = None
                self.parked[slot] = True  # the chunk parked it at its end
        return traces

    def advance(self, lane: int) -> None:
        """Decide the lane's next chunk, start jobs in its free slots (on a start step), park the idle ones, send."""
        slots, obs = self.lanes.slots[lane], self.obs[lane]
        active = np.zeros(self.pool.num_envs, dtype=bool)
        active[slots] = [self.running[slot] is not None for slot in slots]
        chunk = None
        if active.any():
            actions = self.controller.act(obs, active)
            chunk = (actions[:, None] if actions.ndim == 2 else actions)[slots].astype(np.float32)
            end_step = self.steps[lane] + chunk.shape[1]
        else:
            end_step = self.steps[lane] + -self.steps[lane] % self.start_every  # an idle lane waits for a start step
            self.steps[lane] = end_step
        resets: list[Reset] = []  # after the chunk, one masked reset per task (one message per worker)
        if self.scheduler and end_step % self.start_every == 0:
            resets += self._start(slots)
        to_park = [int(slot) for slot in slots if self.running[slot] is None and not self.parked[slot]]
        if to_park:
            resets.append(self.pool._reset(to_park, {"park": True}))
            self.parked[to_park] = True
        if chunk is not None or resets:
            self.lanes.send(lane, chunk, None if chunk is None else active[slots], resets)
            self.in_flight[lane], self.chunks[lane], self.before[lane] = True, chunk, obs

    def _start(self, slots: np.ndarray) -> list[Reset]:
        """Hand the next jobs to the free ``slots``; one masked reset per task."""
        pool, new = self.pool, {}
        for slot in slots:
            entry = self.scheduler.next(pool._tasks[slot], self.skip) if self.running[slot] is None else None
            if entry is not None:
                new.setdefault(entry[1].task, []).append((slot, *entry))
        resets = []
        for task, entries in new.items():
            options = {"task": task, **self.start_options}
            seeds = [job.init_seed for _, _, job in entries]
            resets.append(pool._reset([slot for slot, _, _ in entries], options, seeds))
            for slot, index, job in entries:
                self.running[slot] = (index, job)
                self.starting[slot] = True
                kept = pool.frames == "all" or job.keep_frames
                self.recorders[slot] = _Recorder(pool.cameras if kept else ())
                self.parked[slot] = False
                pool._tasks[slot] = task
                self.controller.start(slot, job)
        return resets


class EnvPool:
    """``num_envs`` envs behind one vector env, fed from a job queue.

    ``env_factory`` builds one env with the given ``cameras`` (picklable, for worker processes); ``check_task``
    raises ``ValueError`` for a task name the envs do not know.
    """

    def __init__(
        self,
        num_envs: int,
        cameras: Sequence[str] = (),
        *,
        env_factory: Callable[[], PoolEnv],
        check_task: Callable[[str], object],
        vectorization: Vectorization = "processes",
        workers: int | None = None,
        frames: Frames = "all",
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if vectorization not in VECTORIZATIONS:
            raise ValueError(f"vectorization must be one of {', '.join(VECTORIZATIONS)}, got '{vectorization}'")
        if frames not in ("all", "decisions"):
            raise ValueError(f"frames must be 'all' or 'decisions', got '{frames}'")
        self.num_envs = num_envs
        self.cameras = tuple(cameras)
        self.frames = frames
        self._check_task = check_task
        fns: list[Callable[[], gym.Env]] = [env_factory] * num_envs
        workers = default_workers() if workers is None else workers
        if vectorization == "processes" and num_envs > 1 and workers > 1:
            self.vec: gym.vector.VectorEnv = ShardedVectorEnv(fns, workers=workers)
        elif vectorization == "async" and num_envs > 1:
            self.vec = gym.vector.AsyncVectorEnv(fns, context="forkserver", autoreset_mode=AutoresetMode.DISABLED)
        else:
            self.vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=AutoresetMode.DISABLED)
        self.vec.reset(options={"park": True})  # every slot starts parked; jobs reset slots individually
        self._tasks: list[str | None] = [None] * num_envs  # the task each slot ran last in this run
        self._parked = np.ones(num_envs, dtype=bool)  # persists across runs: a slot that ended must be parked

    def _reset(self, slots: list[int], options: dict[str, Any], seeds: list[int | None] | None = None) -> Reset:
        """The masked reset of ``slots``, as :meth:`~lerobot_cso.rollout.sharded.ChunkLanes.send` takes it."""
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[slots] = True
        seed_list: list[int | None] = [None] * self.num_envs
        for slot, seed in zip(slots, seeds or [None] * len(slots), strict=True):
            seed_list[slot] = seed
        return seed_list, {**options, "reset_mask": mask}

    def run(
        self,
        jobs: Sequence[Job],
        controller: Controller,
        start_every: int = 1,
        progress: str | None = None,
        skip: Callable[[Job], bool] | None = None,
    ) -> Iterator[tuple[int, Trace]]:
        """Run every job (but those ``skip`` rejects at their start) to its end, yielding ``(job index, trace)``
        as each episode finishes."""
        for task in {job.task for job in jobs}:
            self._check_task(task)
        # Forget the previous run's slot tasks: the same jobs then always get the same slots, hence the same
        # policy batches (float results can depend on a row's batch), and a call is reproducible.
        self._tasks = [None] * self.num_envs
        call = _Run(self, jobs, controller, start_every, skip)
        bar = tqdm(total=len(jobs), desc=progress, disable=progress is None, leave=False)
        try:
            while True:
                # The lanes take turns: a lane's results come in and its ended episodes are yielded, then its next
                # chunk is decided and sent together with the resets that start new episodes in its free slots
                # (which take their first decision on the lane's next turn); then the next lane, while this one runs.
                for lane in range(len(call.lanes.slots)):
                    for ended in call.receive(lane):
                        bar.update()
                        yield ended
                    call.advance(lane)
                if call.done():
                    break  # nothing running and nothing left to start (or the last jobs were skipped)
        finally:
            call.lanes.drain()  # a run left early (a closed generator, an error) leaves no answer in a worker's pipe
        bar.close()

    def close(self) -> None:
        self.vec.close()

    def __enter__(self) -> EnvPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_kept: dict[tuple[Any, ...], EnvPool] | None = None  # the pools kept open by kept_pools(), by their arguments


def _argument_key(value: Any) -> Any:
    """A hashable stand-in for a pool argument: a ``functools.partial`` by its function and arguments."""
    if isinstance(value, partial):
        return (value.func, value.args, tuple(sorted(value.keywords.items())))
    return tuple(value) if isinstance(value, list | tuple) else value


class _KeptPool:
    """A kept pool as a stage sees it: the stage's ``close`` leaves it open for the next stage."""

    def __init__(self, pool: EnvPool) -> None:
        self.pool = pool
        self.num_envs = pool.num_envs

    def run(self, *args: Any, **kwargs: Any) -> Iterator[tuple[int, Trace]]:
        return self.pool.run(*args, **kwargs)

    def close(self) -> None:
        """Nothing: :func:`kept_pools` closes the pool when its block ends."""

    def __enter__(self) -> _KeptPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def kept_pools() -> Iterator[None]:
    """A block in which :func:`open_pool` keeps every pool it builds, for the block's later stages; all are
    closed when it ends."""
    global _kept
    if _kept is not None:
        yield  # nested: the outer block keeps them
        return
    _kept = {}
    try:
        yield
    finally:
        pools, _kept = list(_kept.values()), None
        for pool in pools:
            pool.close()


def open_pool(num_envs: int, cameras: Sequence[str] = (), **kwargs: Any) -> RolloutBackend:
    """An :class:`EnvPool` with these arguments: a new one, or inside :func:`kept_pools` the one kept for them."""
    if _kept is None:
        return EnvPool(num_envs, cameras, **kwargs)
    key = (num_envs, tuple(cameras), *((name, _argument_key(v)) for name, v in sorted(kwargs.items())))
    if key not in _kept:
        _kept[key] = EnvPool(num_envs, cameras, **kwargs)
    return _KeptPool(_kept[key])
