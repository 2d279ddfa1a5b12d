"""Rollout efficiency: policy-driven rollout throughput ÷ scripted-expert throughput, measured in one run.

Both sides run the same tasks, initial states (from the training range) and number of envs; the scripted
experts step in one process (one core, ``sync``), the policy rollouts with ``--vectorization`` (default
``processes``: one worker per core). Measurements alternate between the two for ``--rounds`` rounds so that
load from other processes hits both alike. Throughput is env steps per wall-clock second, resets and (for the
policy) batched inference included. Goal: ratio >= 1.6 with both cores. The experts end their episodes
sooner and so reset more often per step; the ratio without reset time is printed as well. A camera policy's envs
give what it reads (its state layout, its camera at its image size) and render only the frames its decisions
read, as evaluation and SPO do; the experts' envs render nothing.

Without ``--policy_path`` a small cso policy is made first: scripted demos for the tasks, then
``lerobot-train`` for ``--train_steps`` steps (half autoencoder, half prior).

    python benchmarks/rollout_efficiency.py                       # small policy, 4 tasks, 16 envs
    python benchmarks/rollout_efficiency.py --policy_path=outputs/train/.../pretrained_model
    python benchmarks/rollout_efficiency.py --policy_path=... --device=cuda   # the policy's decisions on a GPU
"""

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lerobot_cso import seeds
from lerobot_cso.demos import DemosConfig, generate_demos
from lerobot_cso.rollout.engine import RolloutEngine
from lerobot_cso.rollout.pool import EnvPool, Job
from lerobot_cso.rollout.sharded import ShardedVectorEnv
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.expert import ExpertController
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.metaworld.world import policy_pool
from lerobot_cso.worlds.metaworld.world import pool as metaworld_pool

SMALL_POLICY = [
    "--policy.ae_dim=128",
    "--policy.ae_heads=4",
    "--policy.ae_encoder_layers=2",
    "--policy.ae_decoder_layers=2",
    "--policy.prior_dim=192",
    "--policy.prior_heads=4",
    "--policy.prior_layers=4",
    "--policy.state_embed_dim=64",
]


def train_small_policy(tasks: str, steps: int, work: Path) -> Path:
    """Demos (10 per task) + ``lerobot-train`` of a small cso policy; returns the checkpoint directory."""
    demos = work / "demos"
    generate_demos(DemosConfig(tasks=tasks, episodes_per_task=10, output_dir=demos, num_envs=4))
    cmd = [
        str(Path(sys.executable).parent / "lerobot-train"),
        "--policy.type=cso",
        "--dataset.repo_id=local/benchmark_demos",
        f"--dataset.root={demos}",
        f"--output_dir={work / 'train'}",
        f"--steps={steps}",
        f"--save_freq={steps}",
        f"--policy.n_autoencoder_steps={steps // 2}",
        "--batch_size=32",
        "--num_workers=0",
        "--log_freq=50",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        *SMALL_POLICY,
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"}
    subprocess.run(cmd, check=True, env=env)
    return work / "train" / "checkpoints" / "last" / "pretrained_model"


def expert_round(pool: EnvPool, jobs: list[Job]) -> tuple[int, float, float]:
    """Env steps, seconds and mean episode length of the scripted experts on ``jobs``."""
    started = time.perf_counter()
    traces = [trace for _, trace in pool.run(jobs, ExpertController(pool.num_envs, noise_std=0.2, seed=0))]
    seconds = time.perf_counter() - started
    lengths = [t.length for t in traces]
    return sum(lengths), seconds, float(np.mean(lengths))


def mean_reset_seconds(pool: EnvPool, tasks: list[str], n: int = 10) -> float:
    """Mean wall time of one seeded reset (tasks already built), to show throughput without resets too."""
    env = pool.vec.envs[0]
    started = time.perf_counter()
    for task in tasks:
        for seed in seeds.train_seeds(n):
            env.reset(seed=seed, options={"task": task})
    env.reset(options={"park": True})
    return (time.perf_counter() - started) / (n * len(tasks))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", default="reach-v3,button-press-v3,pick-place-v3,door-open-v3")
    ap.add_argument("--num_envs", type=int, default=16)
    ap.add_argument("--policy_episodes", type=int, default=4, help="policy episodes per task per round")
    ap.add_argument("--expert_episodes", type=int, default=12, help="expert episodes per task per round")
    ap.add_argument("--max_steps", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the experts use one core)")
    ap.add_argument("--train_steps", type=int, default=200)
    ap.add_argument("--policy_path", type=Path, default=None)
    ap.add_argument("--vectorization", default="processes", help="of the policy rollouts (the experts: sync)")
    ap.add_argument("--device", default="cpu", help="the policy's device (e.g. cuda)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    tasks = args.tasks.split(",")

    from lerobot.configs.policies import PreTrainedConfig

    from lerobot_cso.checkpoints import load_policy

    with tempfile.TemporaryDirectory() as tmp:
        path = args.policy_path or train_small_policy(args.tasks, args.train_steps, Path(tmp))
        config = PreTrainedConfig.from_pretrained(path)
        config.device = args.device
        policy, pre, post = load_policy(path, config)
        policy.eval()
    n_params = sum(p.numel() for p in policy.parameters())

    policy_states = [(t, s) for t in tasks for s in seeds.train_seeds(args.policy_episodes)]
    expert_jobs = [Job(t, s) for t in tasks for s in seeds.train_seeds(args.expert_episodes)]
    totals = {"expert": [0, 0.0], "policy": [0, 0.0]}
    episodes = {"expert": 0, "policy": 0}
    lengths: dict[str, list[float]] = {"expert": [], "policy": []}
    decisions, policy_seconds = 0, 0.0
    with (
        policy_pool(
            policy.config.input_features, args.num_envs, args.max_steps, args.vectorization, frames="decisions"
        ) as envs,
        metaworld_pool(args.num_envs, max_steps=args.max_steps, vectorization="sync") as pool,
        RolloutEngine(policy, pre, post, envs, task_description) as engine,
    ):
        # The processes that step (and reset) the policy's envs in parallel.
        workers = len(envs.vec.shards) if isinstance(envs.vec, ShardedVectorEnv) else 1
        expert_round(pool, expert_jobs[:: args.expert_episodes])  # warm-up: build every task's models
        engine.rollout(policy_states[:: args.policy_episodes], sampling=Sampling())
        for r in range(args.rounds):
            steps, seconds, mean_len = expert_round(pool, expert_jobs)
            totals["expert"][0] += steps
            totals["expert"][1] += seconds
            lengths["expert"].append(mean_len)
            episodes["expert"] += len(expert_jobs)
            result = engine.rollout(policy_states, sampling=Sampling(), seed=r)
            totals["policy"][0] += result.env_steps
            totals["policy"][1] += result.seconds
            lengths["policy"].append(np.mean([e.length for e in result.episodes]))
            episodes["policy"] += len(result.episodes)
            decisions += result.decisions
            policy_seconds += result.policy_seconds
            print(
                f"round {r}: expert {steps / seconds:7.0f} steps/s | policy {result.env_steps_per_s:7.0f} steps/s, "
                f"{result.decisions_per_s:6.0f} decisions/s, success {result.success_rate:.0%}",
                flush=True,
            )
        reset_s = mean_reset_seconds(pool, tasks)

    expert_rate = totals["expert"][0] / totals["expert"][1]
    policy_rate = totals["policy"][0] / totals["policy"][1]
    print("\ncommand:", shlex.join([sys.executable, *sys.argv]))
    print(
        f"machine: {os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}; experts: sync vector env (one "
        f"core); policy: {args.vectorization}"
    )
    print(f"tasks: {', '.join(tasks)}; envs: {args.num_envs}; max steps: {args.max_steps}; rounds: {args.rounds}")
    print(f"policy: {path} ({n_params / 1e6:.2f} M parameters) on {args.device}, top-k 5, T 1")
    print(
        f"scripted experts: {totals['expert'][0]} steps in {totals['expert'][1]:.1f} s = {expert_rate:.0f} steps/s "
        f"(mean episode {np.mean(lengths['expert']):.0f} steps)"
    )
    print(
        f"policy rollouts:  {totals['policy'][0]} steps in {totals['policy'][1]:.1f} s = {policy_rate:.0f} steps/s, "
        f"{decisions / totals['policy'][1]:.0f} decisions/s, inference {policy_seconds / totals['policy'][1]:.0%} "
        f"of the time (mean episode {np.mean(lengths['policy']):.0f} steps)"
    )
    ratio = policy_rate / expert_rate
    print(f"rollout efficiency = {ratio:.2f} (policy with {args.vectorization} ÷ single-core experts; goal >= 1.6)")
    # The experts finish episodes sooner, so they pay for more resets per step; without resets (an estimate: the
    # policy's resets are spread evenly over its worker processes):
    reset_time = {"expert": episodes["expert"] * reset_s, "policy": episodes["policy"] * reset_s / workers}
    stepping = {k: totals[k][0] / (totals[k][1] - reset_time[k]) for k in totals}
    print(
        f"without resets ({1000 * reset_s:.1f} ms each, policy over {workers} processes): expert "
        f"{stepping['expert']:.0f}, policy "
        f"{stepping['policy']:.0f} steps/s, ratio {stepping['policy'] / stepping['expert']:.2f}"
    )


if __name__ == "__main__":
    main()
