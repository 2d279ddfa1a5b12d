"""Scale-out with ``accelerate`` / ``torch.distributed``: every process rolls out its share, all see the result.

Launch any rollout stage on N processes (one env pool and policy replica each)::

    accelerate launch --multi_gpu --num_processes N -m lerobot_cso.cli spo ...   # also on CPUs (gloo)

* **Rollouts** (:class:`ShardedRollouts`): of the initial states of one rollout call, process ``r`` runs the
  groups ``r, r + N, r + 2N, ...`` on its own backend and sampling stream, then every episode is gathered to
  every process, in request order. Which states a stage uses never depends on N (they come from its world),
  so seed ranges stay disjoint and a run resumes with another N.
* **Training steps** (:func:`accelerator_for`, :func:`step_meters`): R-SFT and SPO both step with LeRobot's
  ``update_policy`` (as ``lerobot-train``) under one ``Accelerator``: DDP averages the gradients over the
  processes, so a loss that is each process's share of its batch is scaled by the process count (SPO's
  objective) or is a mean over equal shards (R-SFT's): every replica takes the same step as one process.
* **Writes**: only the main process writes checkpoints, buffers and logs (:func:`is_main`); the others wait.

With one process (plain ``lerobot-cso ...``) every function here is the identity.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from typing import Any

import torch
from accelerate import Accelerator, DistributedDataParallelKwargs, PartialState
from accelerate.utils import gather_object
from lerobot.utils.logging_utils import AverageMeter

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
        round_id: int | None = None,
    ) -> RolloutResult:
        """As :meth:`RolloutEngine.rollout`; ``on_episode`` runs on the main process, for every episode."""
        states = [InitialState(*s) for s in initial_states]
        if self.world_size == 1:
            return self.engine.rollout(
                states, k, sampling, seed, progress, on_episode, stop_after, keep_frames, round_id
            )
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
                round_id,
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


def accelerator_for(policy: torch.nn.Module) -> Accelerator:
    """The ``Accelerator`` a training stage steps under with LeRobot's ``update_policy``: DDP over the processes of
    ``accelerate launch`` (none with one process). Parameters that take no part in a loss are allowed: the skill
    autoencoder in Eq. 6 and in SPO's objective, the encoders when frozen."""
    ddp = DistributedDataParallelKwargs(find_unused_parameters=True)
    return Accelerator(cpu=policy.config.device == "cpu", kwargs_handlers=[ddp])


def step_meters() -> dict[str, AverageMeter]:
    """Fresh meters for a ``MetricsTracker`` of ``update_policy`` steps (a tracker adds the loss's own outputs to
    this dict, and a later tracker would treat those as the caller's and never update them)."""
    meters = {"loss": AverageMeter("loss", ":.4f"), "grad_norm": AverageMeter("grdn", ":.3f")}
    meters |= {"lr": AverageMeter("lr", ":0.1e"), "update_s": AverageMeter("updt_s", ":.3f")}
    if torch.cuda.is_available():  # update_policy then records the peak GPU memory, as lerobot-train
        meters["gpu_mem_gb"] = AverageMeter("mem_gb", ":.2f", reduction="max")
    return meters


def weighted_mean(values: dict[str, float], weight: float) -> dict[str, float]:
    """Each value's mean over all processes, weighted by each process's ``weight`` (a process with weight 0
    contributes nothing and may pass ``{}``)."""
    if state().num_processes == 1:
        return values
    rows = [(w, v) for w, v in gather_object([(weight, values)]) if w > 0]
    total = sum(w for w, _ in rows)
    return {key: sum(w * v[key] for w, v in rows) / total for key in rows[0][1]}
