"""A cso policy fresh from its seeded initialisation, for what needs no training (the model's speed, a robot driven by
its actions in a test): the model itself, or saved with its processors as a trained checkpoint is."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors

from lerobot_cso.checkpoints import save_checkpoint
from lerobot_cso.policy import CSOConfig, CSOPolicy


def untrained_policy(
    tasks: Sequence[str],
    state_dim: int,
    action_dim: int,
    images: dict[str, tuple[int, int, int]] | None = None,
    **settings: Any,
) -> CSOPolicy:
    """A cso policy on the CPU for ``tasks``, reading a ``state_dim``-D state and the ``images`` (feature key →
    (C, H, W)) and writing ``action_dim``-D actions; of the default size or with ``settings`` (CSOConfig fields);
    its weights drawn after ``torch.manual_seed(0)``."""
    torch.manual_seed(0)
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    inputs |= {key: PolicyFeature(FeatureType.VISUAL, shape) for key, shape in (images or {}).items()}
    config = CSOConfig(
        **{"device": "cpu", "push_to_hub": False, "n_autoencoder_steps": 0} | settings,
        tasks=list(tasks),
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )
    return CSOPolicy(config)


def save_untrained_policy(
    path: Path,
    stats: dict[str, dict[str, torch.Tensor]],
    tasks: Sequence[str],
    state_dim: int,
    action_dim: int,
    images: dict[str, tuple[int, int, int]] | None = None,
    **settings: Any,
) -> Path:
    """:func:`untrained_policy` saved at ``path`` with its pre/post-processors, which normalise by ``stats``
    (LeRobot's dataset statistics: feature key → ``mean``/``std`` or ``min``/``max`` tensors); returns ``path``."""
    policy = untrained_policy(tasks, state_dim, action_dim, images, **settings)
    pre, post = make_pre_post_processors(policy.config, dataset_stats=stats)
    save_checkpoint(path, policy, pre, post)
    return path
