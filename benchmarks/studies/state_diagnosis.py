"""Per-initial-state success of a policy: how much of its failure is systematic (the state) vs stochastic (sampling).

Rolls the policy out ``--k`` times from each of ``--states`` initial states per task, drawn from the SPO part
of the training seed range (never the evaluation range), in the world its tasks name (MetaWorld, LIBERO), at the
given sampling settings, and prints per task:
the histogram of successes per state (0 … K), the share of states that always fail / always succeed / are
mixed, the SPO rejection rate this predicts for other group sizes (mean over states of p^K + (1 − p)^K with
the measured per-state rates p), and the entropy of the sampled skill tokens (mean of −log π of the sampled
tokens: an unbiased estimate of the per-token entropy of the sampling distribution), and each state's successes
(to pair states across sampling settings). ``--json`` saves it.

    python benchmarks/studies/state_diagnosis.py --policy_path=CKPT --tasks=reach-v3,button-press-v3 --states=40 --k=8
    python benchmarks/studies/state_diagnosis.py --policy_path=CKPT --tasks=libero_object-0 --states=8 --k=2 \\
        --num_envs=2
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from lerobot_cso import seeds
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.rollout.engine import RolloutEngine
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.base import Rollouts, camera_inputs
from lerobot_cso.worlds.registry import default_world


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy_path", type=Path, required=True)
    parser.add_argument("--tasks", default="reach-v3,button-press-v3,drawer-close-v3")
    parser.add_argument("--states", type=int, default=40)
    parser.add_argument("--k", type=int, default=8)
    parser.add_argument("--temperature", type=float, default=1.0)
    parser.add_argument("--top_k", type=int, default=5)
    parser.add_argument(
        "--max_steps",
        type=int,
        default=None,
        help="the episode cap (default: the world's; the MetaWorld studies recorded before 2026-12-07 ran at 200)",
    )
    parser.add_argument("--num_envs", type=int, default=32)
    parser.add_argument("--seed", type=int, default=7, help="the rollouts' sampling seed")
    parser.add_argument("--vectorization", default="processes")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy, pre, post = load_policy(args.policy_path)
    world = default_world(args.tasks).build(args.tasks, policy.config, None)
    tasks = world.resolve_tasks(args.tasks)
    # The last states of the SPO half of the training range: SPO's own runs start from its first ones.
    first = len(seeds.TRAIN) // 2 - args.states
    states = [(t, s) for t in tasks for s in world.training_states(t, "spo", first, args.states)]
    sampling = Sampling(temperature=args.temperature, top_k=args.top_k)
    features = policy.config.input_features  # a camera policy's too
    horizon = world.horizon if args.max_steps is None else args.max_steps
    cameras = tuple(camera_inputs(features, world).values())
    rollouts = Rollouts(args.num_envs, args.vectorization, horizon, args.max_steps, "decisions", cameras, features)
    with RolloutEngine(policy, pre, post, world.backend(rollouts), world.task_description) as engine:
        result = engine.rollout(states, k=args.k, sampling=sampling, seed=args.seed, progress="diagnosis")
    report = {"policy": str(args.policy_path), "k": args.k, "sampling": vars(sampling), "tasks": {}}
    for task in tasks:
        groups = [g for g in result.groups() if g[0].task == task]
        successes = np.array([sum(e.success for e in g) for g in groups])
        p = successes / args.k
        logp = torch.cat([e.logprobs.reshape(-1) for g in groups for e in g])
        report["tasks"][task] = {
            "success_rate": float(p.mean()),
            "histogram": np.bincount(successes, minlength=args.k + 1).tolist(),
            "always_fail": float(np.mean(successes == 0)),
            "always_succeed": float(np.mean(successes == args.k)),
            "mixed": float(np.mean((successes > 0) & (successes < args.k))),
            "predicted_rejection": {str(k): float(np.mean(p**k + (1 - p) ** k)) for k in (2, 4, 8, 16)},
            "token_entropy_nats": float(-logp.mean()),
            "per_state": {str(g[0].init_seed): int(n) for g, n in zip(groups, successes, strict=True)},
        }
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
