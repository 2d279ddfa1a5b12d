"""The imitation-learning stage: ``lerobot-train --policy.type=cso`` on the demos, as a subprocess.

LeRobot's training runs through :mod:`lerobot_cso.train`, which serves camera-free demos from memory (identical
items, no per-item Arrow query). The run writes LeRobot's own output dir; a rerun continues with
``--resume=true`` from its last checkpoint (or starts over when it was killed before its first one). The policy
is ``<output_dir>/checkpoints/last/pretrained_model``.
"""

import ctypes
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot_cso.errors import UsageError
from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.stage import settings_spec

# Policy fields the stage sets itself (or that the dataset fills in).
RESERVED_POLICY_KEYS = ("type", "path", "pretrained_path", "tasks", "n_autoencoder_steps")
RUNTIME_FIELDS = ("num_workers", "save_freq", "log_freq")  # do not change the trained policy
PR_SET_PDEATHSIG = 1  # prctl(2): the signal a child gets when its parent dies


@dataclass
class ILConfig:
    """The imitation-learning stage: ``lerobot-train --policy.type=cso`` on the demos, as a subprocess."""

    steps: int = 20_000
    # The first n_autoencoder_steps train the skill autoencoder, the rest the skill prior.
    n_autoencoder_steps: int = 5_000
    batch_size: int = 64
    num_workers: int = 2
    save_freq: int = 5_000
    log_freq: int = 200
    seed: int = 1000
    # Policy settings, passed as --policy.<key>=<value> (dims, learning rate, device, ...).
    policy: dict[str, Any] = field(default_factory=dict)
    # Further lerobot-train arguments, verbatim (e.g. "--wandb.enable=true").
    extra_args: list[str] = field(default_factory=list)

    def validate(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or self.save_freq < 1 or self.log_freq < 1:
            raise UsageError("il.steps, il.batch_size, il.save_freq and il.log_freq must be >= 1")
        if not 0 <= self.n_autoencoder_steps < self.steps:
            raise UsageError(
                f"il.n_autoencoder_steps must be in [0, il.steps={self.steps}) so that the prior trains too, "
                f"got {self.n_autoencoder_steps}"
            )
        if self.num_workers < 0:
            raise UsageError(f"il.num_workers must be >= 0, got {self.num_workers}")
        known = {f.name for f in dataclasses.fields(CSOConfig)}
        unknown = sorted(k for k in self.policy if k not in known)
        if unknown:
            raise UsageError(f"il.policy: unknown cso policy setting(s) {', '.join(unknown)}")
        reserved = sorted(k for k in self.policy if k in RESERVED_POLICY_KEYS)
        if reserved:
            raise UsageError(f"il.policy: {', '.join(reserved)} cannot be set here (the pipeline sets it)")
        try:
            CSOConfig(**{k: v for k, v in self.policy.items() if k != "push_to_hub"} | {"device": "cpu"})
        except (TypeError, ValueError) as e:
            raise UsageError(f"il.policy: {e}") from None


class ILStage:
    """``lerobot-train`` on a demo dataset (see the module docstring)."""

    name = "il"
    redo_on_change = False
    grows = ()  # more steps are not a continuation: the cosine schedule spans all of them

    def __init__(self, cfg: ILConfig, dataset: Path, repo_id: str, output_dir: Path, threads: int | None) -> None:
        self.cfg, self.dataset, self.repo_id, self.out, self.threads = cfg, dataset, repo_id, output_dir, threads

    def spec(self) -> dict[str, Any]:
        return {"il": settings_spec(self.cfg, exclude=RUNTIME_FIELDS)}

    def output(self) -> Path:
        return self.out

    def policy(self) -> Path:
        return self.out / "checkpoints" / "last" / "pretrained_model"

    def steps_done(self) -> int:
        path = self.out / "checkpoints" / "last" / "training_state" / "training_step.json"
        return json.loads(path.read_text())["step"] if path.is_file() else 0

    def complete(self) -> bool:
        return self.steps_done() >= self.cfg.steps and (self.policy() / "config.json").is_file()

    def run(self) -> dict[str, Any]:
        il = self.cfg
        common = [
            f"--output_dir={self.out}",
            f"--dataset.root={self.dataset}",
            f"--dataset.repo_id={self.repo_id}",
            "--dataset.video_backend=pyav",  # a dataset's videos decode with pyav; skips probing torchcodec
            f"--steps={il.steps}",
            f"--num_workers={il.num_workers}",
        ]
        if self.steps_done() >= il.steps:
            args = None  # finished; only its record was missing
        elif (self.policy() / "train_config.json").is_file():
            args = ["--resume=true", f"--config_path={self.policy() / 'train_config.json'}", *common]
        else:
            shutil.rmtree(self.out, ignore_errors=True)  # killed before its first checkpoint: start over
            settings = {"push_to_hub": False, **il.policy, "n_autoencoder_steps": il.n_autoencoder_steps}
            args = [
                "--policy.type=cso",
                *common,
                f"--batch_size={il.batch_size}",
                f"--save_freq={min(il.save_freq, il.steps)}",
                f"--log_freq={il.log_freq}",
                f"--seed={il.seed}",
                *(f"--policy.{k}={cli_value(v)}" for k, v in settings.items()),
                *il.extra_args,
            ]
        if args is not None:
            lerobot_train(args, self.threads)
        if self.steps_done() < il.steps:
            raise RuntimeError(f"lerobot-train stopped at step {self.steps_done()} of {il.steps}")
        return {"steps": self.steps_done(), "checkpoint": str(self.policy())}


def cli_value(value: Any) -> str:
    """A yaml value as a draccus command-line value (lists, mappings and booleans as JSON)."""
    return (
        json.dumps(value, separators=(",", ":"))
        if isinstance(value, (list, dict, bool)) or value is None
        else str(value)
    )


def lerobot_train(args: list[str], threads: int | None) -> None:
    """Run ``lerobot-train`` (as :mod:`lerobot_cso.train`: camera-free demos served from memory) with our output
    streamed through."""
    command = [sys.executable, "-m", "lerobot_cso.train", *args]
    env = os.environ | ({"OMP_NUM_THREADS": str(threads)} if threads else {})
    print("[pipeline] " + " ".join(command), flush=True)
    returncode = run_tied(command, env)
    if returncode != 0:
        raise RuntimeError(f"lerobot-train failed with exit code {returncode} (its output is above)")


def run_tied(command: list[str], env: dict[str, str]) -> int:
    """Run ``command`` to its end and return its exit code; on Linux it is killed when this process dies, even by
    ``kill -9``, so a rerun never finds an orphaned trainer still writing the same output dir. A Ctrl-C (SIGINT to
    the process group) is this process's to handle: the child ignores it and is killed as this process stops, so
    the command ends with its own one line instead of the child's traceback."""
    parent = os.getpid()

    def die_with_parent() -> None:  # in the child, before exec
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # kept across exec: Python then installs no handler of its own
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != parent:  # the parent died before the request was made
            os._exit(1)

    return subprocess.run(command, env=env, preexec_fn=die_with_parent if sys.platform == "linux" else None).returncode
