"""The episode journal a backend can keep: every finished episode (a :class:`~lerobot_cso.rollout.backend.Trace`) on
disk the moment it ends, so that a rerun of the same jobs replays them instead of running them again.

An attempt is a job's try at its initial state: the jobs of one ``(task, initial state)`` are attempts 1, 2, ... in
request order; a job with a ``round_id`` (a state the caller draws again in later rounds) names its round too, so a
later round's attempts are run, not replayed from an earlier round's. Each attempt is one ``.npz`` of a
:class:`~lerobot_cso.durable.EpisodeJournal` (states, actions, outcome, camera frames, the controller's record); tries
that were discarded are noted beside it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lerobot_cso.durable import EpisodeJournal
from lerobot_cso.rollout.backend import Job, Trace


def _slug(task: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", task).strip("_") or "task"


def numbered(jobs: Sequence[Job]) -> list[tuple[int, Job, int, int]]:
    """``(index, job, attempt, attempts)`` of each job: its attempt at its initial state (from 1) and how many
    attempts the request holds for that state."""
    attempts: dict[tuple[str, int], int] = {}
    numbers = []
    for job in jobs:
        attempts[job.task, job.init_seed] = attempts.get((job.task, job.init_seed), 0) + 1
        numbers.append(attempts[job.task, job.init_seed])
    return [(i, job, numbers[i], attempts[job.task, job.init_seed]) for i, job in enumerate(jobs)]


class TraceJournal:
    """Finished attempts and the discarded tries of each, under ``root`` (see the module doc)."""

    def __init__(self, root: Path, spec: dict[str, Any], what: str) -> None:
        self.root = root
        self.journal = EpisodeJournal(root, spec, what=what)

    def _name(self, job: Job, attempt: int) -> tuple[str, str]:
        round_part = "" if job.round_id is None else f"r{job.round_id}_"
        return _slug(job.task), f"{job.init_seed:07d}_{round_part}{attempt:03d}"

    def has(self, job: Job, attempt: int) -> bool:
        """Whether the attempt is finished and on disk."""
        return self.journal.episode_path(*self._name(job, attempt)).is_file()

    def load(self, job: Job, attempt: int) -> Trace:
        data = EpisodeJournal.load(self.journal.episode_path(*self._name(job, attempt)))
        return Trace(
            job=job,
            success=bool(data["success"]),
            length=int(data["length"]),
            states=data["states"],
            actions=data["actions"],
            images={k.removeprefix("image_"): v for k, v in data.items() if k.startswith("image_")},
            record={k.removeprefix("record_"): torch.from_numpy(v) for k, v in data.items() if k.startswith("record_")},
        )

    def save(self, attempt: int, trace: Trace) -> None:
        arrays = {"states": trace.states, "actions": trace.actions, "success": np.bool_(trace.success)}
        arrays |= {"length": np.int64(trace.length)}
        arrays |= {f"image_{cam}": frames for cam, frames in trace.images.items()}
        arrays |= {f"record_{k}": v.numpy() for k, v in (trace.record or {}).items()}
        self.journal.save_episode(*self._name(trace.job, attempt), arrays)

    def discards(self, job: Job, attempt: int) -> list[str]:
        """Why each earlier try of the attempt was discarded, in order."""
        group, name = self._name(job, attempt)
        return self.journal.records(group).get(name, {}).get("discarded", [])

    def discard(self, job: Job, attempt: int, reason: str) -> None:
        group, name = self._name(job, attempt)
        self.journal.save_record(group, name, {"discarded": [*self.discards(job, attempt), reason]})
