"""LIBERO's scripted expert: its success per task on training placements (the goal: ≥ 90 % on every task).

Runs ``lerobot-cso demos`` with every episode kept (``keep_failed``), so that each task's rate is over exactly
``--episodes_per_task`` placements (the first of the demo seeds, as the demos stage draws them), and no camera (the
expert reads the simulator; rendering changes nothing it does), then writes per task: episodes, successes, rate ±
one binomial standard error, and the steps a success took. Tasks run one after the other, each into its own dataset
under ``--work`` (resumed from there), and the results file is rewritten after each task, so an interrupted run keeps
every finished task; the rows of tasks this run does not reach stay as an earlier run wrote them.

    python benchmarks/libero_expert.py --tasks=libero_object --episodes_per_task=50 \
        --work=outputs/libero_expert --results=outputs/libero_expert.json
"""

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from harness import provenance
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_cso.demos import DemosConfig, generate_demos, metadata_keys
from lerobot_cso.durable import write_atomic
from lerobot_cso.evaluation import standard_error

REPO_ID = "local/libero_expert"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="libero_object")
    parser.add_argument("--episodes_per_task", type=int, default=50)
    parser.add_argument("--num_envs", type=int, default=2)
    parser.add_argument("--work", type=Path, default=Path("outputs/libero_expert"))
    parser.add_argument("--results", type=Path, default=Path("outputs/libero_expert.json"))
    args = parser.parse_args()
    every = DemosConfig(tasks=args.tasks, output_dir=args.work).validate()
    command = "python benchmarks/libero_expert.py " + " ".join(sys.argv[1:])
    earlier = json.loads(args.results.read_text()) if args.results.is_file() else {"tasks": {}}
    if earlier.get("command") and earlier["command"].split("; ")[-1] != command:
        command = earlier["command"] + "; " + command  # the runs that wrote the rows, in order
    record = {"benchmark": "libero_expert", "command": command, "tasks": dict(earlier["tasks"])}
    for task in every:
        cfg = DemosConfig(
            tasks=task,
            episodes_per_task=args.episodes_per_task,
            keep_failed=True,
            num_envs=args.num_envs,
            output_dir=args.work / task,
            repo_id=REPO_ID,
        )
        start = time.time()
        generate_demos(cfg)
        record["tasks"][task] = task_row(cfg) | {"seconds": round(time.time() - start)}
        record |= provenance() | {"settings": cfg.spec()}
        write_atomic(args.results, (json.dumps(record, indent=1) + "\n").encode())
        row = record["tasks"][task]
        print(f"{task:20s} {row['successes']:3d}/{row['episodes']:3d}  {row['rate']:.0%} ± {row['se']:.0%}", flush=True)


def task_row(cfg: DemosConfig) -> dict[str, Any]:
    """The expert's outcomes on the task of ``cfg``'s dataset."""
    keys = metadata_keys(cfg.expert())
    frames = LeRobotDataset(REPO_ID, root=cfg.output_dir).hf_dataset.select_columns(["episode_index", *keys])
    frames = frames.to_pandas()
    frames[list(keys)] = frames[list(keys)].map(lambda value: np.asarray(value).reshape(-1)[0])
    runs = (
        frames.groupby("episode_index")
        .agg(seed=(keys[1], "first"), ok=(keys[2], "first"), steps=(keys[0], "size"))
        .sort_values("seed")
    )
    rate = float(runs.ok.mean())
    return {
        "episodes": len(runs),
        "successes": int(runs.ok.sum()),
        "rate": rate,
        "se": standard_error(rate, len(runs)),
        "failed_states": [int(seed) for seed in runs.seed[~runs.ok]],
        "success_steps_mean": float(runs.steps[runs.ok].mean()) if runs.ok.any() else None,
        "success_steps_max": int(runs.steps[runs.ok].max()) if runs.ok.any() else None,
    }


if __name__ == "__main__":
    main()
