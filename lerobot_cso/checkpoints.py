"""Loading and saving cso checkpoints (policy + processors) the LeRobot way."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors
from safetensors import SafetensorError, safe_open

from lerobot_cso.durable import replace_dir
from lerobot_cso.errors import UsageError
from lerobot_cso.policy import CSOPolicy

SAVED_FILES = ("model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json")  # beside config.json


def policy_config_from_cli(field: str = "policy") -> PreTrainedConfig | None:
    """``--policy.path=DIR [--policy.x=y]`` → the saved config with CLI overrides (as LeRobot's eval does)."""
    path = parser.get_path_arg(field)
    if not path:
        return None
    check_saved_policy(Path(path), f"--{field}.path")
    overrides = parser.get_yaml_overrides(field) + (parser.get_cli_overrides(field) or [])
    config = PreTrainedConfig.from_pretrained(path, cli_overrides=overrides)
    config.pretrained_path = Path(path)
    return config


def check_saved_policy(path: Path, flag: str) -> None:
    """Refuse a directory that is not a whole saved cso policy (config, weights, processors), naming the file at
    fault: missing, damaged (a truncated or empty file) or another policy type's."""
    config_file = path / "config.json"
    if not config_file.is_file():
        raise UsageError(f"{flag}={path} is not a saved policy (no config.json there)")
    try:
        kind = json.loads(config_file.read_text()).get("type")
    except (ValueError, AttributeError) as e:  # not JSON, or not a JSON object
        raise UsageError(f"{config_file} is damaged ({e or 'not a JSON object'})") from None
    if kind != "cso":
        raise UsageError(
            f"{flag}={path} is a '{kind}' policy; lerobot-cso post-trains cso policies (--policy.type=cso)"
        )
    for name in SAVED_FILES:
        if not (path / name).is_file():
            raise UsageError(f"{path / name} is missing: {flag} must be a policy saved with its weights and processors")
    try:
        with safe_open(path / "model.safetensors", "pt"):  # reads and checks the header against the file's size
            pass
    except SafetensorError as e:
        raise UsageError(f"{path / 'model.safetensors'} is damaged ({e})") from None


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
    try:
        policy = CSOPolicy.from_pretrained(path, config=config)
    except RuntimeError as e:  # torch's load_state_dict: weights of another shape than the config's model
        if "loading state_dict" not in str(e):
            raise
        raise UsageError(
            f"{Path(path) / 'model.safetensors'} does not fit the policy its config describes (weights of another "
            f"architecture, or a --policy.* setting that changes the model's shape): {str(e).splitlines()[-1].strip()}"
        ) from None
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
