"""Rollout throughput of ``lerobot-cso eval`` on 1 and on N processes (accelerate launch, one env pool each).

Each process steps its envs in-process (``--vectorization=sync``), so the ratio is what process-level scale-out
buys on this machine. Run:
    ./run.sh python benchmarks/distributed_rollouts.py --policy_path=CKPT [--processes=2] [--episodes_per_task=30]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def eval_run(args: argparse.Namespace, processes: int, out: Path) -> tuple[float, float]:
    """(env steps per second of the rollouts, wall seconds of the whole command) of one evaluation."""
    stage = [
        "eval",
        f"--policy.path={args.policy_path}",
        f"--tasks={args.tasks}",
        f"--episodes_per_task={args.episodes_per_task}",
        f"--num_envs={args.num_envs}",
        f"--max_steps={args.max_steps}",
        "--vectorization=sync",
        f"--output_dir={out}",
    ]
    if processes == 1:
        command = [str(BIN / "lerobot-cso"), *stage]
    else:
        command = [str(BIN / "accelerate"), "launch", "--multi_gpu", f"--num_processes={processes}"]
        command += ["--num_machines=1", "--mixed_precision=no", "--dynamo_backend=no", "--main_process_port=0"]
        command += ["-m", "lerobot_cso.cli", *stage]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    started = time.perf_counter()
    subprocess.run(command, env=env, check=True, capture_output=True)
    wall = time.perf_counter() - started
    record = json.loads((out / "eval.json").read_text())
    steps = sum(e["length"] for e in record["episodes"])
    rollout_seconds = steps / record["throughput"][0]["env_steps_per_s"]
    return steps / rollout_seconds, wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy_path", required=True)
    parser.add_argument("--tasks", default="reach-v3,button-press-v3,drawer-close-v3")
    parser.add_argument("--episodes_per_task", type=int, default=30)
    parser.add_argument("--num_envs", type=int, default=16, help="envs per process")
    parser.add_argument("--max_steps", type=int, default=200)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2, help="alternating 1-process / N-process runs")
    args = parser.parse_args()
    print(f"# command: python {shlex.join(sys.argv)}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    rates: dict[int, list[tuple[float, float]]] = {1: [], args.processes: []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for n in rates:
                rates[n].append(eval_run(args, n, Path(tmp) / f"{n}_{r}"))
    print("| processes | env steps/s (each round) | command wall s (each round) |")
    print("|---:|---|---|")
    for n, runs in rates.items():
        print(f"| {n} | {', '.join(f'{s:.0f}' for s, _ in runs)} | {', '.join(f'{w:.0f}' for _, w in runs)} |")
    ratio = [n_run[0] / one[0] for one, n_run in zip(rates[1], rates[args.processes], strict=True)]
    print(f"\n{args.processes} / 1 process throughput ratio per round: {', '.join(f'{x:.2f}' for x in ratio)}")
    print(f"# load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
