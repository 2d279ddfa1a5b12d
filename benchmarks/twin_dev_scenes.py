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

``failures`` sorts an evaluation's failed trials by what its gripper did (from the journal: the commanded opening
closing, the measured opening 1 s later, under 5 mm being a close on nothing; where the grasp point was, by the
twin's forward kinematics, when the gripper next opened after holding something, against the scene's bowl) and files
the counts under the evaluation's ``failure_modes``. ``sort`` prints the same counts for any cube evaluation, e.g.
the held-out ones of ``twin_table5.py`` (``--scene-seed=100000``), and files nothing.

    python benchmarks/twin_dev_scenes.py add --name=il_n4 --eval=outputs/s33/eval_dev_il_nas4 \\
        --checkpoint="session 30's IL with --policy.n_action_steps=4" --command="the eval_command with ..."
    python benchmarks/twin_dev_scenes.py agreement --names=il,rsft,cso_6,cso_12,cso_trajectory_mean,rsft_60
    python benchmarks/twin_dev_scenes.py failures --name=il_regrasp --eval=outputs/s33/eval_dev_il_regrasp
    python benchmarks/twin_dev_scenes.py sort --eval=outputs/twin_regrasp/cube_in_bowl/eval_il_100 --scene-seed=100000
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
SCENE_SEED = 300000  # the development scenes' first seed: trial i ran scene SCENE_SEED + i


def add(results: dict[str, Any], args: argparse.Namespace) -> str:
    """File one evaluation's outcomes under ``--name`` (and, unless greedy, its paired differences); the report."""
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
    """Scenes solved by k of the named evaluations against independent coins, and the greedy splits; the report."""
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


CLOSED_M, EMPTY_M, OPEN_M, SETTLE_STEPS = 0.01, 0.005, 0.03, 10  # commanded closed / measured empty / reopened


def failure_mode(actions: np.ndarray, states: np.ndarray, bowl_xy: np.ndarray, grasp_point: Any) -> str:
    """What a failed trial's gripper did: never closed, closed only on nothing, or held something and then opened
    (where, against the bowl) or not."""
    commanded, measured = actions[:, 6], states[:, 6]
    closes = [t for t in range(1, len(commanded)) if commanded[t] < CLOSED_M <= commanded[t - 1]]
    settled = [t for t in closes if t + SETTLE_STEPS < len(measured)]
    held = [t for t in settled if measured[t + SETTLE_STEPS] >= EMPTY_M]
    if not closes:
        return "never closed"
    if not held:
        return "only closes on nothing"
    reopened = [t for t in range(held[0], len(commanded)) if commanded[t] > OPEN_M]
    if not reopened:
        return "held the cube to the end"
    point = grasp_point(states[reopened[0], :6])
    if np.linalg.norm(point[:2] - bowl_xy) < 0.10:
        return "held the cube, opened within 10 cm of the bowl"
    return f"held the cube, opened away from the bowl {'below' if point[2] < 0.06 else 'above'} 6 cm"


def failure_modes(eval_dir: Path, scene_seed: int) -> dict[str, int]:
    """The failed trials of an evaluation (its journal) sorted by ``failure_mode``; trial i ran scene
    ``scene_seed + i``."""
    from piper_twin.ik import ArmIK
    from piper_twin.plant import TwinPlant

    plant = TwinPlant("cube_in_bowl", 0)
    ik = ArmIK(plant.model)
    modes: dict[str, int] = {}
    for path in sorted(eval_dir.glob("robot_journal/episodes/*/*.npz")):
        with np.load(path) as episode:
            if bool(episode["success"]):
                continue
            actions, states = episode["actions"], episode["states"]
        plant.reset(scene_seed + int(path.stem.split("_")[0]))
        bowl = plant.data.mocap_pos[plant.model.body("bowl").mocapid[0]][:2].copy()
        mode = failure_mode(actions, states, bowl, lambda q: ik.grasp_pose(q)[0])
        modes[mode] = modes.get(mode, 0) + 1
    return dict(sorted(modes.items()))


def failures(results: dict[str, Any], args: argparse.Namespace) -> str:
    """File the failure modes of an evaluation already added (its journal at ``--eval``); the report."""
    entry = results["checkpoints"][args.name]
    modes = failure_modes(args.eval, SCENE_SEED)
    if sum(modes.values()) != entry["trials"] - entry["successes"]:
        raise ValueError(
            f"{args.eval} does not hold the {entry['trials'] - entry['successes']} failures of {args.name}"
        )
    entry["failure_modes"] = modes
    return f"{args.name}: " + ", ".join(f"{k} {v}" for k, v in modes.items())


def sort(results: dict[str, Any], args: argparse.Namespace) -> str:
    """Any evaluation's failure modes (e.g. on the held-out scenes, ``--scene-seed=100000``), printed, not filed."""
    if not any(args.eval.glob("robot_journal/episodes/*/*.npz")):
        raise ValueError(f"{args.eval} holds no journal of finished trials")
    modes = failure_modes(args.eval, args.scene_seed)
    return f"{args.eval}: {sum(modes.values())} failed: " + ", ".join(f"{k} {v}" for k, v in modes.items())


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
    f = sub.add_parser("failures", help="sort an evaluation's failed trials by what the gripper did")
    f.add_argument("--name", required=True, help="an evaluation already added")
    f.add_argument("--eval", type=Path, required=True, help="its lerobot-cso eval --output_dir")
    o = sub.add_parser("sort", help="print any evaluation's failure modes (files nothing)")
    o.add_argument("--eval", type=Path, required=True, help="a lerobot-cso eval --output_dir on cube_in_bowl")
    o.add_argument("--scene-seed", type=int, required=True, help="its --operator.scene_seed (held-out: 100000)")
    args = ap.parse_args()
    try:
        results = json.loads(args.results.read_text())
        commands = {"add": add, "agreement": agreement, "failures": failures, "sort": sort}
        report = commands[args.command_name](results, args)
        if args.command_name != "sort":
            write_atomic(args.results, (json.dumps(results, indent=1, ensure_ascii=False) + "\n").encode())
    except (OSError, KeyError, ValueError) as e:
        print(f"twin_dev_scenes: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
