"""A LeRobotDataset served from memory: the same items, without a per-item Arrow query or PNG decode.

``LeRobotDataset.__getitem__`` formats one Arrow row, then one Arrow query per delta-timestamp key, and each
query deep-copies the dataset's ``Features`` (≈ 4.5 ms per item with 32-action chunks on one core: more than
the QueST update costs, measured in docs/cso-on-cpu.md), and decodes every PNG camera frame it returns.
The MetaWorld demos and R-SFT buffers are small, so :class:`InMemoryFrames` reads every column once into
tensors — camera frames (``image`` features) decoded once and kept as uint8, a quarter of the float size —
and builds each item by indexing them, with LeRobot's own padding rule and image transforms. Everything else
(``meta``, ``episodes``, ``absolute_to_relative_idx`` …) is the wrapped dataset's. Datasets whose cameras are
videos, or whose items hold a camera history, stay as they are (:func:`in_memory`).

``rows`` serves only some rows (item ``j`` is the wrapped dataset's item ``rows[j]``) and decodes only their
camera frames: R-SFT's fine-tune reads a buffer's decision frames, one in ``n_action_steps``.
"""

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from lerobot.datasets.feature_utils import get_delta_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset


class InMemoryFrames(torch.utils.data.Dataset):
    """``dataset[rows[i]]`` from tensors held in memory; identical items to the wrapped dataset's (no video
    cameras). ``rows``: the rows served, all of them by default."""

    def __init__(self, dataset: LeRobotDataset, rows: Sequence[int] | None = None) -> None:
        if dataset.meta.video_keys:
            raise ValueError(f"InMemoryFrames serves datasets without videos; this one has {dataset.meta.video_keys}")
        if set(dataset.delta_timestamps or {}) & set(dataset.meta.image_keys):
            raise ValueError("InMemoryFrames serves no camera history (delta_timestamps on an image key)")
        self.dataset = dataset
        self.image_keys = list(dataset.meta.image_keys)
        table = dataset.hf_dataset
        values = table.select_columns([c for c in table.column_names if c not in self.image_keys])[:]
        self.columns: dict[str, Any] = {
            key: torch.stack(column) if column and isinstance(column[0], torch.Tensor) else column
            for key, column in values.items()
        }
        self.rows = np.arange(len(table)) if rows is None else np.asarray(rows, dtype=np.int64)
        images = table if rows is None else table.select(self.rows.tolist())
        self.frames = {key: _uint8_frames(images.select_columns([key]), key) for key in self.image_keys}
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
        return len(self.rows)

    def __getattr__(self, name: str) -> Any:
        if name == "dataset":  # not yet set (unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, idx: int) -> dict[str, Any]:
        item = {key: column[self.rows[idx]] for key, column in self.columns.items()}
        for key in self.image_keys:  # as LeRobot's transform makes them: float in [0, 1], (C, H, W)
            item[key] = self.frames[key][idx].float().div(255)
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


def in_memory(dataset: LeRobotDataset, rows: Sequence[int] | None = None) -> torch.utils.data.Dataset | InMemoryFrames:
    """The dataset (its ``rows``, all by default) served from memory, unless its cameras are videos or its items
    hold a camera history (then the dataset itself, or its ``Subset``)."""
    camera_history = set(dataset.delta_timestamps or {}) & set(dataset.meta.image_keys)
    if not dataset.meta.video_keys and not camera_history:
        return InMemoryFrames(dataset, rows)
    return dataset if rows is None else torch.utils.data.Subset(dataset, list(rows))
