"""A camera-free LeRobotDataset served from memory: the same items, without a per-item Arrow query.

``LeRobotDataset.__getitem__`` formats one Arrow row, then one Arrow query per delta-timestamp key, and each
query deep-copies the dataset's ``Features`` (≈ 4.5 ms per item with 32-action chunks on one core: more than
the QueST update costs, measured in docs/cso-on-cpu.md). State-only datasets (the MetaWorld demos, R-SFT
buffers without cameras) are small, so :class:`InMemoryFrames` reads every column once into tensors and
builds each item by indexing them, with LeRobot's own padding rule. Everything else (``meta``,
``episodes``, ``absolute_to_relative_idx`` …) is the wrapped dataset's. Datasets with cameras stay as they
are (:func:`in_memory`).
"""

from typing import Any

import numpy as np
import torch
from lerobot.datasets.feature_utils import get_delta_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset


class InMemoryFrames(torch.utils.data.Dataset):
    """``dataset[i]`` from tensors held in memory; identical items to the wrapped camera-free dataset's."""

    def __init__(self, dataset: LeRobotDataset) -> None:
        if dataset.meta.camera_keys:
            raise ValueError(f"InMemoryFrames serves camera-free datasets; this one has {dataset.meta.camera_keys}")
        self.dataset = dataset
        rows = dataset.hf_dataset[:]  # one formatted read of every row: {column: [tensor per row]}
        self.columns: dict[str, Any] = {
            key: torch.stack(values) if values and isinstance(values[0], torch.Tensor) else values
            for key, values in rows.items()
        }
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
        absolute = int(item["index"])
        start, end = self.episode_bounds[int(item["episode_index"])]
        for key, deltas in self.delta_indices.items():
            wanted = np.asarray(deltas) + absolute
            item[key] = self.columns[key][self.row_of[np.clip(wanted, start, end - 1)]]
            item[f"{key}_is_pad"] = torch.from_numpy((wanted < start) | (wanted >= end))
        item["task"] = self.task_names[int(item["task_index"])]
        return item


def in_memory(dataset: LeRobotDataset) -> LeRobotDataset | InMemoryFrames:
    """The dataset served from memory when it has no cameras, else the dataset itself."""
    return dataset if dataset.meta.camera_keys else InMemoryFrames(dataset)
