"""What the skill autoencoder alone costs on LIBERO: demonstrations replayed open-loop, as recorded and as each
checkpoint's autoencoder reconstructs them.

A policy acts only through its autoencoder's decoder: if the decoded skills cannot redo the demonstrations, no prior
can. Each of the first ``--episodes_per_task`` demonstrations of every task in ``--demos`` is replayed from the
placement it was recorded from (its ``libero.init_seed``; LIBERO's hard reset makes the replay of the recorded actions
exact), once as recorded and once per ``--policy`` with every executed prefix (``n_action_steps``) replaced by the
autoencoder's reconstruction of the ``chunk_size`` actions that start there (``harness.Reconstruction``). Success is
LIBERO's, checked after every action; the mean absolute reconstruction error per action dimension (of the range
[-1, 1]) is reported beside it. No camera is rendered: the replay needs none.

    python benchmarks/libero_skill_replay.py --demos=outputs/libero_object/seed0/demos --episodes_per_task=5 \\
        --policy=outputs/libero_object/seed0/il/checkpoints/last/pretrained_model --out=outputs/skill_replay.json
"""

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np
from harness import Reconstruction, provenance
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_cso.durable import write_atomic
from lerobot_cso.worlds.libero.env import CSOLiberoEnv


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--demos", type=Path, required=True, help="a LIBERO demos dataset of `lerobot-cso demos`")
    p.add_argument("--repo_id", default="local/libero_object")
    p.add_argument("--policy", action="append", default=[], help="a checkpoint whose autoencoder replays (repeatable)")
    p.add_argument("--episodes_per_task", type=int, default=5, help="the first N demonstrations of each task")
    p.add_argument("--out", type=Path, default=None, help="write the results here as JSON")
    args = p.parse_args(argv)
    if args.episodes_per_task < 1:
        p.error(f"--episodes_per_task must be >= 1, got {args.episodes_per_task}")
    if not (args.demos / "meta" / "info.json").is_file():
        p.error(f"--demos={args.demos} is not a LeRobotDataset (no meta/info.json)")
    if args.out is not None and not os.access(args.out.parent, os.W_OK):
        p.error(f"--out={args.out}: its folder does not exist or is not writable")
    missing = [path for path in args.policy if not (Path(path) / "config.json").is_file()]
    if missing:
        p.error(f"--policy={missing[0]} is not a saved policy (no config.json)")
    return args


def replay(env: CSOLiberoEnv, task: str, seed: int, actions: np.ndarray) -> bool:
    """``actions`` from placement ``seed`` of ``task``; whether LIBERO counted a success on the way."""
    env.reset(seed=seed, options={"task": task})
    for action in actions:
        _, _, success, _, _ = env.step(action)
        if success:
            return True
    return False


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    frames = LeRobotDataset(args.repo_id, root=args.demos).hf_dataset.with_format("numpy")
    index = np.asarray(frames["episode_index"])
    actions, tasks, seeds = np.asarray(frames["action"]), np.asarray(frames["libero.task"]), frames["libero.init_seed"]
    first = {}  # the first N episodes of each task, in episode order
    for episode in np.unique(index):
        row = int(np.flatnonzero(index == episode)[0])
        first.setdefault(str(tasks[row]), [])
        if len(first[str(tasks[row])]) < args.episodes_per_task:
            first[str(tasks[row])].append((int(episode), int(seeds[row])))
    filters = {"recorded": None} | {path: Reconstruction(path) for path in args.policy}
    results = {name: {"success": {}, "abs_error": []} for name in filters}
    env = CSOLiberoEnv(next(iter(first)))
    try:
        for task, episodes in first.items():
            for episode, seed in episodes:
                recorded = actions[index == episode].astype(np.float64)
                for name, reconstruct in filters.items():
                    sent = recorded if reconstruct is None else reconstruct(recorded)
                    results[name]["success"].setdefault(task, []).append(replay(env, task, seed, sent))
                    results[name]["abs_error"].append(np.abs(sent - recorded).mean(0))
                verdicts = ", ".join("ok" if r["success"][task][-1] else "FAIL" for r in results.values())
                print(f"{task} demo {episode} (placement {seed}): {verdicts}", flush=True)
    finally:
        env.close()
    summary = {
        name: {
            "success_rate": float(np.mean([s for per_task in r["success"].values() for s in per_task])),
            "per_task": {task: float(np.mean(s)) for task, s in r["success"].items()},
            "episodes": sum(len(s) for s in r["success"].values()),
            "mean_abs_error_per_dim": np.mean(r["abs_error"], axis=0).round(4).tolist(),
        }
        for name, r in results.items()
    }
    for name, s in summary.items():
        print(f"{s['success_rate']:.2f} ({s['episodes']} demos)  error per dim {s['mean_abs_error_per_dim']}  {name}")
    if args.out is not None:
        record = {"command": shlex.join(["python", *sys.argv]), **provenance(), "results": summary}
        write_atomic(args.out, (json.dumps(record, indent=2) + "\n").encode())
    return summary


if __name__ == "__main__":
    main()
