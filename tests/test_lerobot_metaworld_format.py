"""LeRobot's own MetaWorld format as a dataset (issue 33, item 1), written by ``lerobot-cso demos --format=lerobot``:
a 480² ``corner2`` ``observation.image`` stored as video plus the 4-d hand ``observation.state``, trained with the
real ``lerobot-train`` (the frames resized inside the policy) and rolled out in our MetaWorld world, whose env gives
it LeRobot's view of the same camera; the pipeline's dataset check accepts it, R-SFT's buffer holds the policy's own
inputs, ``eval`` films it, and the whole ``lerobot-cso pipeline`` runs on such a dataset."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from cso_fakes import TASKS, ScriptedEngine, mixed, saved_weights
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from safetensors.torch import load_file
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso import cli
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso import rsft
from lerobot_cso.demos import DemosConfig, check_dataset, generate_demos
from lerobot_cso.errors import UsageError
from lerobot_cso.policy import CSOConfig, CSOPolicy
from lerobot_cso.rollout.engine import RolloutEngine
from lerobot_cso.worlds.base import Rollouts, camera_inputs
from lerobot_cso.worlds.metaworld.constants import LEROBOT_CAMERA
from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.metaworld.world import MetaWorld, env_inputs

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
TASK = "reach-v3"
REPO = "local/lerobot_metaworld"
SIZE = 480  # LeRobot's MetaWorld frames
RESIZE = 32  # what the tiny policies' encoders read
DEFAULT_FIT = 128  # what a policy with no image setting reads


def make_lerobot_metaworld_dataset(
    root: Path, episodes: int = 2, length: int = 12, size: int = SIZE, task: str = TASK
) -> LeRobotDataset:
    """Scripted-expert episodes of ``task`` (at most ``length`` frames) in LeRobot's MetaWorld format, written by
    ``lerobot-cso demos --format=lerobot``."""
    settings = {"episodes_per_task": episodes, "max_steps": length, "image_size": size, "noise_std": 0.1}
    generate_demos(DemosConfig(format="lerobot", tasks=task, num_envs=1, output_dir=root, repo_id=REPO, **settings))
    return LeRobotDataset(REPO, root=root, video_backend="pyav")


def test_demos_writes_lerobots_own_metaworld_format_and_tops_it_up_without_duplicates(tmp_path, capsys, monkeypatch):
    """``lerobot-cso demos --format=lerobot`` writes what LeRobot's metaworld env gives a policy, by LeRobot's own
    constants: its keys and shapes and nothing else, its fps, its task description, its view of ``corner2`` and its
    4-d state at the episode's initial state; a second run tops it up with the missing episode only, and the
    cso format is refused on it. (The runs that render are subprocesses: this process renders LeRobot's env.)"""
    from lerobot.envs.configs import MetaworldEnv as LeRobotMetaworldConfig
    from lerobot.envs.metaworld import TASK_DESCRIPTIONS, MetaworldEnv
    from lerobot.utils.constants import DEFAULT_FEATURES

    root = tmp_path / "data"
    demos = [str(BIN / "lerobot-cso"), "demos", f"--tasks={TASK}", "--max_steps=3", f"--output_dir={root}"]
    args = [*demos, "--format=lerobot", "--num_envs=1"]
    proc = subprocess.run([*args, "--episodes_per_task=1"], capture_output=True, text=True, env=ENV, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    theirs = LeRobotMetaworldConfig(task=TASK)
    wanted = {theirs.features_map[key]: tuple(ft.shape) for key, ft in theirs.features.items()}
    ds = LeRobotDataset(REPO, root=root, video_backend="pyav")
    features = {key: tuple(ft["shape"]) for key, ft in ds.meta.features.items() if key not in DEFAULT_FEATURES}
    assert features == wanted == {"observation.image": (480, 480, 3), "observation.state": (4,), "action": (4,)}
    assert ds.meta.video_keys == ["observation.image"] and ds.fps == theirs.fps
    assert list(ds.meta.tasks.index) == [TASK_DESCRIPTIONS[TASK]] and ds.num_frames == 3
    [[task, seed, _]] = json.loads((root / "meta" / "cso_episodes.json").read_text())
    env = MetaworldEnv(TASK, obs_type="pixels_agent_pos")
    obs, _ = env.reset(seed=seed)
    env.close()
    first = ds[0]
    np.testing.assert_allclose(first["observation.state"].numpy(), obs["agent_pos"], atol=1e-6)
    frame = (first["observation.image"].permute(1, 2, 0).numpy() * 255).astype(int)
    same, turned = np.abs(frame - obs["pixels"]).mean(), np.abs(frame - obs["pixels"][::-1, ::-1]).mean()
    assert task == TASK and same < 15 and 3 * same < turned, (same, turned)
    before = ds.hf_dataset.with_format("numpy")["action"][:]

    proc = subprocess.run([*args, "--episodes_per_task=2"], capture_output=True, text=True, env=ENV, timeout=300)
    assert proc.returncode == 0 and proc.stdout.splitlines()[-2] == f"{root}: 2 episodes (1 new)", proc.stderr[-3000:]
    ds = LeRobotDataset(REPO, root=root, video_backend="pyav")
    episodes = json.loads((root / "meta" / "cso_episodes.json").read_text())
    assert ds.num_episodes == len(episodes) == len({(t, s) for t, s, _ in episodes}) == 2 and ds.num_frames == 6
    np.testing.assert_array_equal(ds.hf_dataset.with_format("numpy")["action"][:3], before)
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    assert cli.main(demos[1:]) == 2  # the default format, cso: refused before any env is built
    err = capsys.readouterr().err
    assert "holds a different dataset" in err and "'format': ('lerobot', None)" in err


def test_config_files_written_before_a_setting_load_with_its_default_of_their_day(tmp_path):
    """A config.json written before ``image_resize`` (then ``image_backbone``) existed loads its weights as it was
    trained, the resize off and QueST's ResNet-18 stem, not today's defaults (a fit to 128, the conv net on a CPU);
    a size below 1 is refused."""
    features = {"observation.image": PolicyFeature(FeatureType.VISUAL, (3, 136, 136))}
    config = CSOConfig(
        **TINY_POLICY_KWARGS,
        device="cpu",
        image_backbone="resnet18",
        image_resize=None,
        input_features=features,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    CSOPolicy(config).save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    del saved["image_resize"], saved["image_backbone"], saved["image_fit"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    policy = CSOPolicy.from_pretrained(tmp_path)
    assert (policy.config.image_resize, policy.config.image_backbone) == (None, "resnet18")
    assert policy.encoders.images["observation__image"].resize is None
    with pytest.raises(ValueError, match="image_resize must be >= 1"):
        CSOConfig(image_resize=0)


def test_our_corner2_is_lerobots_view():
    """The same scene through LeRobot's MetaWorld env and ours: our ``corner2`` frame is LeRobot's (its framing and
    its 180° flip; ours renders without shadows, hence a small difference), not its unflipped render."""
    from lerobot.envs.metaworld import MetaworldEnv

    theirs = MetaworldEnv(TASK, obs_type="pixels_agent_pos")
    their_obs, _ = theirs.reset(seed=3)
    ours = CSOMetaWorldEnv(TASK, cameras=(LEROBOT_CAMERA,), image_size=SIZE, state="hand")
    our_obs, _ = ours.reset(seed=3)
    np.testing.assert_allclose(our_obs["agent_pos"], their_obs["agent_pos"], atol=1e-6)  # the same initial state
    mine, lerobot = our_obs["pixels"][LEROBOT_CAMERA].astype(int), their_obs["pixels"].astype(int)
    assert mine.shape == lerobot.shape == (SIZE, SIZE, 3)
    same, turned = np.abs(mine - lerobot).mean(), np.abs(mine - lerobot[::-1, ::-1]).mean()
    assert same < 15 and 3 * same < turned, (same, turned)
    ours.close()
    theirs.close()


@pytest.mark.slow
def test_lerobot_metaworld_dataset_trains_with_only_budget_flags_and_runs_in_our_world(tmp_path):
    """No image setting: the 480² frames reach the encoder fitted to 128² (QueST's size), through the conv net on a
    CPU, the choice saved in config.json, and the first training batch logs what the encoders cost."""
    data = tmp_path / "data"
    ds = make_lerobot_metaworld_dataset(data)
    assert ds.meta.video_keys == ["observation.image"] and ds.meta.fps == 80

    out = tmp_path / "train"
    cmd = [
        str(BIN / "lerobot-train"),
        "--policy.type=cso",
        f"--dataset.repo_id={REPO}",
        f"--dataset.root={data}",
        f"--output_dir={out}",
        "--steps=4",
        "--save_freq=4",
        "--batch_size=4",
        "--num_workers=0",
        "--log_freq=1",
        "--policy.n_autoencoder_steps=2",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=300)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "step:4 " in log and "nll:" in log  # the prior trained too
    assert "cso policy on a CPU: the camera encoders (conv; observation.image 480×480 → 128×128) took" in log
    model = out / "checkpoints" / "last" / "pretrained_model"
    config = json.loads((model / "config.json").read_text())
    features = {k: v["shape"] for k, v in config["input_features"].items()}
    assert features == {"observation.image": [3, SIZE, SIZE], "observation.state": [4]}
    assert (config["image_backbone"], config["image_resize"], config["image_fit"]) == ("conv", DEFAULT_FIT, "crop")
    # The encoder trained on the fitted frames: its keypoint grid is the conv net's (stride 4) map of a 128² image.
    grid = load_file(model / "model.safetensors")["encoders.images.observation__image.keypoints.pos_grid"]
    assert grid.shape == ((DEFAULT_FIT // 4) ** 2, 2)

    # Our world gives the policy what it reads: LeRobot's corner2 view at 480², the 4-d hand state.
    policy, pre, post = load_policy(model)
    assert env_inputs(policy.config.input_features) == ((LEROBOT_CAMERA,), SIZE, "hand")
    encoder = policy.encoders.images["observation__image"]
    read, encoded = [], []
    encoder.register_forward_pre_hook(lambda _, args: read.append(tuple(args[0].shape)))
    encoder.backbone.register_forward_pre_hook(lambda _, args: encoded.append(tuple(args[0].shape)))
    world = MetaWorld()
    rollouts = Rollouts(2, "sync", 16, 16, "decisions", (), policy.config.input_features)
    with RolloutEngine(policy, pre, post, world.backend(rollouts), world.task_description) as engine:
        result = engine.rollout([(TASK, s) for s in world.eval_states(TASK, 0, 2)], keep_frames=[0])
    assert len(result.episodes) == 2 and result.decisions >= 2
    assert read and set(read) == {(2, 3, SIZE, SIZE)}  # both envs' frames at the dataset's size ...
    assert set(encoded) == {(2, 3, DEFAULT_FIT, DEFAULT_FIT)}  # ... fitted before the encoder's conv net
    first = result.episodes[0]
    assert first.states.shape[-1] == 4 and first.images[LEROBOT_CAMERA].shape[1:] == (SIZE, SIZE, 3)
    env = CSOMetaWorldEnv(TASK, cameras=(LEROBOT_CAMERA,), image_size=SIZE, state="hand")
    np.testing.assert_array_equal(
        first.images[LEROBOT_CAMERA][0].numpy(), env.reset(seed=first.init_seed)[0]["pixels"][LEROBOT_CAMERA]
    )
    env.close()


def save_tiny_lerobot_format_policy(path: Path, size: int = 32) -> Path:
    """A tiny untrained cso policy reading LeRobot's MetaWorld format (``observation.image``, the 4-d state)."""
    torch.manual_seed(0)
    config = CSOConfig(
        **TINY_POLICY_KWARGS,
        device="cpu",
        push_to_hub=False,
        n_autoencoder_steps=0,
        image_backbone="conv",
        image_resize=size // 2,
        tasks=[task_description(t) for t in TASKS],
        input_features={
            "observation.image": PolicyFeature(FeatureType.VISUAL, (3, size, size)),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    stats = {
        "observation.image": {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "observation.state": {"mean": torch.zeros(4), "std": torch.ones(4)},
        "action": {"min": -torch.ones(4), "max": torch.ones(4)},
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    CSOPolicy(config).save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


@pytest.fixture(scope="module")
def lerobot_format_policy(tmp_path_factory) -> Path:
    return save_tiny_lerobot_format_policy(tmp_path_factory.mktemp("il") / "pretrained_model")


class CameraEngine(ScriptedEngine):
    """The scripted engine with what our world gives this policy: the 4-d state and LeRobot's ``corner2`` frames,
    named by the camera (as :class:`RolloutEngine` names them; see the test above)."""

    def episode(self, task: str, seed: int, group: int, sample: int, n_action_steps: int = 8):
        episode = super().episode(task, seed, group, sample, n_action_steps)
        frames = np.random.default_rng(seed + sample).integers(0, 256, (episode.length, 32, 32, 3), dtype=np.uint8)
        return dataclasses.replace(
            episode, states=episode.states[:, :4], images={LEROBOT_CAMERA: torch.from_numpy(frames)}
        )


def test_the_one_mapping_of_image_inputs_to_cameras():
    """``observation.images.<camera>`` is that camera in any world; LeRobot's ``observation.image`` is MetaWorld's
    ``corner2`` and refused, as one line, in a world without a single camera (LIBERO's are named)."""
    features = {"observation.image": None, "observation.images.topview": None, "observation.state": None}
    assert camera_inputs(features, MetaWorld()) == {
        "observation.image": "corner2",
        "observation.images.topview": "topview",
    }
    assert camera_inputs({"observation.images.agentview": None}) == {"observation.images.agentview": "agentview"}
    with pytest.raises(UsageError, match="observation.image .* shows no camera of libero"):
        camera_inputs(features, type("Libero", (), {"name": "libero"}))


def test_the_pipelines_dataset_check_accepts_lerobots_metaworld_format(tmp_path):
    """``--demos.dataset_root`` on a dataset in LeRobot's format was refused: camera 'observation.image' unknown."""
    root = tmp_path / "data"
    make_lerobot_metaworld_dataset(root, episodes=1, length=2, size=32)
    tasks, meta = check_dataset(DemosConfig(tasks=TASK, dataset_root=root, repo_id=REPO))
    assert tasks == [TASK] and meta.camera_keys == ["observation.image"]


def test_rsft_buffer_holds_the_policys_own_inputs_and_the_finetune_reads_them(lerobot_format_policy, tmp_path):
    """The buffer named LeRobot's frames ``observation.images.corner2``, which this policy does not read."""
    cfg = rsft.RSFTConfig(
        tasks=",".join(TASKS), output_dir=tmp_path / "rsft", successes_per_task=1, n_strikes=2, epochs=1, batch_size=4
    )
    cfg.policy = load_policy(lerobot_format_policy)[0].config
    cfg.policy.pretrained_path = lerobot_format_policy
    journal = rsft.Journal(cfg.output_dir / "journal", cfg.spec())
    rsft.collect(cfg, list(TASKS), CameraEngine(mixed, length=10), journal)
    buffer = rsft.write_buffer(cfg, list(TASKS), journal, n_tokens=cfg.policy.n_tokens)
    features = LeRobotDataset("local/cso_rsft_buffer", root=buffer, video_backend="pyav").meta.features
    assert not [key for key in features if key.startswith("observation.images")]
    assert tuple(features["observation.image"]["shape"]) == (32, 32, 3)
    assert tuple(features["observation.state"]["shape"]) == (4,)
    model = rsft.finetune(cfg, buffer)
    assert load_policy(model)[0].config.freeze_encoders


def test_eval_films_a_policy_reading_lerobots_format(lerobot_format_policy, tmp_path, monkeypatch):
    """``--video_episodes`` was refused for a policy reading ``observation.image`` ("the policy reads no camera"):
    its cameras were looked up among its ``observation.images.*`` inputs alone."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    out = tmp_path / "eval"
    args = [f"--policy.path={lerobot_format_policy}", f"--tasks={TASK}", "--episodes_per_task=1", "--video_episodes=1"]
    args += ["--max_steps=16", "--num_envs=1", "--vectorization=sync", f"--output_dir={out}"]
    assert cli.main(["eval", *args]) == 0
    videos = json.loads((out / "eval.json").read_text())["videos"]
    assert len(videos) == 1 and Path(videos[0]).parent == out / "videos" / TASK and Path(videos[0]).stat().st_size


def test_a_policy_setting_it_refuses_is_one_error_line_and_exit_2_in_lerobot_train(tmp_path):
    """LeRobot's parser printed draccus's "Couldn't instantiate class CSOConfig", hiding why, and exited 1."""
    cmd = [str(BIN / "lerobot-train"), "--policy.type=cso", "--policy.image_resize=0", "--dataset.repo_id=local/x"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=300, cwd=tmp_path)
    errors = [line for line in proc.stderr.splitlines() if "error" in line.lower()]
    assert proc.returncode == 2 and errors == [
        "error: cso policy: image_resize must be >= 1 (or null: no resize), got 0"
    ], proc.stderr[-2000:]


# The whole pipeline on a dataset in LeRobot's MetaWorld format, 64² frames resized to 32² inside the policy. On
# drawer-close IL learns to push the drawer shut in 100 steps (a constant push closes it), so R-SFT finds its one
# success at once; IL closes it in 33 steps, so SPO's episodes stop at 33 and sample at T 3: a group is mixed.
PIPELINE_TASK = "drawer-close-v3"
PIPELINE_SIZE = 64
SPO_STEPS = 33
TINY_PIPELINE = """
tasks: {task}
output_dir: {out}
torch_threads: 1
il:
  steps: 100
  n_autoencoder_steps: 50
  batch_size: 16
  num_workers: 0
  save_freq: 100
  log_freq: 50
  policy: {{device: cpu, ae_dim: 32, ae_heads: 2, ae_encoder_layers: 1, ae_decoder_layers: 1, prior_dim: 48,
           prior_heads: 2, prior_layers: 2, state_embed_dim: 16, image_backbone: conv, image_keypoints: 8,
           image_embed_dim: 16, image_resize: {resize}, optimizer_lr: 0.001, optimizer_min_lr: 0.0001}}
eval: {{episodes_per_task: 2, num_envs: 2, vectorization: sync, max_steps: 64}}
rsft: {{successes_per_task: 1, n_strikes: 4, states_per_round: 1, max_states_per_task: 8, num_envs: 4,
       vectorization: sync, max_steps: 64, epochs: 1, batch_size: 8}}
spo: {{iterations: 1, groups_per_iteration: 1, group_size: 4, epochs: 1, minibatch_trajectories: 4, num_envs: 4,
      vectorization: sync, max_draw_factor: 4, max_steps: {spo_steps}, lr: 0.001, sampling: {{temperature: 3.0}}}}
"""


@pytest.mark.slow
def test_the_whole_pipeline_runs_on_a_dataset_in_lerobots_metaworld_format(tmp_path):
    """``lerobot-cso pipeline --demos.dataset_root=... --demos.repo_id=...`` on LeRobot's format, every stage of it
    (until now only its dataset check, R-SFT's buffer and eval had run on it, each alone)."""
    data = tmp_path / "data"
    make_lerobot_metaworld_dataset(data, episodes=4, length=80, size=PIPELINE_SIZE, task=PIPELINE_TASK)
    config, run = tmp_path / "pipeline.yaml", tmp_path / "run"
    config.write_text(TINY_PIPELINE.format(task=PIPELINE_TASK, out=run, resize=RESIZE, spo_steps=SPO_STEPS))
    cmd = [str(BIN / "lerobot-cso"), "pipeline", f"--config_path={config}"]
    cmd += [f"--demos.dataset_root={data}", f"--demos.repo_id={REPO}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]

    # Every stage ran and completed; the demo stage only checked the given dataset.
    records = {path.stem: json.loads(path.read_text()) for path in (run / "stages").glob("*.json")}
    assert set(records) == {"demos", "il", "eval_il", "rsft", "eval_rsft", "spo", "eval_cso"}
    assert all(record["complete"] for record in records.values()), records
    assert not (run / "demos").exists() and records["demos"]["summary"]["total_episodes"] == 4
    results = json.loads((run / "results.json").read_text())
    assert set(results["success_rate"]) == {"il", "rsft", "cso"}

    # IL read LeRobot's keys: the corner2 frame as observation.image and the 4-d hand state.
    il = run / "il" / "checkpoints" / "last" / "pretrained_model"
    config_json = json.loads((il / "config.json").read_text())
    assert {k: v["shape"] for k, v in config_json["input_features"].items()} == {
        "observation.image": [3, PIPELINE_SIZE, PIPELINE_SIZE],
        "observation.state": [4],
    }
    assert config_json["image_resize"] == RESIZE

    # R-SFT's buffer holds the policy's own inputs: rendered frames under observation.image, the 4-d state.
    buffer = LeRobotDataset("local/cso_rsft_buffer", root=run / "rsft" / "buffer")
    assert buffer.meta.camera_keys == ["observation.image"] and buffer.num_frames > 0
    assert not [key for key in buffer.meta.features if key.startswith("observation.images")]
    frames = torch.stack([buffer[t]["observation.image"] for t in range(0, buffer.num_frames, 8)])
    assert frames.shape[1:] == (3, PIPELINE_SIZE, PIPELINE_SIZE) and frames.std() > 0.05
    assert not torch.equal(frames[0], frames[-1])  # the hand moved: every frame rendered, not one repeated
    assert tuple(buffer.meta.features["observation.state"]["shape"]) == (4,)

    # SPO updated the prior from a mixed group and, with the freeze, left the encoders bit-identical.
    [iteration] = [json.loads(line) for line in (run / "spo" / "log.jsonl").read_text().splitlines()]
    assert iteration["updates"] >= 1, iteration
    rsft_model, spo_model = run / "rsft" / "pretrained_model", run / "spo" / "pretrained_model"
    assert json.loads((spo_model / "config.json").read_text())["freeze_encoders"]
    before, after = saved_weights(rsft_model, "encoders."), saved_weights(spo_model, "encoders.")
    assert any("observation__image" in k for k in before) and before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    prior_before, prior_after = saved_weights(rsft_model, "prior."), saved_weights(spo_model, "prior.")
    assert prior_before and any(not torch.equal(prior_before[k], v) for k, v in prior_after.items())
