"""Tiny datasets and policy settings small enough for 2 CPU cores (shared by the policy and CSO tests)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

TINY_POLICY_ARGS = [
    "--policy.ae_dim=32",
    "--policy.ae_heads=2",
    "--policy.ae_encoder_layers=1",
    "--policy.ae_decoder_layers=1",
    "--policy.prior_dim=48",
    "--policy.prior_heads=2",
    "--policy.prior_layers=2",
    "--policy.image_keypoints=8",
    "--policy.image_embed_dim=16",
    "--policy.state_embed_dim=16",
    "--policy.device=cpu",
    "--policy.push_to_hub=false",
]
TINY_POLICY_KWARGS = {
    arg.split("=")[0].removeprefix("--policy."): arg.split("=")[1]
    for arg in TINY_POLICY_ARGS
    if arg.split("=")[0] not in ("--policy.device", "--policy.push_to_hub")
}
TINY_POLICY_KWARGS = {k: int(v) for k, v in TINY_POLICY_KWARGS.items()}

TASKS = ("move the block left", "move the block right")


def make_synthetic_dataset(
    root: Path,
    episode_lengths: tuple[int, ...] = (60, 20, 45, 60),
    state_dim: int = 6,
    action_dim: int = 3,
    image_shape: tuple[int, int, int] | None = None,
    with_action: bool = True,
    seed: int = 0,
    tasks: tuple[str, ...] = TASKS,
):
    """A LeRobotDataset whose actions are a smooth function of time and task, so it can be overfit."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {"observation.state": {"dtype": "float32", "shape": (state_dim,), "names": None}}
    if with_action:
        features["action"] = {"dtype": "float32", "shape": (action_dim,), "names": None}
    if image_shape is not None:
        features["observation.images.cam"] = {
            "dtype": "image",
            "shape": image_shape,
            "names": ["height", "width", "channels"],
        }
    ds = LeRobotDataset.create("local/synthetic", fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(seed)
    for e, length in enumerate(episode_lengths):
        sign = 1.0 if e % 2 == 0 else -1.0
        for t in range(length):
            phase = t / 20.0
            frame = {
                "observation.state": (np.full(state_dim, phase) + 0.01 * rng.standard_normal(state_dim)).astype(
                    np.float32
                ),
                "task": tasks[e % 2],
            }
            if with_action:
                frame["action"] = (sign * np.sin(phase + np.arange(action_dim))).astype(np.float32)
            if image_shape is not None:
                frame["observation.images.cam"] = rng.integers(0, 255, image_shape, dtype=np.uint8)
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return ds
