"""Issue 35: every command refuses what it cannot honour, up front, with one ``error:`` line (exit 2).

Most checks run ``validate()`` or ``cli.main`` in this process (one CLI subprocess costs ~10 s of imports); a
subprocess is used only where the process itself is what is tested (its exit code on Ctrl-C, its start time).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from lerobot_cso.cso.rsft import RSFTConfig
from lerobot_cso.cso.spo import SPOConfig
from lerobot_cso.demos import DemosConfig
from lerobot_cso.envs.tasks import task_description
from lerobot_cso.errors import UsageError, check_number
from lerobot_cso.evaluation import EvalConfig
from lerobot_cso.pipeline import Pipeline, PipelineConfig
from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.rollout.engine import Sampling
from lerobot_cso.rollout.operator import OperatorConfig

NAN, INF = math.nan, math.inf


def stand_in_policy() -> CSOConfig:
    """A policy config that passes the stages' checks without any file (as the pipeline's stand-in)."""
    policy = CSOConfig(tasks=[task_description("reach-v3")], device="cpu")
    policy.pretrained_path = Path("/nonexistent/pretrained_model")
    return policy


def rollout_config(cls: type, **settings):
    return cls(tasks="reach-v3", policy=stand_in_policy(), output_dir=Path("/tmp/unused"), **settings)


@pytest.mark.parametrize("bad", [NAN, INF, -INF])
@pytest.mark.parametrize(
    ("make", "name"),
    [
        (lambda v: rollout_config(EvalConfig, sampling=Sampling(temperature=v)), "sampling.temperature"),
        (lambda v: rollout_config(SPOConfig, sampling=Sampling(temperature=v)), "sampling.temperature"),
        (lambda v: rollout_config(SPOConfig, lr=v), "lr"),
        (lambda v: rollout_config(SPOConfig, weight_decay=v), "weight_decay"),
        (lambda v: rollout_config(SPOConfig, grad_clip_norm=v), "grad_clip_norm"),
        (lambda v: rollout_config(SPOConfig, clip_low=v), "clip_low"),
        (lambda v: rollout_config(SPOConfig, clip_high=v), "clip_high"),
        (lambda v: rollout_config(SPOConfig, target_kl=v), "target_kl"),
        (lambda v: rollout_config(RSFTConfig, lr=v), "lr"),
        (lambda v: rollout_config(RSFTConfig, min_lr=v), "min_lr"),
        (lambda v: rollout_config(RSFTConfig, demo_fraction=v), "demo_fraction"),
        (lambda v: DemosConfig(tasks="reach-v3", noise_std=v), "noise_std"),
        (lambda v: OperatorConfig(episode_time_s=v), "operator.episode_time_s"),
        (lambda v: OperatorConfig(rest_time_s=v), "operator.rest_time_s"),
    ],
)
def test_nan_and_inf_settings_are_refused_before_any_work(make, name, bad):
    with pytest.raises(UsageError, match=rf"^{name} must be a finite number"):
        make(bad).validate()


@pytest.mark.parametrize(
    "name",
    [
        "temperature",
        "ae_dropout",
        "prior_dropout",
        "decoder_loss_scale",
        "optimizer_lr",
        "optimizer_min_lr",
        "optimizer_weight_decay",
        "optimizer_grad_clip_norm",
    ],
)
def test_the_policy_config_refuses_nan_in_every_float_setting(name):
    """``lerobot-train --policy.type=cso --policy.temperature=nan`` saved NaN into config.json."""
    with pytest.raises(ValueError, match=rf"^{name} must be a finite number"):
        CSOConfig(device="cpu", **{name: NAN})
    with pytest.raises(ValueError, match="optimizer_betas must be a finite number"):
        CSOConfig(device="cpu", optimizer_betas=(0.9, NAN))


def test_the_pipeline_refuses_nan_in_any_section_before_running(tmp_path):
    cfg = PipelineConfig(tasks="reach-v3", output_dir=tmp_path / "run")
    for section, settings in (("spo", {"lr": NAN}), ("rsft", {"min_lr": NAN}), ("demos", {"noise_std": NAN})):
        bad = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **settings)})
        with pytest.raises(UsageError, match=f"^{next(iter(settings))} must be a finite number"):
            Pipeline(bad)
    bad = dataclasses.replace(cfg, il=dataclasses.replace(cfg.il, policy={"temperature": "nan"}))
    with pytest.raises(UsageError, match="^il.policy: temperature must be a finite number"):
        Pipeline(bad)
    assert not (tmp_path / "run").exists()


def test_check_number_names_the_setting_its_bounds_and_the_value():
    check_number("x", 0.5, gt=0, lt=1)
    check_number("x", None, gt=0, optional=True)
    with pytest.raises(UsageError, match=r"^x must be a finite number >= 0 and < 1 \(or null\), got nan$"):
        check_number("x", NAN, ge=0, lt=1, optional=True)
    with pytest.raises(ValueError, match=r"^x must be a finite number > 0, got -1$"):
        check_number("x", -1, gt=0, error=ValueError)
