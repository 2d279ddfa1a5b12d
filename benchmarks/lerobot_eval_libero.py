"""LeRobot's own evaluation of a cso policy on LIBERO (``lerobot-eval --env.type=libero``) beside ``lerobot-cso
eval``'s on the same fixed init states.

Runs ``lerobot-eval`` on one task for ``--episodes`` episodes, one env (LeRobot's ``LiberoEnv`` then starts
episode ``i`` from the benchmark's init state ``i``, as ``lerobot-cso eval`` does), its cameras at the policy's image
size, and pairs each episode with the same state's episode of evaluation seed 0 in ``--cso_eval`` (the ``eval.json``
of ``lerobot-cso eval`` or of the pipeline's evaluation of that policy). Both sample the policy's skills, so the two
rates agree only within their noise (one binomial standard error each is recorded).

    python benchmarks/lerobot_eval_libero.py \\
        --policy=outputs/libero_object/seed0/il/checkpoints/last/pretrained_model \\
        --cso_eval=outputs/libero_object/seed0/eval/il/eval.json --task=libero_object-0 --episodes=10 \\
        --work=outputs/lerobot_eval_libero --out=benchmarks/results/lerobot_eval_libero.json
"""

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
from harness import provenance

from lerobot_cso.durable import write_atomic
from lerobot_cso.evaluation import standard_error
from lerobot_cso.worlds.libero.env import parse_task


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", type=Path, required=True, help="a saved cso policy trained on LIBERO")
    p.add_argument("--cso_eval", type=Path, required=True, help="the eval.json of lerobot-cso eval on that policy")
    p.add_argument("--task", default="libero_object-0")
    p.add_argument("--episodes", type=int, default=10, help="init states 0 .. N-1")
    p.add_argument("--work", type=Path, default=Path("outputs/lerobot_eval_libero"), help="lerobot-eval's output_dir")
    p.add_argument("--out", type=Path, default=None, help="write the results here as JSON")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 50:
        p.error(f"--episodes must be in [1, 50] (LIBERO's fixed init states), got {args.episodes}")
    if not (args.policy / "config.json").is_file():
        p.error(f"--policy={args.policy} is not a saved policy (no config.json)")
    if not args.cso_eval.is_file():
        p.error(f"--cso_eval={args.cso_eval} does not exist")
    if args.work.exists():
        p.error(f"--work={args.work} exists; lerobot-eval writes a new folder")
    if args.out is not None and not os.access(args.out.parent, os.W_OK):
        p.error(f"--out={args.out}: its folder does not exist or is not writable")
    if "observation.images.image" not in json.loads((args.policy / "config.json").read_text())["input_features"]:
        p.error(f"--policy={args.policy} reads no observation.images.image (agentview): not a LIBERO camera policy")
    try:
        parse_task(args.task)
    except ValueError as e:
        p.error(str(e))
    return args


def cso_successes(path: Path, task: str, episodes: int) -> list[bool]:
    """The successes of evaluation seed 0 on ``task``'s init states 0 .. episodes-1, in state order."""
    by_state = {
        e["init_seed"]: e["success"]
        for e in json.loads(path.read_text())["episodes"]
        if e["task"] == task and e["seed"] == 0
    }
    missing = [s for s in range(episodes) if s not in by_state]
    if missing:
        sys.exit(f"error: {path} has no seed-0 episode of {task} from init state {missing[0]}")
    return [bool(by_state[s]) for s in range(episodes)]


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    suite, index = parse_task(args.task)
    config = json.loads((args.policy / "config.json").read_text())
    size = config["input_features"]["observation.images.image"]["shape"][-1]
    command = [
        str(Path(sys.executable).with_name("lerobot-eval")),
        f"--policy.path={args.policy}",
        "--policy.device=cpu",
        "--env.type=libero",
        f"--env.task={suite}",
        f"--env.task_ids=[{index}]",
        f"--env.observation_height={size}",
        f"--env.observation_width={size}",
        f"--eval.n_episodes={args.episodes}",
        "--eval.batch_size=1",
        f"--output_dir={args.work}",
    ]
    done = subprocess.run(command)
    if done.returncode != 0:
        sys.exit(f"error: lerobot-eval exited with {done.returncode} (its output is above)")
    info = json.loads((args.work / "eval_info.json").read_text())
    lerobot = [bool(s) for s in info["per_task"][0]["metrics"]["successes"]]
    cso = cso_successes(args.cso_eval, args.task, args.episodes)
    rates = {"lerobot_eval": float(np.mean(lerobot)), "lerobot_cso_eval": float(np.mean(cso))}
    summary = {
        "task": args.task,
        "init_states": list(range(args.episodes)),
        "successes": {"lerobot_eval": lerobot, "lerobot_cso_eval": cso},
        "rate": rates,
        "se": {name: standard_error(rate, args.episodes) for name, rate in rates.items()},
        "lerobot_eval_seconds": info["overall"]["eval_s"],
    }
    print(json.dumps(summary, indent=2))
    if args.out is not None:
        record = {
            "command": shlex.join(["python", *sys.argv]),
            "lerobot_eval_command": shlex.join(["lerobot-eval", *command[1:]]),
            **provenance(),
            "policy": str(args.policy),
            "results": summary,
        }
        write_atomic(args.out, (json.dumps(record, indent=2) + "\n").encode())
    return summary


if __name__ == "__main__":
    main()
