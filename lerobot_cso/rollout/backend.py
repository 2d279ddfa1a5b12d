"""The rollout backend interface: a world that runs a queue of episodes under one controller.

A backend knows its world (MetaWorld vector envs, LIBERO, a LeRobot robot with an operator); the
controller knows the policy. The flow is one-way: the engine hands jobs and a controller to the backend,
the backend calls the controller for actions and yields each finished episode as a :class:`Trace`.

Observations reach the controller in LeRobot's gym format: ``{"agent_pos": (num_envs, S)}`` plus, with
cameras, ``{"pixels": {camera: (num_envs, H, W, 3) uint8}}``; actions are unnormalised, ``(num_envs, A)``
or a chunk ``(num_envs, L, A)`` executed open-loop.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np


@dataclass(frozen=True)
class Job:
    """One episode to run: a task, the initial state's id in its world, and the caller's handle for it;
    ``keep_frames`` asks a backend that records no camera frames (only decisions are rendered) for this
    episode's frames (e.g. for a video). ``round_id`` names the caller's round where one initial state recurs
    across rounds (SPO's state pool): a journal keeps each round's attempts apart."""

    task: str
    init_seed: int
    key: Any = None
    keep_frames: bool = False
    round_id: int | None = None


@dataclass
class Trace:
    """What a backend records for a finished episode (``states[t]`` is the input of ``actions[t]``)."""

    job: Job
    success: bool
    length: int
    states: np.ndarray  # (length, S) float32
    actions: np.ndarray  # (length, A) float32, as executed
    images: dict[str, np.ndarray] = field(default_factory=dict)  # camera -> (length, H, W, 3) uint8
    record: Any = None  # whatever the controller returned from ``finish``


@dataclass(frozen=True)
class ActiveSkill:
    """The skill a slot is executing: its index among the episode's decisions (0 = the first), the step it
    was chosen at, and its tokens."""

    index: int
    step: int
    tokens: tuple[int, ...]


class Controller(Protocol):
    """Chooses the actions of every slot of a backend."""

    def start(self, slot: int, job: Job) -> None:
        """A new episode begins in ``slot``."""

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        """Actions ``(num_envs, A)``, or a chunk ``(num_envs, L, A)`` executed open-loop, for the batched
        observation; rows where ``active`` is False are ignored."""

    def finish(self, slot: int) -> Any:
        """The episode in ``slot`` ended; return the controller's record of it (or None)."""

    def current_skill(self, slot: int) -> ActiveSkill | None:
        """The skill ``slot`` is executing; None before its first decision, or for a controller without skills."""


class RolloutBackend(Protocol):
    """Runs jobs to their end under a controller; what R-SFT, SPO and evaluation roll out on."""

    num_envs: int  # slots stepped together (one policy batch)

    def run(
        self,
        jobs: Sequence[Job],
        controller: Controller,
        start_every: int = 1,
        progress: str | None = None,
        skip: Callable[[Job], bool] | None = None,
    ) -> Iterator[tuple[int, Trace]]:
        """Yield ``(job index, trace)`` as each episode finishes. Episodes start only on steps that are
        multiples of ``start_every``, so every running episode decides on the same steps. A job for which
        ``skip(job)`` is True when its turn to start comes is not run and yields nothing."""

    def close(self) -> None:
        """Release the world (env processes, the robot)."""
