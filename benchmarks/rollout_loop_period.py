"""Control-loop period of ``lerobot-rollout`` with a full-size cso policy on the simulated PiPER, at 30 Hz.

Saves an untrained full-size policy (prior 6×384, autoencoder 256) with the PiPER's 7-D state and action, starts
``piper-emulator`` on a private udp_multicast channel, runs ``lerobot-rollout --strategy.type=base`` against it
once per variant (synchronous decode, and the background decode started ``--lead`` ticks before the queue runs
dry), and measures the loop period from the kernel receive times of the joint commands on the bus. Run:
    ./run.sh python benchmarks/rollout_loop_period.py [--duration 60] [--lead 3] [--weights float32]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from lerobot_robot_piper.cli_processes import explain, rollout_args, run_cli
from piper_can.channel_recorder import ChannelRecorder
from piper_can.emulator_process import start_emulator, unique_udp_channel

from lerobot_cso.untrained import save_untrained_policy

TASK = "hold still"
BINS_MS = (0, 30, 32, 33, 34, 35, 36.7, 40, 50, 70, 100, 1000, float("inf"))


def save_untrained_piper_policy(
    path: Path,
    lead: int,
    weights: str,
    settings: dict | None = None,
    cameras: tuple[str, ...] = (),
    side: int = 0,
    task: str = TASK,
) -> Path:
    """Untrained cso policy for ``task`` on the PiPER (7-D state and action, plus ``cameras`` at ``side`` x
    ``side``), of the default size or with ``settings`` (CSOConfig fields), saved with its processors."""
    images = {f"observation.images.{c}": (3, side, side) for c in cameras}
    # Actions stay within ±0.1 rad of home (gripper 0 … 2 cm): the untrained policy only jitters.
    stats = {
        "observation.state": {"mean": torch.zeros(7), "std": torch.ones(7)},
        "action": {"min": torch.tensor([-0.1] * 6 + [0.0]), "max": torch.tensor([0.1] * 6 + [0.02])},
    }
    stats |= {key: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)} for key in images}
    settings = {"async_decode_lead": lead, "inference_weights": weights} | (settings or {})
    return save_untrained_policy(path, stats, [task], 7, 7, images, **settings)


def loop_periods_ms(checkpoint: Path, home: Path, duration: float, fps: int) -> np.ndarray:
    """Run lerobot-rollout against a fresh emulator; periods between consecutive joint commands (ms)."""
    follower = start_emulator(*unique_udp_channel())
    recorder = ChannelRecorder(follower.group, follower.port)
    try:
        robot = ["--robot.type=piper_follower", *follower.args("robot"), "--robot.feedback_timeout_s=1.0"]
        out = run_cli(
            "lerobot-rollout",
            # the emulator shares the CPUs with the policy: feedback may come up to 1 s late
            [*rollout_args(checkpoint, robot, TASK, duration, fps), "--return_to_initial_position=false"],
            home,
            timeout=duration + 240,
        )
    finally:
        recorder.stop()
        follower.stop()
    if out.returncode != 0:
        raise RuntimeError(explain(out))
    times = np.array([c.time_s for c in recorder.commands.joints])
    times = times[times >= times[0] + 1.0]  # the first second: connection and the first decode
    return np.diff(times) * 1000


def report(name: str, periods: np.ndarray, limit_ms: float) -> None:
    counts, _ = np.histogram(periods, bins=BINS_MS)
    print(
        f"\n{name}: {len(periods)} periods, median {np.median(periods):.2f} ms, p99 {np.percentile(periods, 99):.2f}"
        f" ms, max {periods.max():.2f} ms, over {limit_ms:.1f} ms: {(periods > limit_ms).sum()}"
    )
    print("| period ms | " + " | ".join(f"{a:g}–{b:g}" for a, b in zip(BINS_MS, BINS_MS[1:], strict=False)) + " |")
    print("|---|" + "---:|" * len(counts))
    print("| ticks | " + " | ".join(str(c) for c in counts) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--lead", type=int, default=3)
    parser.add_argument("--weights", default="float32")
    args = parser.parse_args()
    limit_ms = 1.1 * 1000 / args.fps
    print(f"# command: python {shlex.join(sys.argv)}")
    with open("/proc/loadavg") as f:
        print(f"# load average before: {f.read().strip()}")
    with tempfile.TemporaryDirectory() as tmp:
        home = Path(tmp)
        for name, lead in (("synchronous decode", 0), (f"background decode, lead {args.lead}", args.lead)):
            checkpoint = save_untrained_piper_policy(home / f"policy_lead{lead}", lead, args.weights)
            report(f"{name} ({args.weights})", loop_periods_ms(checkpoint, home, args.duration, args.fps), limit_ms)
            with open("/proc/loadavg") as f:
                print(f"# load average after: {f.read().strip()}")


if __name__ == "__main__":
    main()
