"""Loading and saving cso checkpoints (policy + processors) the LeRobot way."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors

from lerobot_cso.durable import replace_dir
from lerobot_cso.errors import UsageError
from lerobot_cso.policy import CSOPolicy


def policy_config_from_cli(field: str = "policy") -> PreTrainedConfig | None:
    """``--policy.path=DIR [--policy.x=y]`` → the saved config with CLI overrides (as LeRobot's eval does)."""
    path = parser.get_path_arg(field)
    if not path:
        return None
    if not (Path(path) / "config.json").is_file():
        raise UsageError(f"--{field}.path={path} is not a saved policy (no config.json there)")
    overrides = parser.get_yaml_overrides(field) + (parser.get_cli_overrides(field) or [])
    config = PreTrainedConfig.from_pretrained(path, cli_overrides=overrides)
    config.pretrained_path = Path(path)
    return config


@dataclass
class PolicyPathConfig:
    """Base of the subcommand configs that take ``--policy.path=DIR`` (LeRobot's ``EvalPipelineConfig`` way)."""

    policy: PreTrainedConfig | None = None

    def __post_init__(self) -> None:
        self.policy = policy_config_from_cli() or self.policy

    @classmethod
    def __get_path_fields__(cls) -> list[str]:
        return ["policy"]


def load_policy(path: str | Path, config: PreTrainedConfig | None = None) -> tuple[CSOPolicy, Any, Any]:
    """A saved cso policy with its pre/post-processors (normalisation statistics of its training data).

    The preprocessor moves observations to the policy's device (``--policy.device``), whatever device the
    checkpoint was saved from; the postprocessor returns actions on the CPU.
    """
    policy = CSOPolicy.from_pretrained(path, config=config)
    pre, post = make_pre_post_processors(
        policy.config,
        pretrained_path=str(path),
        preprocessor_overrides={"device_processor": {"device": str(policy.config.device)}},
    )
    return policy, pre, post


def save_checkpoint(directory: Path, policy: CSOPolicy, preprocessor: Any, postprocessor: Any) -> None:
    """Write policy + processors to ``directory`` atomically (a temporary sibling renamed into place)."""
    tmp = directory.with_name(directory.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    policy.save_pretrained(tmp)
    preprocessor.save_pretrained(tmp)
    postprocessor.save_pretrained(tmp)
    replace_dir(tmp, directory)
