"""Decode latency of one skill on CPU: 8 tokens from the prior + the decoder → 32 actions.

Full-size QueST policy (prior 6×384, autoencoder 256), MetaWorld shapes (state 39, action 4). Reports median and
p99 over repeated calls at batch 1 and 16, with and without the KV cache, decoding the whole chunk (32) or only
the executed prefix (8, what ``select_action`` and the rollout engine decode). Run:
    ./run.sh python benchmarks/decode_latency.py [--iters 300] [--threads 2]
"""

from __future__ import annotations

import argparse
import platform
import shlex
import sys
import time

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_cso.policy import CSOConfig, CSOPolicy


def measure(policy: CSOPolicy, batch_size: int, use_cache: bool, n_actions: int, iters: int) -> tuple[float, float]:
    batch = {"observation.state": torch.randn(batch_size, 39), "task": ["reach"] * batch_size}
    times = []
    with torch.inference_mode():
        for i in range(iters + 20):
            start = time.perf_counter()
            context = policy.encode_context(batch)
            tokens, _ = policy.sample_skills(context, top_k=5, use_cache=use_cache)
            policy.decode_skills(tokens, n_actions)
            if i >= 20:  # warm-up
                times.append(time.perf_counter() - start)
    ms = np.array(times) * 1000
    return float(np.median(ms)), float(np.percentile(ms, 99))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=300)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    config = CSOConfig(
        device="cpu",
        tasks=["reach"],
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (39,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    policy = CSOPolicy(config).eval()
    print(f"# command: python {shlex.join(sys.argv)}")
    print(f"# torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}")
    print("| batch | KV cache | decoded actions | median ms | p99 ms |")
    print("|---:|:---:|---:|---:|---:|")
    for batch_size in (1, 16):
        for use_cache, n_actions in ((True, 32), (False, 32), (True, config.n_action_steps)):
            median, p99 = measure(policy, batch_size, use_cache, n_actions, args.iters)
            print(f"| {batch_size} | {'yes' if use_cache else 'no'} | {n_actions} | {median:.2f} | {p99:.2f} |")


if __name__ == "__main__":
    main()
