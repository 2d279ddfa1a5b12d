"""Helpers shared by the MetaWorld tests: tiny demo datasets and a tiny cso policy trained a few steps."""

from __future__ import annotations

from pathlib import Path

import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.feature_utils import dataset_to_policy_features

from lerobot_cso.demos import DemosConfig, generate_demos
from lerobot_cso.policy import CSOConfig, CSOPolicy
from lerobot_cso.worlds.metaworld.constants import FPS

TINY = {
    "ae_dim": 32,
    "ae_heads": 2,
    "ae_encoder_layers": 1,
    "ae_decoder_layers": 1,
    "prior_dim": 48,
    "prior_heads": 2,
    "prior_layers": 2,
    "state_embed_dim": 16,
    "device": "cpu",
    "push_to_hub": False,
}


def make_demos(root: Path, tasks: str, episodes: int, **overrides) -> dict:
    """Generate a demo dataset in-process (state only unless ``cameras`` is given)."""
    settings = {"num_envs": 2, **overrides}
    cfg = DemosConfig(tasks=tasks, episodes_per_task=episodes, output_dir=root, **settings)
    return generate_demos(cfg)


def train_tiny_policy(dataset_root: Path, out_dir: Path, steps: int = 6, seed: int = 0) -> Path:
    """A tiny cso policy trained ``steps`` steps (half autoencoder, half prior), saved with its processors."""
    torch.manual_seed(seed)
    cfg = CSOConfig(n_autoencoder_steps=steps // 2, **TINY)
    ds = LeRobotDataset("local/demos", root=dataset_root, video_backend="pyav")
    features = dataset_to_policy_features(ds.meta.features)
    cfg.input_features = {k: f for k, f in features.items() if k.startswith("observation.")}
    cfg.output_features = {"action": features["action"]}
    ds = LeRobotDataset(
        "local/demos",
        root=dataset_root,
        video_backend="pyav",
        delta_timestamps={"action": [i / FPS for i in range(cfg.chunk_size)]},
    )
    pre, post = make_pre_post_processors(cfg, dataset_stats=ds.meta.stats)
    policy = CSOPolicy(cfg, dataset_meta=ds.meta).train()
    opt = torch.optim.AdamW(policy.get_optim_params(), lr=1e-3)
    loader = torch.utils.data.DataLoader(ds, batch_size=32, shuffle=True)
    batches = iter(loader)
    for _ in range(steps):
        loss, _ = policy.forward(pre(next(batches)))
        opt.zero_grad()
        loss.backward()
        opt.step()
    policy.eval()
    policy.save_pretrained(out_dir)
    pre.save_pretrained(out_dir)
    post.save_pretrained(out_dir)
    return out_dir


DEMO_TASKS = "reach-v3,button-press-v3"
DEMO_EPISODES = 5


def shared_demos(tmp_path_factory) -> Path:
    """The session's demo dataset (reach-v3 and button-press-v3, 5 episodes each), built on first use."""
    root = tmp_path_factory.getbasetemp() / "shared_metaworld_demos"
    if not root.exists():
        make_demos(root, DEMO_TASKS, DEMO_EPISODES)
    return root


def shared_policy(tmp_path_factory) -> Path:
    """The session's tiny cso policy, trained a few steps on :func:`shared_demos`."""
    out = tmp_path_factory.getbasetemp() / "shared_tiny_cso_policy"
    if not (out / "config.json").exists():
        train_tiny_policy(shared_demos(tmp_path_factory), out)
    return out


def load_policy(path: Path):
    """Policy and processors from a saved directory, as the CLI loads them."""
    policy = CSOPolicy.from_pretrained(path).eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path))
    return policy, pre, post
