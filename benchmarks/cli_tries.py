"""Issues 35 and 58's command-line tries as a fuzz-style check: each bad input to a command must end it with one
``error:`` line and exit code 2, before any work (docs/cli-reliability.md keeps the table of tries and their outcomes).

Every try runs the installed command as its own process (``lerobot-cso``, ``piper-emulator``, ``piper-recover``)
in a scratch directory, offline; the outcome is judged by its exit code and its last stderr line, and a try
whose stderr holds a ``Traceback`` fails whatever its exit code. Besides bad command-line input, the scratch
directory holds the state a try meets (issue 58): outputs without their own record, a policy of another action
size, demonstrations of another shape, a symbolic link to an output dir, and output dirs another process writes
(a holder process keeps their lock while the try runs). The states are made here (an untrained policy from
``lerobot_cso.untrained``, a two-frame LeRobotDataset), and each stateful try is also a test in
``tests/test_cli_errors.py`` (in process). Each ``lerobot-cso`` try costs a process start (~8 s idle, the cso plugin
imports torch). Run:
    ./run.sh python benchmarks/cli_tries.py [--only SUBSTRING] [--rows 48,49] [--timeout 300]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
TASKS = ("reach-v3", "button-press-v3")


@dataclass(frozen=True)
class Try:
    """One command line and the start of the one error line it must end with (exit code 2)."""

    row: str  # its row(s) in docs/cli-reliability.md
    command: list[str]
    error: str
    holds: Path | None = None  # an output dir another process holds (its lock) while the try runs


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
        *stateful_tries(scratch, cso),
    ]


def stateful_tries(scratch: Path, cso: str) -> list[Try]:
    """Issue 58's tries, and the state each meets, made under ``scratch``."""
    import lerobot_policy_cso  # noqa: F401  (the cso plugin: LeRobot's torchcodec page in one line)

    policy = metaworld_policy(scratch / "policy" / "pretrained_model")
    three_d = shutil.copytree(policy, scratch / "three_d" / "pretrained_model")
    config = json.loads((three_d / "config.json").read_text())
    config["output_features"]["action"]["shape"] = [3]
    (three_d / "config.json").write_text(json.dumps(config))
    unfit_dataset(scratch / "synthetic")
    unrecorded = {}  # work without its own record, as the pipeline or older code leaves it
    for name in ("spo", "rsft"):
        (scratch / "pipeline" / name / "state").mkdir(parents=True)
        (scratch / "pipeline" / name / "state" / "progress.json").write_text('{"iteration": 1}')
        unrecorded[name] = f"{scratch / 'pipeline' / name} holds work but no record of the settings"
    (scratch / "real").mkdir()
    (scratch / "link").symlink_to(scratch / "real", target_is_directory=True)
    stage = [f"--policy.path={policy}", f"--tasks={TASKS[0]}"]
    return [
        *(
            Try("48", [cso, name, *stage, f"--output_dir={scratch / 'pipeline' / name}"], f"error: {unrecorded}")
            for name, unrecorded in unrecorded.items()
        ),
        Try(
            "49",
            [
                cso,
                "rsft",
                *stage,
                "--demo_fraction=0.5",
                f"--demos_root={scratch / 'synthetic'}",
                "--demos_repo_id=local/synthetic",
                f"--output_dir={scratch / 'rsft_demos'}",
            ],
            f"error: --demos_root={scratch / 'synthetic'} does not fit the policy",
        ),
        Try(
            "50",
            [cso, "eval", f"--policy.path={three_d}", f"--tasks={TASKS[0]}", f"--output_dir={scratch / 'e'}"],
            "error: the policy's 'action' has shape (3,), metaworld's is (4,)",
        ),
        Try(
            "50",
            [cso, "spo", f"--policy.path={three_d}", f"--tasks={TASKS[0]}", f"--output_dir={scratch / 's'}"],
            "error: the policy's 'action' has shape (3,), metaworld's is (4,)",
        ),
        Try(
            "51",
            [cso, "eval", *stage, f"--output_dir={scratch / 'link'}"],
            f"error: {scratch / 'link'} is being written by another run",
            holds=scratch / "real",
        ),
        Try(
            "51",
            [cso, "spo", *stage, f"--output_dir={scratch / 'running' / 'spo'}"],
            f"error: {scratch / 'running' / 'spo'} is inside {scratch / 'running'}, which is being written",
            holds=scratch / "running",
        ),
        Try("53", [cso, "eval", *stage, "--num_envs=100000"], "error: num_envs must be in [1, 1024]"),
        Try("53", [cso, "eval", *stage, "--output_dir=/"], "error: --output_dir=/ is the root of the file system"),
        Try("54", [cso, "eval", "--help"], ""),  # the first one after an install or an edit keeps the help
        Try("54", [cso, "eval", "--help"], ""),
        Try("54", [cso, "eval", "--num_env=4"], "error: unrecognized arguments: --num_env=4"),
    ]


def metaworld_policy(path: Path) -> Path:
    """A small untrained cso policy with MetaWorld's shapes (state 39, action 4) for :data:`TASKS`, saved."""
    import torch

    from lerobot_cso.untrained import save_untrained_policy
    from lerobot_cso.worlds.metaworld.tasks import task_description

    stats = {
        "observation.state": {"mean": torch.zeros(39), "std": torch.ones(39)},
        "action": {"min": -torch.ones(4), "max": torch.ones(4)},
    }
    small = {"ae_dim": 32, "ae_heads": 2, "prior_dim": 32, "prior_heads": 2, "prior_layers": 1, "state_embed_dim": 16}
    return save_untrained_policy(path, stats, [task_description(t) for t in TASKS], 39, 4, **small)


def unfit_dataset(root: Path) -> None:
    """A LeRobotDataset of one two-frame episode with a 6-d state and a 3-d action: not the policy's 39 and 4."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        key: {"dtype": "float32", "shape": (n,), "names": None} for key, n in (("observation.state", 6), ("action", 3))
    }
    dataset = LeRobotDataset.create("local/synthetic", fps=10, features=features, root=root, use_videos=False)
    for _ in range(2):
        dataset.add_frame(
            {"observation.state": np.zeros(6, np.float32), "action": np.zeros(3, np.float32), "task": "t"}
        )
    dataset.save_episode()
    dataset.finalize()


HOLDER = (
    "import sys, time; from pathlib import Path; from lerobot_cso.durable import output_lock\n"
    "with output_lock(Path(sys.argv[1])):\n    print('held', flush=True); time.sleep(3600)"
)


def run(attempt: Try, cwd: Path, timeout: float) -> tuple[bool, str, float]:
    """Whether the try ended as it must (an ``error`` of "" must exit 0: ``--help``), what it printed last (or why
    it failed), and its seconds (a holder's start not counted)."""
    env = os.environ | {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "WANDB_MODE": "disabled"}
    holder = None
    if attempt.holds is not None:
        holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(attempt.holds)], stdout=subprocess.PIPE, text=True)
        holder.stdout.readline()  # "held"
    started = time.perf_counter()
    try:
        done = subprocess.run(attempt.command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, f"still running after {timeout:.0f} s", time.perf_counter() - started
    finally:
        if holder is not None:
            holder.kill()
            holder.wait()
    seconds = time.perf_counter() - started
    last = (done.stderr.strip().splitlines() or [""])[-1]
    if "Traceback" in done.stderr:
        return False, f"exit {done.returncode} with a traceback; last line: {last}", seconds
    if not attempt.error:
        return done.returncode == 0 and not done.stderr.strip(), f"exit {done.returncode}: {last}", seconds
    return done.returncode == 2 and last.startswith(attempt.error), f"exit {done.returncode}: {last}", seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the tries whose command line contains this")
    parser.add_argument("--rows", default="", help="run the tries of these rows of the table (a comma list)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds one try may take")
    args = parser.parse_args()
    failed = 0
    with tempfile.TemporaryDirectory(prefix="cli_tries_") as scratch:
        for attempt in tries(Path(scratch)):
            rows = args.rows.split(",") if args.rows else [attempt.row]
            if args.only not in " ".join(attempt.command) or attempt.row not in rows:
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
