"""Issue 35's command-line tries as a fuzz-style check: each bad input to a command must end it with one ``error:``
line and exit code 2, before any work (docs/cli-reliability.md keeps the table of tries and their outcomes).

Every try runs the installed command as its own process (``lerobot-cso``, ``piper-emulator``, ``piper-recover``)
in a scratch directory, offline; the outcome is judged by its exit code and its last stderr line, and a try
whose stderr holds a ``Traceback`` fails whatever its exit code. Each ``lerobot-cso`` try costs a process start
(~8 s idle, the cso plugin imports torch). Run:
    ./run.sh python benchmarks/cli_tries.py [--only SUBSTRING] [--timeout 300]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent


@dataclass(frozen=True)
class Try:
    """One command line and the start of the one error line it must end with (exit code 2)."""

    row: str  # its row(s) in docs/cli-reliability.md
    command: list[str]
    error: str


def tries(scratch: Path) -> list[Try]:
    """The tries, their files made under ``scratch``."""
    (scratch / "a_file").write_text("not a directory")
    (scratch / "broken.yaml").write_text("tasks: [reach-v3\n  x: : :\n")
    (scratch / "list.yaml").write_text("- reach-v3\n")
    (scratch / "empty.yaml").write_text("")
    cso, emulator, recover = str(BIN / "lerobot-cso"), str(BIN / "piper-emulator"), str(BIN / "piper-recover")
    virtual = ["--interface=virtual", "--channel=cli-tries"]
    out = f"--output_dir={scratch / 'a_file' / 'out'}"
    return [
        Try("14", [cso, "demos", "--episodes_per_task=abc"], "error: `episodes_per_task`: Couldn't parse 'abc'"),
        Try("18", [cso, "demos", "--tasks=reach-v3", out], f"error: {out}: {scratch / 'a_file'} is a file"),
        Try("33", [cso, "demos", "--tasks=reach-v3", "--output_dir=/proc/cli_tries"], "error: --output_dir=/proc"),
        Try("7", [cso, "demos", "--tasks=reach-v3", "--noise_std=nan"], "error: noise_std must be a finite number"),
        Try("34", [cso, "eval", f"--config_path={scratch / 'missing.yaml'}"], "error: --config_path="),
        Try("34", [cso, "demos", f"--config_path={scratch}"], f"error: --config_path={scratch}: Is a directory"),
        Try("35", [cso, "eval", f"--config_path={scratch / 'broken.yaml'}"], "error: --config_path="),
        Try("36", [cso, "demos", f"--config_path={scratch / 'list.yaml'}"], "error: --config_path="),
        Try("36", [cso, "pipeline", f"--config_path={scratch / 'empty.yaml'}"], "error: --config_path="),
        Try("44", [cso, "demos", "--tasks=libero_goal-0"], "error: LIBERO's scripted expert does libero_object"),
        Try("27", [emulator, *virtual, "--initial-pose=nan,0,0,0,0,0"], "piper-emulator: error: argument --initial"),
        Try("27", [emulator, *virtual, "--rate-scale=nan"], "piper-emulator: error: argument --rate-scale"),
        Try("27", [emulator, *virtual, "--enable-latency-ms=-5"], "piper-emulator: error: argument --enable-latency"),
        Try("28", [recover, *virtual, "--feedback-timeout-s=-1"], "piper-recover: error: feedback_timeout_s must be"),
    ]


def run(attempt: Try, cwd: Path, timeout: float) -> tuple[bool, str, float]:
    """Whether the try ended as it must, what it printed last (or why it failed), and its seconds."""
    env = os.environ | {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "WANDB_MODE": "disabled"}
    started = time.perf_counter()
    try:
        done = subprocess.run(attempt.command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, f"still running after {timeout:.0f} s", time.perf_counter() - started
    seconds = time.perf_counter() - started
    last = (done.stderr.strip().splitlines() or [""])[-1]
    if "Traceback" in done.stderr:
        return False, f"exit {done.returncode} with a traceback; last line: {last}", seconds
    return done.returncode == 2 and last.startswith(attempt.error), f"exit {done.returncode}: {last}", seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the tries whose command line contains this")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds one try may take")
    args = parser.parse_args()
    failed = 0
    with tempfile.TemporaryDirectory(prefix="cli_tries_") as scratch:
        for attempt in tries(Path(scratch)):
            if args.only not in " ".join(attempt.command):
                continue
            ok, said, seconds = run(attempt, Path(scratch), args.timeout)
            failed += not ok
            shown = " ".join(Path(attempt.command[0]).name if i == 0 else a for i, a in enumerate(attempt.command))
            print(
                f"{'ok  ' if ok else 'FAIL'} row {attempt.row:>3} {seconds:6.1f} s  {shown}\n      {said}", flush=True
            )
    print(f"{failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
