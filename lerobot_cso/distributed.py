"""Scale-out with ``accelerate`` / ``torch.distributed``: every process rolls out its share, all see the result.

Launch any rollout stage on N processes (one env pool and policy replica each)::

    accelerate launch --multi_gpu --num_processes N -m lerobot_cso.cli spo ...   # also on CPUs (gloo)

* **Rollouts** (:class:`ShardedRollouts`): of the initial states of one rollout call, process ``r`` runs the
  groups ``r, r + N, r + 2N, ...`` on its own backend and sampling stream, then every episode is gathered to
  every process, in request order. Which states a stage uses never depends on N (they come from its world),
  so seed ranges stay disjoint and a run resumes with another N.
* **Prior updates** (:func:`all_reduce_gradients`): each process back-propagates its rows of every
  minibatch, its loss divided by the whole minibatch's unit count, and the gradients are summed over the
  processes: the sum is the whole minibatch's gradient, so every replica takes the same step as one process.
* **Writes**: only the main process writes checkpoints, buffers and logs (:func:`is_main`); the others wait.

With one process (plain ``lerobot-cso ...``) every function here is the identity.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from typing import Any

import torch
from accelerate import PartialState
from accelerate.utils import gather_object

from lerobot_cso import seeds
from lerobot_cso.rollout.engine import Episode, InitialState, RolloutResult
from lerobot_cso.sampling import Sampling


def state() -> PartialState:
    """This process's place in the run (initialises torch.distributed under ``accelerate launch``)."""
    return PartialState(cpu=not torch.cuda.is_available())


def is_main() -> bool:
    return state().is_main_process


def wait_for_everyone() -> None:
    state().wait_for_everyone()


class ShardedRollouts:
    """Wraps a rollout engine: each process rolls out its share of the groups; every process gets all of them."""

    def __init__(self, engine: Any) -> None:
        self.engine = engine
        self.rank, self.world_size = state().process_index, state().num_processes

    def rollout(
        self,
        initial_states: Sequence[InitialState | tuple[str, int]],
        k: int = 1,
        sampling: Sampling = Sampling(),  # noqa: B008  (frozen dataclass, as in RolloutEngine.rollout)
        seed: int = 0,
        progress: str | None = None,
        on_episode: Callable[[Episode], None] | None = None,
        stop_after: int | None = None,
        keep_frames: Collection[int] = (),
    ) -> RolloutResult:
        """As :meth:`RolloutEngine.rollout`; ``on_episode`` runs on the main process, for every episode."""
        states = [InitialState(*s) for s in initial_states]
        if self.world_size == 1:
            return self.engine.rollout(states, k, sampling, seed, progress, on_episode, stop_after, keep_frames)
        mine = list(range(self.rank, len(states), self.world_size))
        local = (
            self.engine.rollout(
                [states[g] for g in mine],
                k,
                sampling,
                seeds.round_seed(seed, self.rank),
                progress,
                None,
                stop_after,
                [i for i, g in enumerate(mine) if g in keep_frames],
            )
            if mine
            else None
        )
        shards = gather_object([(mine, local)])
        episodes: list[Episode] = []
        seconds = policy_seconds = 0.0
        for groups, result in shards:
            if result is None:
                continue
            seconds, policy_seconds = max(seconds, result.seconds), max(policy_seconds, result.policy_seconds)
            for episode in result.episodes:
                episode.group = groups[episode.group]
                episodes.append(episode)
        episodes.sort(key=lambda e: (e.group, e.sample))
        if on_episode is not None and self.rank == 0:
            for episode in episodes:
                on_episode(episode)
        return RolloutResult(episodes, k, sampling, seconds, policy_seconds)

    def __enter__(self) -> ShardedRollouts:
        self.engine.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.engine.__exit__(*exc)


def shard_rows(n: int) -> slice:
    """This process's rows of a minibatch of ``n`` (every process holds the same minibatch)."""
    s = state()
    return slice(s.process_index, n, s.num_processes)


def all_reduce_gradients(parameters: Sequence[torch.nn.Parameter]) -> None:
    """Sum the gradients of ``parameters`` over all processes (each process scales its loss so the sum is the
    minibatch's gradient); a no-op with one process."""
    if state().num_processes == 1:
        return
    for p in parameters:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        torch.distributed.all_reduce(p.grad)


def weighted_mean(values: dict[str, float], weight: float) -> dict[str, float]:
    """Each value's mean over all processes, weighted by each process's ``weight`` (a process with weight 0
    contributes nothing and may pass ``{}``)."""
    if state().num_processes == 1:
        return values
    rows = [(w, v) for w, v in gather_object([(weight, values)]) if w > 0]
    total = sum(w for w, _ in rows)
    return {key: sum(w * v[key] for w, v in rows) / total for key in rows[0][1]}
