"""The settings every rollout stage shares (evaluation, R-SFT, SPO), checked by one ``validate()``.

A rollout stage rolls a saved policy out on the tasks of one world (:mod:`lerobot_cso.rollout.world`):
``--tasks`` names them, ``--sampling.temperature/top_k/greedy`` say how skills are drawn, ``--num_envs``,
``--vectorization`` and ``--max_steps`` shape the rollouts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from lerobot_cso.checkpoints import PolicyPathConfig
from lerobot_cso.errors import UsageError
from lerobot_cso.rollout.engine import Sampling
from lerobot_cso.rollout.pool import VECTORIZATIONS
from lerobot_cso.rollout.world import World, world_for


@dataclass
class RolloutStageConfig(PolicyPathConfig):
    """Base of ``EvalConfig``, ``RSFTConfig`` and ``SPOConfig``."""

    # What --policy.path must point at, for the error message when it is missing.
    policy_role: ClassVar[str] = "a directory written by save_pretrained"

    # One task, a comma list, or a set of the world (MetaWorld: MT10, MT50, ML45-train, ML45-test).
    tasks: str = "MT10"
    output_dir: Path | None = None
    sampling: Sampling = field(default_factory=Sampling)
    num_envs: int = 16
    # processes (envs split over one worker process per core) | sync (this process) | async (a process per env)
    vectorization: str = "processes"
    # Episode cap of the rollouts (a failure runs to the cap); null: the world's horizon.
    max_steps: int | None = None

    def world(self) -> World:
        """The world the tasks belong to."""
        return world_for(self.tasks)

    def horizon(self) -> int:
        """The episode cap of the rollouts: ``max_steps``, or the world's horizon."""
        return self.world().horizon if self.max_steps is None else self.max_steps

    def validate(self) -> list[str]:
        """Check the shared settings; returns the resolved task list. Raises ``UsageError``."""
        if self.policy is None or self.policy.pretrained_path is None:
            raise UsageError(f"--policy.path is required ({self.policy_role})")
        world = self.world()
        try:
            tasks = world.resolve_tasks(self.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        if self.num_envs < 1:
            raise UsageError(f"num_envs must be >= 1, got {self.num_envs}")
        if self.vectorization not in VECTORIZATIONS:
            raise UsageError(f"vectorization must be one of {', '.join(VECTORIZATIONS)}, got '{self.vectorization}'")
        if self.max_steps is not None and not 1 <= self.max_steps <= world.horizon:
            raise UsageError(f"max_steps must be in [1, {world.horizon}], got {self.max_steps}")
        s = self.sampling
        if s.temperature <= 0 or (s.top_k is not None and s.top_k < 1):
            raise UsageError("sampling.temperature must be > 0 and sampling.top_k >= 1 (or null)")
        known = getattr(self.policy, "tasks", None)  # the task strings a language/one-hot policy was trained on
        unknown = [t for t in tasks if known and world.task_description(t) not in known]
        if unknown:
            raise UsageError(
                f"the policy was not trained on {', '.join(unknown)}; it knows: {'; '.join(map(repr, known))}"
            )
        return tasks
