"""What the skill autoencoder alone costs on the twin: recorded demonstrations replayed open-loop on
``piper_twin_sim``, as recorded and as each checkpoint's autoencoder reconstructs them.

A policy can only act through its autoencoder's decoder: if the decoded skills cannot redo the demonstrations, no
prior can. For each demonstration (its scene placed from the seed it was recorded with, the arm moved to the rest
pose first, as ``benchmarks/twin_table5.py`` does before every episode), the recorded actions are sent at ``--fps``,
then, per ``--policy``, the same actions with every executed prefix (``n_action_steps``) replaced by the
autoencoder's reconstruction of the ``chunk_size`` actions that start there (normalised and unnormalised by the
checkpoint's own processors). Success is the scene's, checked after every step and for 2 s after the last action.
The reconstruction error per joint (mean |error| over the executed prefixes, in rad and m) is reported beside it.

    python benchmarks/twin_skill_replay.py --work=outputs/twin_table5/cube_in_bowl --episodes=20 \\
        --policy=outputs/twin_table5/cube_in_bowl/il/checkpoints/last/pretrained_model
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
from harness import Reconstruction
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot_robot_piper.config_piper_twin_sim import PiperTwinSimConfig
from lerobot_robot_piper.piper_twin_sim import PiperTwinSim
from twin_table5 import REST_POSE, SETTLE_S

TAIL_S = 2.0  # the last action held this long before the verdict


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="a task's folder of twin_table5 (demos, its attempts log)")
    p.add_argument("--scene", default=None, help="the twin scene (default: the --work folder's name)")
    p.add_argument("--policy", action="append", default=[], help="a checkpoint whose autoencoder replays (repeatable)")
    p.add_argument("--episodes", type=int, default=20, help="the first N demonstrations")
    p.add_argument("--fps", type=int, default=10)
    p.add_argument("--rest-time-s", type=float, default=3.0)
    p.add_argument("--out", type=Path, default=None, help="write the results here as JSON")
    args = p.parse_args(argv)
    if args.episodes < 1 or args.fps < 1:
        p.error(f"--episodes and --fps must be >= 1, got {args.episodes} and {args.fps}")
    if not 0 <= args.rest_time_s < float("inf"):
        p.error(f"--rest-time-s must be a finite number >= 0, got {args.rest_time_s}")
    if not (args.work / "demos_attempts.jsonl").is_file() or not (args.work / "demos").is_dir():
        p.error(f"--work={args.work} holds no demos/ and demos_attempts.jsonl (a task folder of twin_table5.py)")
    if args.out is not None and not os.access(args.out.parent, os.W_OK):
        p.error(f"--out={args.out}: its folder does not exist or is not writable")
    return args


def replay(robot: PiperTwinSim, seed: int, actions: np.ndarray, fps: int, rest_time_s: float) -> bool:
    """Rest pose, scene ``seed``, then ``actions`` one per control period; the scene's verdict."""
    keys = list(robot.action_features)
    rest = np.array(REST_POSE)
    observation = robot.get_observation()
    start = np.array([observation[k] for k in keys])
    steps = max(1, round(rest_time_s * fps))
    for i in range(1, steps + 1):
        robot.send_action(dict(zip(keys, map(float, start + (rest - start) * i / steps), strict=True)))
    robot.plant.place(seed)
    robot.pass_time(SETTLE_S)
    held = [actions[-1]] * round(TAIL_S * fps)
    for action in [*actions, *held]:
        robot.send_action(dict(zip(keys, map(float, action), strict=True)))
        if robot.plant.succeeded():
            return True
    return False


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    scene = args.scene or args.work.name
    attempts = [json.loads(line) for line in (args.work / "demos_attempts.jsonl").read_text().splitlines()]
    seeds = [a["seed"] for a in attempts if a["success"]]  # demonstration k was recorded from the k-th kept seed
    dataset = LeRobotDataset(f"local/twin_{scene}", root=args.work / "demos")
    frames = dataset.hf_dataset.with_format("numpy")
    index, all_actions = np.asarray(frames["episode_index"]), np.stack(frames["action"]).astype(np.float64)
    filters = {"recorded": None} | {path: Reconstruction(path) for path in args.policy}
    robot = PiperTwinSim(
        PiperTwinSimConfig(
            scene=scene, fps=args.fps, channel=f"skill-replay-{scene}", initial_pose=list(REST_POSE[:6]),
            motion_mode="position", speed_percent=100,
        )
    )  # fmt: skip
    robot.connect()
    results = {name: {"success": [], "abs_error": []} for name in filters}
    try:
        for episode in range(min(args.episodes, len(seeds))):
            actions = all_actions[index == episode]
            for name, reconstruct in filters.items():
                sent = actions if reconstruct is None else reconstruct(actions)
                results[name]["success"].append(replay(robot, seeds[episode], sent, args.fps, args.rest_time_s))
                results[name]["abs_error"].append(np.abs(sent - actions).mean(0).tolist())
            verdicts = ", ".join("ok" if r["success"][-1] else "FAIL" for r in results.values())
            print(f"demo {episode} (seed {seeds[episode]}): {verdicts}", flush=True)
    finally:
        robot.disconnect()
    summary = {
        name: {
            "success_rate": float(np.mean(r["success"])),
            "episodes": len(r["success"]),
            "mean_abs_error_per_joint": np.mean(r["abs_error"], axis=0).round(4).tolist(),
        }
        for name, r in results.items()
    }
    for name, s in summary.items():
        errors = s["mean_abs_error_per_joint"]
        print(f"{s['success_rate']:.2f} ({s['episodes']} demos)  error per joint {errors}  {name}")
    if args.out is not None:
        record = {"command": shlex.join(["python", *sys.argv]), "date": time.strftime("%Y-%m-%d"), "results": summary}
        args.out.write_text(json.dumps(record, indent=2) + "\n")
    return summary


if __name__ == "__main__":
    main()
