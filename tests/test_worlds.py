"""Worlds as registered plugins: ``--world.type=...`` chooses one, ``--tasks`` implies one, a third party adds one
with one registration, the robot's short spellings stay, and a robot stage's spec keeps the keys it had."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from lerobot_robot_piper import PiperFollowerConfig

from lerobot_cso import cli
from lerobot_cso.evaluation import EvalConfig
from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.worlds.base import Rollouts, WorldConfig
from lerobot_cso.worlds.libero.world import LiberoConfig
from lerobot_cso.worlds.metaworld.world import MetaWorld, MetaWorldConfig
from lerobot_cso.worlds.registry import default_world
from lerobot_cso.worlds.robot.config import RobotWorldConfig
from lerobot_cso.worlds.robot.operator import OperatorConfig


def stand_in_policy(tasks: list[str]) -> CSOConfig:
    policy = CSOConfig(tasks=tasks, device="cpu")
    policy.pretrained_path = Path("/nonexistent/pretrained_model")
    return policy


@pytest.mark.parametrize("stage", ["eval", "rsft", "spo", "pipeline"])
def test_world_type_is_in_every_rollout_stages_help(stage, capsys, monkeypatch, tmp_path):
    """Made (LeRobot's help exits), then kept (printed from the cache): both list the worlds."""
    monkeypatch.setattr("sys.argv", ["lerobot-cso"])
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    for _ in range(2):
        try:
            code = cli.main([stage, "--help"])
        except SystemExit as e:
            code = e.code
        assert code in (0, None)
        out = capsys.readouterr().out
        assert "--world.type" in out and all(name in out for name in ("metaworld", "libero", "robot"))


def test_the_tasks_imply_the_world_and_the_registry_holds_the_three():
    assert {"metaworld", "libero", "robot"} <= set(WorldConfig.get_known_choices())
    assert isinstance(default_world("MT10"), MetaWorldConfig)
    assert isinstance(default_world("libero_spatial,libero_goal-3"), LiberoConfig)
    assert isinstance(default_world("libero_goal-0,reach-v3"), MetaWorldConfig)  # not LIBERO's alone


def test_the_robots_short_spellings_are_the_robot_worlds_settings():
    args = ["--policy.path=P", "--robot.type=piper_follower", "--operator.fps=30", "--display_data=true"]
    assert cli.robot_world_args(args) == [
        "--world.type=robot",
        "--policy.path=P",
        "--world.robot.type=piper_follower",
        "--world.operator.fps=30",
        "--world.display_data=true",
    ]
    spelt = ["--world.type=robot", "--teleop.type", "piper_leader"]
    assert cli.robot_world_args(spelt) == ["--world.type=robot", "--world.teleop.type", "piper_leader"]
    assert cli.robot_world_args(["--tasks=MT10"]) == ["--tasks=MT10"]
    assert cli.robot_world_args(["--tasks", "robot"]) == ["--tasks", "robot"]  # a value, not a setting


def test_a_robot_stages_spec_has_the_keys_it_had_before_worlds():
    """Resumption keys must not change: a robot stage's spec names the robot's type, the teleop and the operator
    at the top level, and no ``world``; the display is not part of it."""
    world = RobotWorldConfig(robot=PiperFollowerConfig(channel="can7"), operator=OperatorConfig(fps=30))
    cfg = EvalConfig(world=world, tasks="pick", policy=stand_in_policy(["pick"]), output_dir=Path("/tmp/x"))
    spec = cfg.stage_spec()
    assert set(spec) == {
        "sampling",
        "num_envs",
        "vectorization",
        "max_steps",
        "robot",
        "teleop",
        "operator",
        "episodes_per_task",
        "seeds",
        "video_episodes",
    }
    assert spec["robot"] == {"type": "piper_follower"} and spec["teleop"] is None and spec["operator"]["fps"] == 30
    shown = dataclasses.replace(cfg, world=dataclasses.replace(world, display_data=True))
    assert shown.stage_spec() == spec


class ToyWorld:
    """Two tasks, states 0.. for every purpose; no backend needed here."""

    name = "toy"
    robot_type = "toy"
    fps = 10
    horizon = 20
    eval_seeds = 1
    eval_states_per_seed = 100

    def resolve_tasks(self, spec: str) -> list[str]:
        if spec not in ("left", "right"):
            raise ValueError(f"unknown toy task '{spec}'; valid: left, right")
        return [spec]

    def task_description(self, task: str) -> str:
        return f"go {task}"

    def training_states(self, task: str, purpose: str, start: int, count: int) -> list[int]:
        return list(range(start, start + count))

    def eval_states(self, task: str, eval_seed: int, count: int) -> list[int]:
        return list(range(count))

    def backend(self, rollouts: Rollouts) -> Any:
        raise NotImplementedError


def test_a_third_partys_world_is_one_registration(tmp_path):
    @WorldConfig.register_subclass("toy")
    @dataclass
    class ToyConfig(WorldConfig):
        @classmethod
        def claims(cls, tasks: str) -> bool:
            return tasks in ("left", "right")

        def build(self, tasks: str, policy: Any, output_dir: Path | None) -> ToyWorld:
            return ToyWorld()

    try:
        assert isinstance(default_world("left"), ToyConfig)
        cfg = EvalConfig(world=ToyConfig(), tasks="left", policy=stand_in_policy(["go left"]), output_dir=tmp_path)
        assert (
            cfg.validate() == ["left"]
            and cfg.horizon() == 20
            and cfg.stage_spec() == dataclasses.replace(cfg, world=None).stage_spec()
        )
        assert isinstance(dataclasses.replace(cfg, world=None, tasks="MT10").rollout_world(), MetaWorld)
    finally:
        del WorldConfig.get_known_choices()["toy"]


def test_a_config_recorded_before_the_robot_settings_moved_into_the_world_is_the_same_spec():
    """Benchmarks record a whole pipeline config (``benchmarks/mw_proxy.py``): its rollout sections held
    ``robot``, ``teleop``, ``operator`` and ``display_data`` before they moved into the robot world."""
    from lerobot_cso.pipeline import PipelineConfig
    from lerobot_cso.stage import settings_spec, without_added_settings

    now = settings_spec(PipelineConfig())
    before = {k: v for k, v in now.items() if k != "world"}
    for section in ("eval", "rsft", "spo"):
        moved = {"robot": None, "teleop": None, "operator": settings_spec(OperatorConfig()), "display_data": False}
        before[section] = {k: v for k, v in now[section].items() if k != "world"} | moved
    assert without_added_settings(before) == without_added_settings(now)
    assert without_added_settings(settings_spec({"operator": OperatorConfig()})) == {}  # the default is the old one
