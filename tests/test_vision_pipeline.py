"""The camera path through the real CLIs: QueST's MetaWorld observation (a corner2 image + the 8-d proprio, no
object position) from demos through ``lerobot-train``, R-SFT, SPO and an evaluation that writes videos."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from cso_fakes import saved_weights
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors.torch import load_file

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}

# One easy task, 32² images, the small conv encoder: IL closes the drawer often enough for R-SFT to find successes.
TINY_VISION = """
tasks: drawer-close-v3
output_dir: {out}
torch_threads: 1
demos: {{episodes_per_task: 8, num_envs: 2, cameras: corner2, image_size: 32, state: proprio}}
il:
  steps: 200
  n_autoencoder_steps: 80
  batch_size: 16
  num_workers: 0
  save_freq: 200
  log_freq: 50
  policy: {{device: cpu, ae_dim: 32, ae_heads: 2, ae_encoder_layers: 1, ae_decoder_layers: 1, prior_dim: 48,
           prior_heads: 2, prior_layers: 2, state_embed_dim: 16, image_backbone: conv, image_shift: 2,
           image_keypoints: 8, image_embed_dim: 16, optimizer_lr: 0.001, optimizer_min_lr: 0.0001}}
eval: {{episodes_per_task: 4, num_envs: 4, vectorization: sync, max_steps: 150, video_episodes: 2}}
rsft: {{successes_per_task: 2, n_strikes: 4, states_per_round: 1, max_states_per_task: 20, num_envs: 4,
       vectorization: sync, epochs: 1, batch_size: 16, buffer_frames: decisions}}
spo: {{iterations: 1, groups_per_iteration: 2, group_size: 4, epochs: 1, minibatch_trajectories: 4, num_envs: 4,
      vectorization: sync, max_draw_factor: 4, max_steps: {spo_steps}, sampling: {{temperature: 2.0}}}}
"""
# IL closes the drawer in 33-37 steps: SPO's episodes stop at 36 and sample at T 2, so its groups are mixed.
SPO_STEPS = 36


SPO_CLI = {  # the pipeline's SPO section above, as command-line flags
    "iterations": 1,
    "groups_per_iteration": 2,
    "group_size": 4,
    "epochs": 1,
    "minibatch_trajectories": 4,
    "num_envs": 4,
    "vectorization": "sync",
    "max_draw_factor": 4,
    "max_steps": SPO_STEPS,
    "sampling.temperature": 2.0,
}


def test_camera_demos_train_refine_and_evaluate_with_videos(tmp_path):
    config = tmp_path / "vision.yaml"
    config.write_text(TINY_VISION.format(out=tmp_path / "run", spo_steps=SPO_STEPS))
    cmd = [str(BIN / "lerobot-cso"), "pipeline", f"--config_path={config}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    run = tmp_path / "run"

    # The policy reads the camera and the proprio only: no object or goal position anywhere in its input.
    il = run / "il" / "checkpoints" / "last" / "pretrained_model"
    features = json.loads((il / "config.json").read_text())["input_features"]
    assert {k: v["shape"] for k, v in features.items()} == {
        "observation.state": [8],
        "observation.images.corner2": [3, 32, 32],
    }

    # The R-SFT buffer (buffer_frames: decisions) holds the camera's decision frames, not blanks, each repeated
    # over its skill's frames; the skill's next decision frame is a new render.
    buffer = LeRobotDataset("local/cso_rsft_buffer", root=run / "rsft" / "buffer")
    assert buffer.meta.camera_keys == ["observation.images.corner2"] and buffer.num_frames > 0
    items = [buffer[i] for i in range(buffer.meta.episodes["length"][0])]  # the first episode
    frames = torch.stack([item["observation.images.corner2"] for item in items])
    starts = [i for i, item in enumerate(items) if item["observation.skill_start"].item() == 1]
    assert frames.shape[1:] == (3, 32, 32) and frames.std() > 0.05
    assert starts == list(range(0, len(items), 8)) and len(starts) >= 2
    for first, end in zip(starts, [*starts[1:], len(items)], strict=True):
        assert all(torch.equal(frames[first], frames[t]) for t in range(first, end))
    assert not torch.equal(frames[starts[0]], frames[starts[-1]])  # the hand moved between the decisions
    assert tuple(buffer.meta.features["observation.state"]["shape"]) == (8,)

    # With the freeze (Algorithm 1, line 11), SPO leaves the encoders bit-identical while it moves the prior.
    rsft_encoders, spo_encoders = (
        saved_weights(run / "rsft" / "pretrained_model", "encoders."),
        saved_weights(run / "spo" / "pretrained_model", "encoders."),
    )
    assert any("images" in k for k in rsft_encoders)
    assert rsft_encoders.keys() == spo_encoders.keys()
    assert all(torch.equal(rsft_encoders[k], spo_encoders[k]) for k in rsft_encoders)
    prior = {k: v for k, v in load_file(run / "spo" / "pretrained_model" / "model.safetensors").items() if "prior" in k}
    before = load_file(run / "rsft" / "pretrained_model" / "model.safetensors")
    assert any(not torch.equal(before[k], v) for k, v in prior.items())
    # Without it (the ablation), the same SPO run through its own CLI moves the encoders too.
    unfrozen = tmp_path / "spo_no_freeze"
    spo = [
        str(BIN / "lerobot-cso"),
        "spo",
        f"--policy.path={run / 'rsft' / 'pretrained_model'}",
        "--tasks=drawer-close-v3",
        f"--output_dir={unfrozen}",
        "--encoder_freeze=false",
        *(f"--{k}={v}" for k, v in SPO_CLI.items()),
    ]
    proc = subprocess.run(spo, capture_output=True, text=True, env=ENV, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    moved = saved_weights(unfrozen / "pretrained_model", "encoders.")
    assert any(not torch.equal(rsft_encoders[k], moved[k]) for k in rsft_encoders)
    assert not json.loads((unfrozen / "pretrained_model" / "config.json").read_text())["freeze_encoders"]

    # Each evaluation wrote the first two episodes' videos of what the policy saw, named by state and outcome.
    for stage in ("il", "cso"):
        record = json.loads((run / "eval" / stage / "eval.json").read_text())
        episodes = [e for e in record["episodes"] if e["seed"] == 0][:2]
        names = sorted(f"{e['init_seed']}_{'success' if e['success'] else 'failure'}.mp4" for e in episodes)
        videos = sorted(run / "eval" / stage / "videos" / "drawer-close-v3" / name for name in names)
        assert [str(p) for p in videos] == sorted(record["videos"])
        assert all(p.stat().st_size > 1000 for p in videos)
    import av

    with av.open(str(videos[0])) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    length = next(e["length"] for e in episodes if str(e["init_seed"]) in videos[0].name)
    assert len(decoded) == -(-length // 8) + 1  # one frame per decision (every 8 steps) and the last
    assert decoded[0].shape == (32, 32, 3) and np.std(decoded[0]) > 5
