"""Where a LIBERO env step's time goes on a CPU: the hard reset, the physics step, and the render of the policy's
cameras, per task, in this process on one core (the policy's share is in the evaluations' records).

Per task, one :class:`~lerobot_cso.worlds.libero.env.CSOLiberoEnv` with the cameras at ``--image_size``: its first
reset (the model built), then ``--resets`` hard resets to demo placements, then ``--steps`` steps with small random
actions rendering every frame and as many rendering none. ``render`` is the difference per step; a policy that
decides every 8 steps and renders only those frames (``frames="decisions"``) pays render / 8 per step.

    python benchmarks/libero_costs.py --tasks=libero_object-0,libero_object-1 --out=benchmarks/results/libero_costs.json
"""

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from harness import provenance

from lerobot_cso import seeds
from lerobot_cso.durable import write_atomic
from lerobot_cso.worlds.libero.env import CSOLiberoEnv

NEVER = 10**9  # a render cadence no episode reaches


def seconds_per_step(env: CSOLiberoEnv, seed: int, render_every: int, steps: int, rng: np.random.Generator) -> float:
    env.reset(seed=seed, options={"render_every": render_every})
    started = time.perf_counter()
    for _ in range(steps):
        env.step(rng.uniform(-0.3, 0.3, 7).astype(np.float32))
    return (time.perf_counter() - started) / steps


def task_costs(task: str, cameras: tuple[str, ...], size: int, resets: int, steps: int) -> dict[str, float]:
    placements = [seeds.DEMO_PLACEMENTS[i] for i in range(resets + 1)]
    rng = np.random.default_rng(0)
    env = CSOLiberoEnv(task, cameras, size)
    try:
        started = time.perf_counter()
        env.reset(seed=placements[0])
        first = time.perf_counter() - started
        times = []
        for seed in placements[1:]:
            started = time.perf_counter()
            env.reset(seed=seed)
            times.append(time.perf_counter() - started)
        every = seconds_per_step(env, placements[0], 1, steps, rng)
        none = seconds_per_step(env, placements[0], NEVER, steps, rng)
    finally:
        env.close()
    return {
        "first_reset_s": first,
        "hard_reset_s": statistics.median(times),
        "physics_step_s": none,
        "render_step_s": every - none,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", default="libero_object-0")
    parser.add_argument("--cameras", default="image,image2")
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--resets", type=int, default=3, help="timed hard resets per task (after the first)")
    parser.add_argument("--steps", type=int, default=100, help="timed steps per task, with and without rendering")
    parser.add_argument("--out", type=Path, default=Path("outputs/libero_costs.json"))
    args = parser.parse_args()
    if args.resets < 1 or args.steps < 1:
        parser.error("--resets and --steps must be >= 1")
    cameras = tuple(c for c in args.cameras.split(",") if c)
    rows, load = {}, [os.getloadavg()[0]]
    for task in args.tasks.split(","):
        rows[task] = task_costs(task, cameras, args.image_size, args.resets, args.steps)
        print(task, {k: round(v, 4) for k, v in rows[task].items()}, flush=True)
    mean = {k: statistics.mean(r[k] for r in rows.values()) for k in next(iter(rows.values()))}
    report = {
        "command": "python benchmarks/libero_costs.py " + " ".join(sys.argv[1:]),
        "cameras": list(cameras),
        "image_size": args.image_size,
        "tasks": rows,
        "mean": mean,
        "load_average": load + [os.getloadavg()[0]],  # 1-min, before and after: the machine is shared
        **provenance(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(report, indent=2).encode())
    print(f"[libero_costs] wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
