"""What the pipeline needs of a stage (demos, IL, evaluation, R-SFT, SPO), and the spec helper they share.

A stage knows its own settings and output: :meth:`Stage.spec` is everything its result depends on (as plain
JSON data), :meth:`Stage.complete` says whether its output is finished, :meth:`Stage.run` makes (or resumes)
it and returns a JSON-able summary. :class:`~lerobot_cso.pipeline.Pipeline` only keeps records of specs and
completion, so a rerun skips, resumes, or refuses stale results without knowing any stage's layout.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

PIPELINE_FIELDS = ("tasks", "output_dir", "policy", "world")  # set by the pipeline for every stage, not part of a spec
# What --policy.path must point at, per rollout command (its error when missing, which lerobot-cso says before importing
# the command).
POLICY_ROLES = {
    "eval": "a directory written by save_pretrained",
    "rsft": "the IL checkpoint's pretrained_model directory",
    "spo": "the R-SFT checkpoint's pretrained_model directory",
}
# Settings added after outputs had been recorded without them, at the values that behave as before they existed:
# a record that lacks one is the same spec as one holding that value, so older outputs still resume (another
# value is another spec). A new setting whose default keeps the old behaviour is added here with that default.
ADDED_SETTINGS: dict[str, Any] = {
    "stop_state_at_cap": False,
    "keep_short_tasks": False,
    "train_threads": None,
    "advantage_weighted": False,
    "state": "full",
    "video_episodes": 0,
    "encoder_freeze": True,
    "trajectory_mean": False,
    "buffer_frames": "all",
    "ratio": None,
    "advantage": None,
    "world": None,
    "format": "cso",  # the demos' dataset format (lerobot: LeRobot's own MetaWorld format)
    # Settings of every rollout stage before they moved into the robot world (--world.type=robot), at their values
    # on a simulated world: a record that holds them is the same spec as one without them.
    "robot": None,
    "teleop": None,
    "display_data": False,
    "operator": {
        "type": "keyboard",
        "script": None,
        "episode_time_s": 30.0,
        "rest_time_s": 3.0,
        "rest_pose": None,
        "fps": None,
        "on_fault": "stop",
    },
    # --operator.type=twin's settings (issue 36), at their defaults in every robot record made before them.
    "state_group": "239.74.1.1",
    "state_port": 43200,
    "scene_seed": 0,
}


class Stage(Protocol):
    """One step of the pipeline."""

    name: str
    # True: a changed spec simply redoes the stage (evaluations); False: a changed spec with an existing
    # output is refused, so stale results are never mixed with new ones.
    redo_on_change: bool
    # Flattened spec keys (e.g. "spo.iterations") whose increase continues an existing output instead of being
    # refused: the stage then resumes, and the longer run is what it would have been from the start.
    grows: tuple[str, ...]

    def spec(self) -> dict[str, Any]:
        """The settings and inputs the stage's result depends on."""

    def output(self) -> Path:
        """Where the stage writes."""

    def complete(self) -> bool:
        """Whether the output is finished."""

    def run(self) -> Any:
        """Make (or resume) the output; returns a JSON-able summary."""


class CheckpointStage:
    """A rollout stage whose output is ``output_dir/pretrained_model`` (R-SFT, SPO); subclasses set ``name``
    and ``run``. ``make_engine(policy, preprocessor, postprocessor, cfg)`` builds its rollout engine."""

    name: str
    redo_on_change = False
    grows: tuple[str, ...] = ()

    def __init__(self, cfg: Any, make_engine: Callable[..., Any] | None = None) -> None:
        self.cfg, self.make_engine = cfg, make_engine

    def spec(self) -> dict[str, Any]:
        return {self.name: self.cfg.stage_spec()}

    def output(self) -> Path:
        return self.cfg.output_dir

    def policy(self) -> Path:
        return self.cfg.output_dir / "pretrained_model"

    def complete(self) -> bool:
        return (self.policy() / "config.json").is_file()

    def proven_origin(self) -> bool:
        """Whether work found in the output without the stage's record is provably this stage's own (see
        :func:`~lerobot_cso.records.check_own_record`); none is, unless a stage says how."""
        return False


def settings_spec(config: Any, exclude: tuple[str, ...] = ()) -> dict[str, Any]:
    """A config dataclass (or a dict of settings) as plain JSON data, without the fields in ``exclude``."""
    if isinstance(config, dict):
        data = {k: v for k, v in config.items() if k not in exclude}
    else:
        data = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name not in exclude}
    return json.loads(
        json.dumps(data, default=lambda o: dataclasses.asdict(o) if dataclasses.is_dataclass(o) else str(o))
    )


def without_added_settings(spec: Any) -> Any:
    """``spec`` (JSON data) without the :data:`ADDED_SETTINGS` that hold their behave-as-before value, at any depth;
    a setting's value is judged without the settings added inside it (an operator with a later field at its
    default is still the default operator)."""
    if isinstance(spec, dict):
        stripped = {k: without_added_settings(v) for k, v in spec.items()}
        return {k: v for k, v in stripped.items() if not (k in ADDED_SETTINGS and v == ADDED_SETTINGS[k])}
    return spec
