"""The cube's development-scene evaluations (issue 36), kept in ``benchmarks/results/twin_cube_spo_dev.json``.

Every evaluation here ran ``lerobot-cso eval`` on the twin (the file's ``eval_command``) on the 100 development
scenes 300000-300099, never the held-out range. Two subcommands:

``add`` reads one evaluation's output folder (its robot journal, as ``twin_table5.py`` reads it), stores
the outcome of every trial under ``--name`` and the paired difference against every evaluation already there
(mean, 95 % CI of the paired mean, trials won and lost); ``--section=greedy`` files it with the greedy-decoding
evaluations instead, which are compared with the sampled ones by ``agreement``.

``agreement`` asks how much of a trial the scene decides: per scene, how many of the named sampled evaluations
solved it, against as many independent coins at their rates (20 000 simulated draws); and for each greedy
evaluation (a deterministic policy on a deterministic twin: its outcome is a function of the scene) the sampled
evaluations' rate on the scenes it won and on those it lost.

    python benchmarks/twin_dev_scenes.py add --name=il_n4 --eval=outputs/s33/eval_dev_il_nas4 \\
        --checkpoint="session 30's IL with --policy.n_action_steps=4" --command="the eval_command with ..."
    python benchmarks/twin_dev_scenes.py agreement --names=il,rsft,cso_6,cso_12,cso_trajectory_mean,rsft_60
"""

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from twin_table5 import journal, paired_difference

from lerobot_cso.durable import write_atomic

RESULTS = Path(__file__).parent / "results" / "twin_cube_spo_dev.json"
TRIALS = 100


def add(results: dict[str, Any], args: argparse.Namespace) -> str:
    outcomes = {trial: int(ok) for trial, (ok, _) in journal(args.eval).items()}
    if len(outcomes) != TRIALS:
        raise ValueError(f"{args.eval} holds {len(outcomes)} finished trials, not {TRIALS}")
    entry = {
        "checkpoint": args.checkpoint,
        "trials": TRIALS,
        "successes": sum(outcomes.values()),
        "success_rate": sum(outcomes.values()) / TRIALS,
        "outcomes": outcomes,
    }
    if args.command:
        entry["command"] = args.command
    lines = [f"{args.name}: {entry['successes']} / {TRIALS}"]
    if args.section == "greedy":
        results["greedy"]["checkpoints"][args.name] = entry
        return lines[0]
    for other, theirs in results["checkpoints"].items():
        if other != args.name:
            d = results["paired"][f"{args.name}_minus_{other}"] = paired_difference(outcomes, theirs["outcomes"])
            low, high = (100 * x for x in d["ci95"])
            lines.append(f"  {args.name} - {other}: {100 * d['mean']:+.1f} [{low:+.1f}, {high:+.1f}]")
    results["checkpoints"][args.name] = entry
    return "\n".join(lines)


def agreement(results: dict[str, Any], args: argparse.Namespace) -> str:
    names = args.names.split(",")
    scenes = sorted(results["checkpoints"][names[0]]["outcomes"])
    wins = np.array([[results["checkpoints"][n]["outcomes"][s] for n in names] for s in scenes])
    solved_by = np.bincount(wins.sum(1), minlength=len(names) + 1)
    draws = np.random.default_rng(0).random((20_000, len(scenes), len(names))) < wins.mean(0)
    expected = np.bincount(draws.sum(2).ravel(), minlength=len(names) + 1) / 20_000
    results["scene_agreement"] = {
        "what": f"per development scene, how many of the {len(names)} sampled evaluations named solved it, against "
        f"{len(names)} independent coins at their rates (mean of 20 000 simulated draws, numpy seed 0)",
        "checkpoints": names,
        "scenes_solved_by_k": solved_by.tolist(),
        "expected_if_independent": np.round(expected, 2).tolist(),
    }
    coins = np.round(expected, 1).tolist()
    lines = [f"scenes solved by k = 0..{len(names)}: {solved_by.tolist()}; independent coins: {coins}"]
    for name, entry in results["greedy"]["checkpoints"].items():
        greedy = np.array([entry["outcomes"][s] for s in scenes])
        split = {
            n: [float(wins[greedy == 1, i].mean()), float(wins[greedy == 0, i].mean())] for i, n in enumerate(names)
        }
        entry["sampled_rate_where_greedy_won_lost"] = split
        lines.append(
            f"greedy {name} ({greedy.sum()} / {len(scenes)}): sampled rate where it won / lost: "
            + ", ".join(f"{n} {w:.2f} / {lo:.2f}" for n, (w, lo) in split.items())
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=RESULTS)
    sub = ap.add_subparsers(dest="command_name", required=True)
    a = sub.add_parser("add", help="store one evaluation's outcomes and its paired differences")
    a.add_argument("--name", required=True)
    a.add_argument("--eval", type=Path, required=True, help="the lerobot-cso eval --output_dir")
    a.add_argument("--checkpoint", required=True, help="which checkpoint and settings, in words")
    a.add_argument("--command", default="", help="how it was run, when not the file's eval_command")
    a.add_argument("--section", choices=("checkpoints", "greedy"), default="checkpoints")
    g = sub.add_parser("agreement", help="how much of a trial the scene decides")
    g.add_argument("--names", required=True, help="comma-separated sampled evaluations")
    args = ap.parse_args()
    try:
        results = json.loads(args.results.read_text())
        report = add(results, args) if args.command_name == "add" else agreement(results, args)
    except (OSError, KeyError, ValueError) as e:
        print(f"twin_dev_scenes: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    write_atomic(args.results, (json.dumps(results, indent=1, ensure_ascii=False) + "\n").encode())
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
