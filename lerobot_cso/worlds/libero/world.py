"""The LIBERO world: the benchmark's five suites, rolled out on LeRobot's ``LiberoEnv`` through the env pool.

``--tasks`` takes suites (``libero_spatial``, ``libero_object``, ``libero_goal``, ``libero_10``, ``libero_90``),
single tasks ``<suite>-<index>``, or a comma list of both. The paper's protocol (App. E, as LIBERO and QueST
evaluate):

- **evaluation** runs on the benchmark's fixed init states: episode ``i`` of a task starts from init state
  ``i`` (50 per task), and every evaluation seed (3 by default) reuses the same 50 states, the seed changing
  the policy's sampling and the simulator's seed;
- **training rollouts** (R-SFT, SPO) start from placements drawn from each task's BDDL regions with the seeds of
  :mod:`lerobot_cso.seeds`' training ranges (R-SFT and SPO disjoint), so they never reuse an evaluation
  state;
- each episode is capped at its suite's standard horizon (LeRobot's ``TASK_SUITE_MAX_STEPS``: 280 spatial and
  object, 300 goal, 520 libero_10, 400 libero_90) unless ``--max_steps`` caps it lower.

Cameras render at the resolution of the policy's image inputs (128 without cameras in the policy). Stages
whose settings say ``records_frames = False`` (evaluation, SPO: they keep only the policy's contexts) render
only the decision steps' frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import Any

from lerobot_cso import seeds
from lerobot_cso.rollout.backend import RolloutBackend
from lerobot_cso.rollout.pool import open_pool
from lerobot_cso.worlds.base import DemoExpert, Purpose, Rollouts, WorldConfig, image_size_of

SUITE_PREFIX = "libero_"
EVAL_SEEDS = 3  # the paper's three evaluation seeds
DEFAULT_HORIZON = 500  # LeRobot's LIBERO default for a suite it does not know


def _env() -> ModuleType:
    """:mod:`lerobot_cso.worlds.libero.env` (configures LIBERO offline on import); ``ValueError`` if not installed."""
    from lerobot_cso.worlds.libero.setup import INSTALL_HINT, LiberoSetupError

    try:
        from lerobot_cso.worlds.libero import env as libero_env
    except LiberoSetupError as e:
        raise ValueError(str(e)) from None
    except ImportError as e:  # a LIBERO (or a package it needs) of another layout or version; not our own modules
        if (e.name or "").startswith("lerobot_cso"):
            raise
        raise ValueError(f"LIBERO cannot be imported ({e}): {INSTALL_HINT}") from None
    return libero_env


class Libero:
    """LIBERO: fixed benchmark init states for evaluation, sampled placements for training rollouts."""

    name = "libero"
    robot_type = "panda"
    fps = 20
    eval_seeds = EVAL_SEEDS
    eval_states_per_seed = 50

    def __init__(self, tasks: str) -> None:
        self.spec = tasks

    @property
    def state_dims(self) -> tuple[int, ...]:
        return (_env().STATE_DIM,)

    @property
    def action_dim(self) -> int:
        return _env().ACTION_DIM

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(_env().CAMERAS)

    @property
    def horizon(self) -> int:
        """The longest standard horizon of the suites the spec names."""
        env = _env()
        suites = {t.strip().rpartition("-")[0] or t.strip() for t in self.spec.split(",") if t.strip()}
        return max((env.TASK_SUITE_MAX_STEPS.get(s, DEFAULT_HORIZON) for s in suites), default=DEFAULT_HORIZON)

    def resolve_tasks(self, spec: str) -> list[str]:
        env = _env()
        tasks: list[str] = []
        for item in (t.strip() for t in spec.split(",") if t.strip()):
            if item in env.SUITES:
                tasks += [f"{item}-{i}" for i in range(len(env.suite(item).tasks))]
            else:
                env.parse_task(item)
                tasks.append(item)
        if not tasks:
            raise ValueError(f"no LIBERO tasks in '{spec}'; suites: {', '.join(env.SUITES)}")
        return list(dict.fromkeys(tasks))

    def task_description(self, task: str) -> str:
        return _env().task_description(task)

    def training_states(self, task: str, purpose: Purpose, start: int, count: int) -> list[int]:
        return seeds.training_seeds(purpose, start, count)

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        if not 0 <= eval_seed < EVAL_SEEDS or count > self.eval_states_per_seed:
            raise ValueError(f"LIBERO has {self.eval_states_per_seed} fixed init states per task, seeds 0..2")
        return list(range(count))

    def backend(self, rollouts: Rollouts) -> RolloutBackend:
        env = _env()
        image_size = image_size_of(rollouts.features, env.IMAGE_SIZE)
        first = self.resolve_tasks(self.spec)[0]  # each job resets its slot onto its own task
        # max_steps None: each task's suite horizon
        factory = partial(env.CSOLiberoEnv, first, rollouts.cameras, image_size, rollouts.max_steps)
        return open_pool(
            rollouts.num_envs,
            rollouts.cameras,
            env_factory=factory,
            check_task=env.parse_task,
            vectorization=rollouts.vectorization,
            frames=rollouts.frames,
        )


@WorldConfig.register_subclass("libero")
@dataclass
class LiberoConfig(WorldConfig):
    """LIBERO (``--tasks``: suites, ``<suite>-<index>`` tasks, or a comma list of both); the world of a
    ``--tasks`` that names only LIBERO tasks."""

    @classmethod
    def claims(cls, tasks: str) -> bool:
        """Whether a ``--tasks`` spec names LIBERO tasks (checked without importing LIBERO)."""
        items = [t.strip() for t in tasks.split(",") if t.strip()]
        return bool(items) and all(t.startswith(SUITE_PREFIX) for t in items)

    def demo_expert(self) -> DemoExpert:
        """The pick-and-place expert (expert.py, demos.py); ``ValueError`` when LIBERO is not installed."""
        _env()
        from lerobot_cso.worlds.libero.demos import LiberoDemos

        return LiberoDemos()

    def build(self, tasks: str, policy: Any, output_dir: Path | None) -> Libero:
        return Libero(tasks)
