"""Pre/post-processing pipelines of the cso policy (LeRobot's canonical rename → batch → device → normalise)."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_cso.policy.configuration_cso import CSOConfig


def make_cso_pre_post_processors(
    config: CSOConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]
]:
    """Observations and actions are normalised with dataset statistics; the 'task' string passes through."""
    return make_default_pre_post_processors(config, dataset_stats)
