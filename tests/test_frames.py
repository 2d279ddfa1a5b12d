"""In-memory frames: identical items to LeRobotDataset's, and ``lerobot_cso.train`` trains what lerobot-train does."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors.torch import load_file
from tiny_data import TINY_POLICY_ARGS, make_synthetic_dataset

from lerobot_cso.frames import InMemoryFrames, in_memory

# fps 10: a 32-step action chunk runs past every episode's end, the previous state before its start.
DELTAS = {"action": [i / 10 for i in range(32)], "observation.state": [-0.2, -0.1, 0.0]}


def assert_same_item(expected: dict, got: dict) -> None:
    assert expected.keys() == got.keys()
    for key, value in expected.items():
        if isinstance(value, torch.Tensor):
            assert value.dtype == got[key].dtype and value.shape == got[key].shape, key
            assert torch.equal(value, got[key]), key
        else:
            assert value == got[key], key


@pytest.mark.parametrize("episodes", [None, [1, 3]])
def test_every_item_equals_lerobot_datasets(synthetic_dataset, episodes):
    ds = LeRobotDataset("local/synthetic", root=synthetic_dataset, episodes=episodes, delta_timestamps=DELTAS)
    fast = InMemoryFrames(ds)
    assert len(fast) == len(ds) == (sum((60, 20, 45, 60)) if episodes is None else 20 + 60)
    pads = 0
    for i in range(len(ds)):
        item = fast[i]
        assert_same_item(ds[i], item)
        pads += int(item["action_is_pad"].any()) + int(item["observation.state_is_pad"].any())
    assert pads > 0  # the padding at both episode ends was exercised
    assert fast.meta is ds.meta and fast.absolute_to_relative_idx == ds.absolute_to_relative_idx


def test_camera_frames_equal_lerobot_datasets(tmp_path):
    """PNG camera frames decoded once and kept as uint8 give the float frames LeRobot decodes per item."""
    make_synthetic_dataset(tmp_path / "cam", episode_lengths=(5, 7), image_shape=(8, 8, 3))
    ds = LeRobotDataset("local/synthetic", root=tmp_path / "cam", delta_timestamps=DELTAS)
    fast = in_memory(ds)
    assert isinstance(fast, InMemoryFrames) and fast.frames["observation.images.cam"].dtype == torch.uint8
    for i in range(len(ds)):
        assert_same_item(ds[i], fast[i])
    assert fast[3]["observation.images.cam"].std() > 0.2  # random pixels, not a blank frame
    rows = [9, 0, 5, 6]  # some rows, in any order: the same items, and only their frames decoded
    some = in_memory(ds, rows)
    assert len(some) == 4 and len(some.frames["observation.images.cam"]) == 4
    for j, row in enumerate(rows):
        assert_same_item(ds[row], some[j])


def test_video_datasets_are_left_alone(monkeypatch, tmp_path):
    make_synthetic_dataset(tmp_path / "cam", episode_lengths=(5,), image_shape=(8, 8, 3))
    ds = LeRobotDataset("local/synthetic", root=tmp_path / "cam")
    monkeypatch.setattr(type(ds.meta), "video_keys", property(lambda self: ["observation.images.cam"]))
    assert in_memory(ds) is ds
    with pytest.raises(ValueError, match="without videos"):
        InMemoryFrames(ds)


def test_camera_history_is_left_alone(tmp_path):
    make_synthetic_dataset(tmp_path / "cam", episode_lengths=(5,), image_shape=(8, 8, 3))
    ds = LeRobotDataset(
        "local/synthetic", root=tmp_path / "cam", delta_timestamps={"observation.images.cam": [-0.1, 0]}
    )
    assert in_memory(ds) is ds and list(in_memory(ds, [3, 1]).indices) == [3, 1]
    with pytest.raises(ValueError, match="camera history"):
        InMemoryFrames(ds)


def test_train_module_gives_lerobot_trains_weights(synthetic_dataset, tmp_path):
    """Same seed, same sampler, same items: ``python -m lerobot_cso.train`` ≡ ``lerobot-train`` bit for bit."""
    weights = {}
    for name, command in {
        "lerobot": [os.path.join(os.path.dirname(sys.executable), "lerobot-train")],
        "in_memory": [sys.executable, "-m", "lerobot_cso.train"],
    }.items():
        out = tmp_path / name
        proc = subprocess.run(
            [
                *command,
                "--policy.type=cso",
                "--dataset.repo_id=local/synthetic",
                f"--dataset.root={synthetic_dataset}",
                f"--output_dir={out}",
                "--steps=6",
                "--save_freq=6",
                "--batch_size=8",
                "--num_workers=0",
                "--policy.n_autoencoder_steps=3",
                *TINY_POLICY_ARGS,
            ],
            check=True,
            capture_output=True,
            env=os.environ | {"HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"},
            timeout=300,
            text=True,
        )
        assert ("frames served from memory" in proc.stdout + proc.stderr) == (name == "in_memory")
        weights[name] = load_file(out / "checkpoints" / "last" / "pretrained_model" / "model.safetensors")
    assert weights["lerobot"].keys() == weights["in_memory"].keys()
    for key, value in weights["lerobot"].items():
        assert torch.equal(value, weights["in_memory"][key]), key
