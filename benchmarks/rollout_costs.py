"""What a camera costs in the loop: policy-in-the-loop env steps/s of policies on the same tasks (a camera policy
against a state-only one), and one env step's cost split into sim / render / encoder / prior / decode (issue 33).

Throughput: each policy's :class:`~lerobot_cso.rollout.engine.RolloutEngine` on its own pool (``processes``: one
worker per core; envs that render only the frames a decision reads, as evaluation and SPO do), the policies
alternating for ``--rounds`` rounds on the same training-range states; env steps per wall-clock second, resets and
batched inference included.

Cost split, on one core in this process: ``sim`` is one ``step`` of an env without a camera, ``render`` one frame
of each camera the policy reads, and per decision row (a batch of ``--num_envs`` observations) ``encoder`` (the
processors and the observation encoders), ``prior`` (sampling the skill's tokens) and ``decode`` (the executed
actions). Per env step: sim + render / n_action_steps + (encoder + prior + decode) / n_action_steps.

    python benchmarks/rollout_costs.py --policies=CAMERA/pretrained_model,STATE/pretrained_model \\
        --tasks=button-press-topdown-v3,door-open-v3,window-open-v3 --out=benchmarks/results/rollout_costs.json
"""

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.utils import preprocess_observation

from lerobot_cso import seeds
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.durable import write_atomic
from lerobot_cso.rollout.engine import RolloutEngine
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.metaworld.world import env_inputs, policy_pool


def policy_env(features: dict[str, Any], task: str) -> CSOMetaWorldEnv:
    """An env giving what a policy with these input features reads (as :func:`policy_pool` builds them)."""
    cameras, size, state = env_inputs(features)
    return CSOMetaWorldEnv(task, cameras, size, state=state)


def seconds_per_call(fn: Any, n: int) -> float:
    started = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - started) / n


def sim_and_render(features: dict[str, Any], tasks: list[str], steps: int) -> dict[str, float]:
    """Seconds of one env step without a camera, and of one frame of the policy's cameras (all of them)."""
    rng = np.random.default_rng(0)
    sim, render = [], []
    for task in tasks:
        bare = CSOMetaWorldEnv(task, state=env_inputs(features)[2])
        bare.reset(seed=seeds.train_seeds(1)[0])
        sim.append(seconds_per_call(lambda env=bare: env.step(rng.uniform(-1, 1, 4).astype(np.float32)), steps))
        bare.close()
        if env_inputs(features)[0]:
            env = policy_env(features, task)
            env.reset(seed=seeds.train_seeds(1)[0])  # renders the first frame: the renderer is built
            render.append(len(env.cameras) * seconds_per_call(env.render, steps // 4))
            env.close()
    return {"sim": float(np.mean(sim)), "render": float(np.mean(render)) if render else 0.0}


def decision_costs(path: Path, tasks: list[str], rows: int, repeats: int) -> dict[str, float]:
    """Seconds per decision row of the encoder (with the processors), the prior and the decode, in batches of
    ``rows`` observations from training-range initial states."""
    policy, pre, post = load_policy(path, PreTrainedConfig.from_pretrained(path))
    policy.eval()
    features = policy.config.input_features
    env = policy_env(features, tasks[0])
    observations, descriptions = [], []
    for i, seed in enumerate(seeds.train_seeds(rows)):
        task = tasks[i % len(tasks)]
        observations.append(env.reset(seed=seed, options={"task": task})[0])
        descriptions.append(task_description(task))
    env.close()
    raw: dict[str, Any] = {"agent_pos": np.stack([o["agent_pos"] for o in observations])}
    if "pixels" in observations[0]:
        raw["pixels"] = {cam: np.stack([o["pixels"][cam] for o in observations]) for cam in observations[0]["pixels"]}
    timing = {"encoder": 0.0, "prior": 0.0, "decode": 0.0}
    with torch.no_grad():
        for _ in range(repeats):
            started = time.perf_counter()
            batch = preprocess_observation(raw)
            batch["task"] = descriptions
            context = policy.encode_context(pre(batch))
            encoded = time.perf_counter()
            tokens, _ = policy.sample_skills(context, Sampling())
            sampled = time.perf_counter()
            chunk = policy.decode_skills(tokens, policy.config.n_action_steps)
            post(chunk.reshape(-1, chunk.shape[-1]))
            done = time.perf_counter()
            timing["encoder"] += encoded - started
            timing["prior"] += sampled - encoded
            timing["decode"] += done - sampled
    return {k: v / (repeats * rows) for k, v in timing.items()}


def throughput(paths: list[Path], tasks: list[str], args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """Env steps/s and inference share of each policy's rollouts, the policies alternating per round."""
    states = [(t, s) for t in tasks for s in seeds.train_seeds(args.episodes)]
    totals = {str(p): {"env_steps": 0, "seconds": 0.0, "policy_seconds": 0.0, "successes": 0} for p in paths}
    engines = []
    for path in paths:
        policy, pre, post = load_policy(path, PreTrainedConfig.from_pretrained(path))
        policy.eval()
        pool = policy_pool(policy.config.input_features, args.num_envs, args.max_steps, frames="decisions")
        engines.append(RolloutEngine(policy, pre, post, pool, task_description))
    try:
        for engine in engines:  # warm-up: workers started, every task's model built
            engine.rollout(states[:: args.episodes], sampling=Sampling())
        for r in range(args.rounds):
            for path, engine in zip(paths, engines, strict=True):
                result = engine.rollout(states, sampling=Sampling(), seed=r)
                total = totals[str(path)]
                total["env_steps"] += result.env_steps
                total["seconds"] += result.seconds
                total["policy_seconds"] += result.policy_seconds
                total["successes"] += sum(e.success for e in result.episodes)
                print(f"round {r}: {path}: {result.env_steps_per_s:.0f} env steps/s", flush=True)
    finally:
        for engine in engines:
            engine.close()
    return {
        p: {
            "env_steps_per_s": t["env_steps"] / t["seconds"],
            "inference_share": t["policy_seconds"] / t["seconds"],
            "success_rate": t["successes"] / (args.rounds * len(states)),
            **t,
        }
        for p, t in totals.items()
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policies", required=True, help="comma-separated pretrained_model directories")
    ap.add_argument("--tasks", default="button-press-topdown-v3,door-open-v3,window-open-v3")
    ap.add_argument("--num_envs", type=int, default=48, help="envs of each pool, and rows of a decision batch")
    ap.add_argument("--episodes", type=int, default=16, help="policy episodes per task per round")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--max_steps", type=int, default=200)
    ap.add_argument("--sim_steps", type=int, default=400, help="timed env steps per task for the cost split")
    ap.add_argument("--out", type=Path, default=None, help="write the measurements as JSON here")
    args = ap.parse_args()
    paths = [Path(p) for p in args.policies.split(",")]
    if missing := [str(p) for p in paths if not (p / "config.json").is_file()]:
        ap.error(f"not a policy checkpoint (no config.json): {', '.join(missing)}")
    torch.set_num_threads(1)  # as the rollout stages run the policy (torch_threads: 1)
    tasks = args.tasks.split(",")
    report: dict[str, Any] = {
        "command": shlex.join([sys.executable, *sys.argv]),
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{os.cpu_count()} CPUs, torch threads 1",
        "throughput": throughput(paths, tasks, args),
        "cost_split_seconds": {},
    }
    for path in paths:
        features = PreTrainedConfig.from_pretrained(path).input_features
        split = sim_and_render(features, tasks, args.sim_steps) | decision_costs(path, tasks, args.num_envs, 5)
        n = PreTrainedConfig.from_pretrained(path).n_action_steps
        per_step = {"sim": split["sim"]} | {k: split[k] / n for k in ("render", "encoder", "prior", "decode")}
        report["cost_split_seconds"][str(path)] = {"measured": split, "per_env_step": per_step}
        shares = ", ".join(f"{k} {v / sum(per_step.values()):.0%}" for k, v in per_step.items())
        print(f"{path}: {1000 * sum(per_step.values()):.2f} ms per env step on one core ({shares})")
    for path, t in report["throughput"].items():
        print(f"{path}: {t['env_steps_per_s']:.0f} env steps/s, inference {t['inference_share']:.0%} of the time")
    if args.out:
        write_atomic(args.out, json.dumps(report, indent=2).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
