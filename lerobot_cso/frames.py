"""A LeRobotDataset served from memory: the same items, without a per-item Arrow query or PNG decode.

``LeRobotDataset.__getitem__`` formats one Arrow row, then one Arrow query per delta-timestamp key, and each
query deep-copies the dataset's ``Features`` (≈ 4.5 ms per item with 32-action chunks on one core: more than
the QueST update costs, measured in docs/cso-on-cpu.md), and decodes every PNG camera frame it returns.
The MetaWorld demos and R-SFT buffers are small, so :class:`InMemoryFrames` reads every column once into
tensors — camera frames (``image`` features) decoded once and kept as uint8, a quarter of the float size —
and builds each item by indexing them, with LeRobot's own padding rule and image transforms. Everything else
(``meta``, ``episodes``, ``absolute_to_relative_idx`` …) is the wrapped dataset's. Datasets whose cameras are
videos stay as they are (:func:`in_memory`): their frames live in the video files.
"""

from typing import Any

import numpy as np
import torch
from lerobot.datasets.feature_utils import get_delta_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset


class InMemoryFrames(torch.utils.data.Dataset):
    """``dataset[i]`` from tensors held in memory; identical items to the wrapped dataset's (no video cameras)."""

    def __init__(self, dataset: LeRobotDataset) -> None:
        if dataset.meta.video_keys:
            raise ValueError(f"InMemoryFrames serves datasets without videos; this one has {dataset.meta.video_keys}")
        self.dataset = dataset
        self.image_keys = list(dataset.meta.image_keys)
        table = dataset.hf_dataset
        rows = table.select_columns([c for c in table.column_names if c not in self.image_keys])[:]
        self.columns: dict[str, Any] = {
            key: torch.stack(values) if values and isinstance(values[0], torch.Tensor) else values
            for key, values in rows.items()
        }
        for key in self.image_keys:
            self.columns[key] = _uint8_frames(table.select_columns([key]), key)
        episodes = dataset.meta.episodes
        self.episode_bounds = {
            int(e): (int(a), int(b))
            for e, a, b in zip(
                episodes["episode_index"], episodes["dataset_from_index"], episodes["dataset_to_index"], strict=True
            )
        }
        timestamps = dataset.delta_timestamps
        self.delta_indices = get_delta_indices(timestamps, dataset.fps) if timestamps else {}
        absolute = self.columns["index"].numpy()
        # Absolute frame index → row of this (possibly episode-filtered) table.
        self.row_of = np.full(int(absolute.max()) + 1, -1, dtype=np.int64)
        self.row_of[absolute] = np.arange(len(absolute))
        self.task_names = list(dataset.meta.tasks.index)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name: str) -> Any:
        if name == "dataset":  # not yet set (unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, idx: int) -> dict[str, Any]:
        item = {key: column[idx] for key, column in self.columns.items()}
        for key in self.image_keys:  # as LeRobot's transform makes them: float in [0, 1], (C, H, W)
            item[key] = item[key].float().div(255)
            if self.dataset.image_transforms is not None:
                item[key] = self.dataset.image_transforms(item[key])
        absolute = int(item["index"])
        start, end = self.episode_bounds[int(item["episode_index"])]
        for key, deltas in self.delta_indices.items():
            wanted = np.asarray(deltas) + absolute
            item[key] = self.columns[key][self.row_of[np.clip(wanted, start, end - 1)]]
            item[f"{key}_is_pad"] = torch.from_numpy((wanted < start) | (wanted >= end))
        item["task"] = self.task_names[int(item["task_index"])]
        return item


def _uint8_frames(table: Any, key: str, rows_per_read: int = 1024) -> torch.Tensor:
    """Every frame of image column ``key`` (N, C, H, W) as uint8, decoded a slice of rows at a time (the float
    tensors of a whole table would not fit in memory)."""
    parts = []
    for start in range(0, len(table), rows_per_read):
        frames = torch.stack(table[start : start + rows_per_read][key])  # float in [0, 1], exactly k / 255
        parts.append(frames.mul(255).round_().to(torch.uint8))
    return torch.cat(parts)


def in_memory(dataset: LeRobotDataset) -> LeRobotDataset | InMemoryFrames:
    """The dataset served from memory unless its cameras are videos (then the dataset itself)."""
    return dataset if dataset.meta.video_keys else InMemoryFrames(dataset)
