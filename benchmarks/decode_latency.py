"""Decode latency of one skill on CPU: context + 8 tokens from the prior + decoding the executed 8 actions.

Full-size QueST policy (prior 6×384, autoencoder 256), MetaWorld shapes (state 39, action 4). Compares, in one
run and interleaved call by call (so load changes hit every path alike), the prior's reference sampler
(``sample_skills``, fp32, KV cache) with the inference sampler ``select_action`` uses (``FastSkillSampler``:
fp32, and weight-only int8), at batch 1 and 16: median and p99 latency, and skills/s at batch 16. Run:
    ./run.sh python benchmarks/decode_latency.py [--iters 200] [--threads 1]
"""

from __future__ import annotations

import argparse
import platform
import shlex
import sys
import time
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from lerobot_cso.policy import CSOPolicy
from lerobot_cso.policy.fast_prior import FastSkillSampler
from lerobot_cso.sampling import Sampling
from lerobot_cso.untrained import untrained_policy

WARMUP = 10


def paths(policy: CSOPolicy) -> dict[str, Callable[[Tensor], tuple[Tensor, Tensor]]]:
    """Token samplers by name, each (context) → (tokens, log-probs), top-k 5."""
    fast = {w: FastSkillSampler(policy.prior, w) for w in ("float32", "int8")}
    return {
        "reference fp32 (sample_skills)": lambda c: policy.sample_skills(c, Sampling(top_k=5)),
        "fast fp32": lambda c: fast["float32"].sample(c, Sampling(top_k=5)),
        "fast int8": lambda c: fast["int8"].sample(c, Sampling(top_k=5)),
    }


def measure(policy: CSOPolicy, batch_size: int, iters: int) -> dict[str, np.ndarray]:
    """Milliseconds per skill for every path, interleaved."""
    batch = {"observation.state": torch.randn(batch_size, 39), "task": ["reach"] * batch_size}
    samplers = paths(policy)
    times: dict[str, list[float]] = {name: [] for name in samplers}
    with torch.inference_mode():
        for i in range(iters + WARMUP):
            for name, sample in samplers.items():
                start = time.perf_counter()
                tokens, _ = sample(policy.encode_context(batch))
                policy.decode_skills(tokens, policy.config.n_action_steps)
                if i >= WARMUP:
                    times[name].append(time.perf_counter() - start)
    return {name: np.array(t) * 1000 for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=200)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = untrained_policy(["reach"], state_dim=39, action_dim=4).eval()  # full size, MetaWorld shapes
    print(f"# command: python {shlex.join(sys.argv)}")
    print(f"# torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}")
    with open("/proc/loadavg") as f:
        print(f"# load average before: {f.read().strip()}")
    print("| batch | path | median ms | p99 ms | skills/s (median) |")
    print("|---:|:---|---:|---:|---:|")
    for batch_size in (1, 16):
        for name, ms in measure(policy, batch_size, args.iters).items():
            median, p99 = float(np.median(ms)), float(np.percentile(ms, 99))
            print(f"| {batch_size} | {name} | {median:.2f} | {p99:.2f} | {batch_size * 1000 / median:.0f} |")
    with open("/proc/loadavg") as f:
        print(f"# load average after: {f.read().strip()}")


if __name__ == "__main__":
    main()
