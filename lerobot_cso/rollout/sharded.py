"""Action chunks on vector envs in lanes, and a vector env whose envs are split over a few worker processes.

A chunk is L actions per env executed open-loop (QueST executes 8 actions per decision); the observation after
every step comes back, and an env whose episode ends inside the chunk is parked at once
(``reset(options={"park": True})``, no simulation), so it never steps past its end.

Gymnasium's ``AsyncVectorEnv`` gives every env a process of its own; with 16 MetaWorld envs on two cores
that costs more in pipe round trips and context switches than it gains (measured: 365 vs 653 env steps/s
with the policy in the loop). :class:`ShardedVectorEnv` runs ``workers`` processes (default: one per core),
each stepping a contiguous shard of the envs in a ``SyncVectorEnv``; a whole chunk is one round trip per
worker, and the shards simulate in parallel.

:class:`ChunkLanes` splits the envs into lanes that step chunks independently. A ``ShardedVectorEnv`` has two
lanes (halves of its workers). A lane's chunk and the resets that follow it (the next episodes' starts, one
masked reset per task) are one message per worker, and run there while the caller decides the other lane's
actions, so that neither the workers nor the caller wait on each other; any other vector env is one lane, run
in the caller's process.

Only what :class:`~lerobot_cso.rollout.pool.EnvPool` uses is supported: ``reset`` with per-env seeds and
``options["reset_mask"]`` (``autoreset_mode=DISABLED``), ``step``, :class:`ChunkLanes` and ``close``. Infos are
not gathered.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from lerobot_cso.errors import EnvWorkerError


def _concat(parts: Sequence[Any], axis: int = 0) -> Any:
    """Concatenate batched observations (arrays or nested dicts of arrays) along the env axis ``axis``."""
    if isinstance(parts[0], dict):
        return {key: _concat([p[key] for p in parts], axis) for key in parts[0]}
    return np.concatenate(parts, axis)


def last_step(value: Any) -> Any:
    """The last step of stacked observations (arrays or nested dicts)."""
    return {key: last_step(v) for key, v in value.items()} if isinstance(value, dict) else value[-1]


def _stack(parts: Sequence[Any]) -> Any:
    """Stack per-step batched observations into (L, num_envs, ...) arrays (nested dicts kept)."""
    if isinstance(parts[0], dict):
        return {key: _stack([p[key] for p in parts]) for key in parts[0]}
    return np.stack(parts)


def _run_chunk(vec: gym.vector.VectorEnv, actions: np.ndarray, active: np.ndarray):
    """Step ``actions`` (num_envs, L, A) in the ``active`` envs of a local vector env: observations after each
    step (L, num_envs, ...), ``terminated`` and ``truncated`` (L, num_envs), True only at the step where an
    active env's episode ended; an env is parked right after its end, so its later observations repeat."""
    done = ~active
    observations, terminated, truncated = [], [], []
    for j in range(actions.shape[1]):
        obs, _, term, trunc, _ = vec.step(actions[:, j])
        ended = (term | trunc) & ~done
        observations.append(obs)
        terminated.append(term & ended)
        truncated.append(trunc & ended)
        done |= ended
        if ended.any():
            vec.reset(options={"park": True, "reset_mask": ended})
    return _stack(observations), np.stack(terminated), np.stack(truncated)


Reset = tuple[Sequence[int | None], dict[str, Any]]  # per-env seeds, options (with "reset_mask")
Chunk = tuple[Any, np.ndarray, np.ndarray]  # observations (L, n, ...), terminated, truncated (L, n)


def _run(vec: gym.vector.VectorEnv, actions: np.ndarray | None, active: np.ndarray | None, resets: Sequence[Reset]):
    """A chunk (none when ``actions`` is None), then ``resets`` in order, in a local vector env; returns the
    chunk's results (or None) and the batched observation after both (None when neither ran)."""
    chunk = None if actions is None else _run_chunk(vec, actions, active)
    obs = None if chunk is None else last_step(chunk[0])
    for seeds, options in resets:
        obs, _ = vec.reset(seed=list(seeds), options=options)
    return chunk, obs


def _shard_resets(resets: Sequence[Reset], shard: np.ndarray) -> list[Reset]:
    """The parts of ``resets`` (over all envs) that touch ``shard``, over its envs."""
    parts = []
    for seeds, options in resets:
        shard_options = dict(options)
        mask = shard_options.pop("reset_mask", None)
        if mask is not None:
            if not mask[shard].any():
                continue
            shard_options["reset_mask"] = mask[shard]
        parts.append(([seeds[j] for j in shard], shard_options))
    return parts


class _Failed:
    """A worker's answer when its envs raised: the error, as one line."""

    def __init__(self, error: BaseException) -> None:
        self.line = f"{type(error).__name__}: {' '.join(str(error).split())}"


def _worker(pipe: Any, env_fns: list[Callable[[], gym.Env]]) -> None:
    vec = gym.vector.SyncVectorEnv(env_fns, autoreset_mode=AutoresetMode.DISABLED)
    try:
        while True:
            command, payload = pipe.recv()
            if command == "run":
                pipe.send(_run(vec, *payload))
            elif command == "step":
                obs, reward, terminated, truncated, _ = vec.step(payload)
                pipe.send((obs, reward, terminated, truncated))
            else:
                break
    except KeyboardInterrupt:
        pass
    except Exception as e:  # the caller raises it as one line; the traceback is printed here, where it happened
        traceback.print_exc()
        with contextlib.suppress(OSError):
            pipe.send(_Failed(e))
    finally:
        vec.close()
        pipe.close()


class ShardedVectorEnv(gym.vector.VectorEnv):
    """``len(env_fns)`` envs in ``workers`` processes (contiguous shards), stepped in parallel."""

    metadata = {"autoreset_mode": AutoresetMode.DISABLED}

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], workers: int = 2, context: str = "forkserver"):
        self.num_envs = len(env_fns)
        workers = max(1, min(workers, self.num_envs))
        self.shards = [s for s in np.array_split(np.arange(self.num_envs), workers) if len(s)]
        probe = env_fns[0]()
        self.single_observation_space, self.single_action_space = probe.observation_space, probe.action_space
        probe.close()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        ctx = mp.get_context(context)
        self._pipes, self._processes = [], []
        for shard in self.shards:
            parent, child = ctx.Pipe()
            process = ctx.Process(target=_worker, args=(child, [env_fns[i] for i in shard]), daemon=True)
            process.start()
            child.close()
            self._pipes.append(parent)
            self._processes.append(process)
        self._obs: list[Any] = [None] * len(self.shards)
        self._in_flight: set[int] = set()  # workers sent a command whose answer is not received yet
        self._closed = False

    def reset(self, *, seed: Sequence[int | None] | int | None = None, options: dict[str, Any] | None = None):
        seeds = list(seed) if isinstance(seed, Sequence) else [seed] * self.num_envs
        shards = list(range(len(self.shards)))
        self.send(shards, None, None, [(seeds, dict(options or {}))])
        self.receive(shards)
        if any(o is None for o in self._obs):
            raise RuntimeError("the first reset of a ShardedVectorEnv must reset every env (no reset_mask)")
        return self.observation(), {}

    def step(self, actions: np.ndarray):
        for pipe, shard in zip(self._pipes, self.shards, strict=True):
            pipe.send(("step", actions[shard]))
        results = [self._answer(i) for i in range(len(self._pipes))]
        self._obs = [r[0] for r in results]
        reward, terminated, truncated = (np.concatenate([r[k] for r in results]) for k in (1, 2, 3))
        return _concat(self._obs), reward, terminated, truncated, {}

    def observation(self) -> Any:
        """The batched last observation of every env."""
        return _concat(self._obs)

    def send(
        self, shards: Sequence[int], actions: np.ndarray | None, active: np.ndarray | None, resets: Sequence[Reset]
    ) -> None:
        """Start, in the workers of ``shards`` and without waiting, a chunk of ``actions`` (n, L, A) for the
        ``active`` (n,) of their n envs (none when ``actions`` is None), then the parts of ``resets`` (over all
        envs) that touch them. A shard with nothing to do is sent nothing."""
        offset = 0
        for i in shards:
            n = len(self.shards[i])
            part = None if actions is None else (actions[offset : offset + n], active[offset : offset + n])
            offset += n
            shard_resets = _shard_resets(resets, self.shards[i])
            if part is not None or shard_resets:
                self._pipes[i].send(("run", (*(part or (None, None)), shard_resets)))
                self._in_flight.add(i)

    def receive(self, shards: Sequence[int]) -> Chunk | None:
        """Wait for what :meth:`send` started in ``shards``: the chunk's results over their envs in order (None
        when no chunk was sent); :meth:`observation` then holds their envs' observations after it all."""
        results = {}
        for i in shards:
            if i in self._in_flight:
                self._in_flight.remove(i)
                chunk, obs = self._answer(i)
                results[i] = chunk
                if obs is not None:
                    self._obs[i] = obs
        chunks = [results.get(i) for i in shards]
        if any(c is None for c in chunks):
            return None
        return (
            _concat([c[0] for c in chunks], axis=1),
            np.concatenate([c[1] for c in chunks], 1),
            np.concatenate([c[2] for c in chunks], 1),
        )

    def _answer(self, i: int) -> Any:
        """Worker ``i``'s answer; :class:`EnvWorkerError` if its envs raised or the process is gone."""
        try:
            answer = self._pipes[i].recv()
        except (EOFError, OSError):
            self._processes[i].join(timeout=1)
            raise EnvWorkerError(f"env worker {i} exited (exit code {self._processes[i].exitcode})") from None
        if isinstance(answer, _Failed):
            raise EnvWorkerError(f"env worker {i} failed: {answer.line}")
        return answer

    def close_extras(self, **kwargs: Any) -> None:
        if self._closed:
            return
        self._closed = True
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self._processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()


class ChunkLanes:
    """The envs of ``vec`` as lanes (``slots[lane]``: the env indices of each, contiguous) that run independently:
    two lanes of a :class:`ShardedVectorEnv` (halves of its workers), else one of all envs.

    :meth:`send` starts a lane's chunk (``actions`` (n, L, A) for the ``active`` (n,) of its n envs; none when
    ``actions`` is None) followed by ``resets`` (per-env seeds and options with a ``reset_mask`` over all envs,
    which must lie in the lane), and :meth:`receive` returns the chunk's observations after each step (L, n, ...)
    and ``terminated`` / ``truncated`` (L, n), True only at the step where an active env's episode ended (None
    when no chunk ran); an env is parked right after its end. :meth:`observation` then holds the lane's envs'
    observations after the chunk and the resets. A sharded lane runs in its workers meanwhile, so the caller
    decides another lane's actions while this one simulates and resets; any other vector env runs it in
    :meth:`send`.
    """

    def __init__(self, vec: gym.vector.VectorEnv) -> None:
        self.vec = vec
        if isinstance(vec, ShardedVectorEnv):
            self._shards = [list(g) for g in np.array_split(np.arange(len(vec.shards)), min(2, len(vec.shards)))]
            self.slots = [np.concatenate([vec.shards[i] for i in group]) for group in self._shards]
        else:
            self.slots = [np.arange(vec.num_envs)]
        self._done: dict[int, Chunk | None] = {}
        self._obs: Any = None

    def send(self, lane: int, actions: np.ndarray | None, active: np.ndarray | None, resets: Sequence[Reset]) -> None:
        if isinstance(self.vec, ShardedVectorEnv):
            self.vec.send(self._shards[lane], actions, active, resets)
            return
        chunk, obs = _run(self.vec, actions, active, resets)
        self._done[lane] = chunk
        self._obs = self._obs if obs is None else obs

    def receive(self, lane: int) -> Chunk | None:
        if isinstance(self.vec, ShardedVectorEnv):
            return self.vec.receive(self._shards[lane])
        return self._done.pop(lane)

    def drain(self) -> None:
        """Wait for every lane's work in flight and drop it (workers already gone are passed over)."""
        if isinstance(self.vec, ShardedVectorEnv):
            with contextlib.suppress(EnvWorkerError):
                self.vec.receive(range(len(self.vec.shards)))
        self._done.clear()

    def observation(self) -> Any:
        """The batched last observation of every env, after the lanes' received work."""
        return self.vec.observation() if isinstance(self.vec, ShardedVectorEnv) else self._obs
