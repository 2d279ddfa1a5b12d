"""LeRobot's console scripts of this environment run as processes: offline, with LeRobot's caches (calibration
directories) under a home folder of the caller's, and the informative tail of what they say when they fail."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from piper_can.emulator_process import BIN

CLI_TIMEOUT_S = 240


def cli_env(home: Path) -> dict[str, str]:
    """This process's environment, offline, with LeRobot's caches under ``home``."""
    env = dict(os.environ)
    env.update(
        HF_HOME=str(home / "hf"),
        HF_LEROBOT_HOME=str(home / "lerobot"),
        HF_HUB_OFFLINE="1",
        HF_DATASETS_OFFLINE="1",
        TOKENIZERS_PARALLELISM="false",
    )
    return env


def run_cli(name: str, args: list[str], home: Path, timeout: float = CLI_TIMEOUT_S) -> subprocess.CompletedProcess:
    """Run the console script ``name`` in ``home`` to completion (killed after ``timeout`` s), its output captured."""
    return subprocess.run(
        [str(BIN / name), *args], capture_output=True, text=True, timeout=timeout, env=cli_env(home), cwd=home
    )


def explain(out: subprocess.CompletedProcess) -> str:
    """The informative tail of a CLI's stderr (without LeRobot's torchcodec fallback noise)."""
    lines = [line for line in out.stderr.splitlines() if "torchcodec" not in line and "libav" not in line]
    return "\n".join(lines[-40:])


def rollout_args(policy: Path, robot: list[str], task: str, duration: float, fps: int) -> list[str]:
    """``lerobot-rollout`` arguments: the saved ``policy`` on the CPU drives the robot that ``robot`` (its
    ``--robot.…`` arguments) names, for ``task``, ``duration`` seconds at ``fps`` (LeRobot's base strategy)."""
    return [
        "--strategy.type=base",
        f"--policy.path={policy}",
        *robot,
        f"--task={task}",
        f"--duration={duration}",
        f"--fps={fps}",
        "--device=cpu",
    ]
