"""The env protocol of the pool (:class:`~lerobot_cso.rollout.pool.EnvPool`), as a base class.

A :class:`PoolEnv` runs one task at a time and switches task on reset; ``reset(seed=s)`` starts an episode from
initial state ``s`` (its meaning is the world's own). Reset options:

- ``task``: switch to this task first;
- ``park``: park the env: until its next real reset it does no simulation and every step returns the last
  observation (the pool parks a slot that has no episode left to run);
- ``render_every``: render cameras only on every k-th step of the episode (the decision steps of a policy
  acting in chunks of k); the other steps repeat the last frame.

An episode terminates at its first success (``info["is_success"]``) and is truncated after
``_max_episode_steps`` steps. Observations are LeRobot's gym format: ``agent_pos`` and, with cameras,
``pixels = {camera: uint8 (H, W, 3)}``. A world's env implements :meth:`_set_task`, :meth:`_restart`,
:meth:`_advance` and :meth:`_observe`; this class keeps the step count, the parking and the render cadence.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def zeros(space: spaces.Space) -> Any:
    """An all-zero observation of a (nested dict of) Box space."""
    if isinstance(space, spaces.Dict):
        return {key: zeros(sub) for key, sub in space.items()}
    return np.zeros(space.shape, space.dtype)


class PoolEnv(gym.Env):
    """One task at a time, switchable on reset; parkable; cameras rendered every ``render_every`` steps."""

    _max_episode_steps: int

    def __init__(self) -> None:
        super().__init__()
        self._t = 0  # steps of the current episode
        self._parked = False
        self._render_every = 1
        self._last_obs: dict[str, Any] | None = None

    def _set_task(self, task: str) -> None:
        """Switch to ``task`` (``ValueError`` naming the valid tasks when unknown)."""
        raise NotImplementedError

    def _restart(self, seed: int | None) -> Any:
        """Reset the simulation to initial state ``seed``; returns its raw observation."""
        raise NotImplementedError

    def _advance(self, action: np.ndarray) -> tuple[Any, float, bool]:
        """Simulate one step: the raw observation, the reward, whether the task is solved."""
        raise NotImplementedError

    def _observe(self, raw: Any) -> dict[str, Any]:
        """The observation of ``raw`` after ``self._t`` steps (cameras as the render cadence asks)."""
        raise NotImplementedError

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Start an episode from initial state ``seed`` (options: ``task``, ``park``, ``render_every``)."""
        super().reset(seed=seed)
        options = options or {}
        if options.get("park"):
            self._parked = True
            if self._last_obs is None:  # parked before its first episode: a blank observation
                self._last_obs = zeros(self.observation_space)
            return self._last_obs, {"is_success": False}
        if "task" in options:
            self._set_task(options["task"])
        raw = self._restart(seed)
        self._t = 0
        self._parked = False
        self._render_every = max(1, int(options.get("render_every", 1)))
        self._last_obs = self._observe(raw)
        return self._last_obs, {"is_success": False}

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """Apply one action; terminated on success, truncated at ``_max_episode_steps``."""
        if self._parked:
            return self._last_obs, 0.0, False, False, {"is_success": False}
        raw, reward, success = self._advance(action)
        self._t += 1
        self._last_obs = self._observe(raw)
        truncated = not success and self._t >= self._max_episode_steps
        return self._last_obs, float(reward), success, truncated, {"is_success": success}
