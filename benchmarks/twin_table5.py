"""Table 5 of the paper on the PiPER's physics twin (issue 36): IL, R-SFT and CSO on Press Button and Cube in Bowl,
20 trials each, with the operator-equivalent budget of every stage.

Per task, each part in order (docs/real-arm.md, "Table 5 on the twin: benchmarks/twin_table5.py"):

1. ``demos``: ``--demos`` demonstrations, recorded in real time by ``lerobot-record`` with the scripted
   teleoperator (``--teleop.type=piper_scripted --teleop.cycle=false``) against ``piper-emulator --physics
   --scene=<task>``. LeRobot's episode windows are fixed, the scripted demonstrations are not: before each
   episode this driver does what a person does between two episodes, and what ``--operator.type=twin`` does
   before each trial of the policy: it moves the arm to the rest pose (straight in joint space over
   ``--rest-time-s``), has the twin place the objects for the next seed and lets 0.3 s of twin time pass. The
   episode ends 0.5 s after the scene reports success (LeRobot's "exit early", the key a person presses); a
   demonstration still unfinished when its window (``--demo-window-s``) closes is recorded again from the next
   seed (LeRobot's "re-record"). So every demonstration starts at the rest pose with the objects just placed, as
   every trial does. This is ``lerobot-record``'s own ``record()`` (``python benchmarks/twin_table5.py _record``)
   with that between-episodes step wrapped around its ``record_loop``. Demonstration k uses seed
   ``--demo-seed`` + k (+ the re-recorded ones before it).
2. ``il``: ``python -m lerobot_cso.train`` (``lerobot-train --policy.type=cso``, frames served from memory) on the
   demos: the camera benchmark's policy (configs/metaworld_vision.yaml: conv encoder, 4 px random shift) on 64x64
   front and wrist cameras and the 7 joint values; ``--ae-dim`` and ``--image-shift`` change two of its fields.
3. ``eval_il``, ``rsft``, ``eval_rsft``, ``spo``, ``eval_cso``: ``lerobot-cso eval|rsft|spo`` on
   ``--robot.type=piper_twin_sim`` (faster than real time) labelled by ``--operator.type=twin``, with the budgets of
   configs/piper_rsft.yaml / piper_spo.yaml / piper_eval.yaml unless told otherwise (``--spo-clip``,
   ``--spo-state-pool`` and ``--spo-skip-uniform-for`` give SPO the camera benchmark's trust region and state
   pool; ``--spo-trajectory-mean`` weighs every SPO trajectory the same, where Eq. 9 weighs it by its length;
   ``--rsft-demo-fraction`` mixes the task's demonstrations into R-SFT's fine-tune). R-SFT and SPO place their
   scenes from ``--train-seed`` + i, the evaluations from ``--eval-seed`` + i (trial i): disjoint from each other and
   from the demonstrations' seeds (checked).

``--record-on=sim`` records on ``piper_twin_sim`` instead (the same ``lerobot-record`` loop, paced in real time, but
the twin on simulated time: a starved or paused process records the same demonstration), for a machine too busy
for the real-time emulator.

Every finished part is written at once to ``--results`` (default ``outputs/twin_table5.json``) with its wall
time and its episodes (an evaluation's also trial by trial, ``outcomes``: its journal's names, 1 for a success, so a
later run on the same scenes can be paired with it), and per task the paired differences of the evaluations
(``paired``); a rerun skips the finished
parts and resumes an unfinished one from its own output (``lerobot-record --resume``, ``lerobot-train --resume``, the
robot stages' journals). A results file made with other settings is refused, but ``--reuse=<results>
--reuse-work=<work>`` starts each task from a copy of the parts of another run that its differing settings do not change
(e.g. a larger SPO budget from the same IL and R-SFT; the copied records say ``reused_from``); when only R-SFT's
fine-tune settings differ, its collection is copied too and only its fine-tune runs again (the task says
``rsft_collection_reused_from``); when only ``--spo-iterations`` differs for SPO and is larger, SPO's output is copied
and continued, so its first iterations' episodes are not collected again (``spo_continued_from``). An R-SFT that
finds fewer than ``--rsft-successes`` successes in ``--rsft-max-states`` scenes is recorded as failed (no SPO, no CSO
for that task at this budget). The operator-equivalent cost of each part: its episodes, their length on the twin (its
time is the real arm's time), and what a person would spend at the arm: the episodes' seconds, plus per episode the
rest move and ``--arrange-s`` (an assumption: placing the objects by hand; the twin does it instantly). The defaults
and their measured costs: docs/real-arm.md.

    python benchmarks/twin_table5.py                      # the full run (defaults), ~1.5 h on a free 2-core VM
    python benchmarks/twin_table5.py --dry-run            # the commands of the parts still to run
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from harness import mean_ci

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
TASKS = {"press_button": "press the button", "cube_in_bowl": "put the cube in the bowl"}
# The rest pose (joint_1..joint_6 in rad, gripper in m): the grasp point 0.26 m above the table's centre line, the
# wrist camera looking at the workspace; J5 (57 degrees) well inside its +-70 degrees. Every demonstration and every
# trial starts here.
REST_POSE = (0.0, 1.0, -1.0, 0.0, 1.0, 0.0, 0.0)
SETTLE_S = 0.3  # the twin's time between placing the objects and the start (the twin operator's TWIN_SETTLE_S)
SUCCESS_TAIL_S = 0.5  # a demonstration's episode goes on this long after the scene's success
# The camera benchmark's policy (configs/metaworld_vision.yaml, il.policy): what trains on two cores.
POLICY = {
    "device": "cpu",
    "ae_dim": 96,
    "ae_heads": 4,
    "ae_encoder_layers": 1,
    "ae_decoder_layers": 2,
    "state_embed_dim": 64,
    "image_backbone": "conv",
    "image_shift": 4,
    "image_keypoints": 32,
    "image_embed_dim": 64,
    "prior_dim": 128,
    "prior_heads": 4,
    "prior_layers": 3,
    "optimizer_lr": 0.0005,
    "optimizer_min_lr": 0.00005,
}
PARTS = ("demos", "il", "eval_il", "rsft", "eval_rsft", "spo", "eval_cso")
EVALS = {"eval_il": "il", "eval_rsft": "rsft", "eval_cso": "cso"}
# Settings that do not change the results (where things run, how fast); the rest are the results' config.
RUNTIME = ("work", "results", "threads", "tasks", "dry_run", "stop_after", "reuse", "reuse_work")
# Flags named after the POLICY field they set: the results' config holds them inside its "policy" entry.
POLICY_FLAGS = ("ae_dim", "image_shift")
# Flags added after results were first written: the config holds them only when they differ from these defaults
# (which are the stages' own), so older results files stay valid.
OPTIONAL = {
    "spo_clip": None,
    "spo_state_pool": None,
    "spo_skip_uniform_for": 0,
    "rsft_demo_fraction": 0.0,
    "demo_detour": 0.0,
    "demo_regrasp": 0.0,
    "demo_close_s": 0.8,
    "spo_trajectory_mean": False,
}
# The parts each setting changes directly (a setting not named here changes every part, from the demos on); a part
# also changes when the part it starts from (INPUT) does. What --reuse may copy from a results file of other
# settings is every part that no differing setting changes.
CHANGES = {
    **dict.fromkeys(("il_steps", "il_ae_steps", "il_batch", "il_seed", "policy"), ("il",)),
    "episode_s": ("eval_il", "rsft", "eval_rsft", "spo", "eval_cso"),
    **dict.fromkeys(("trials", "eval_seed"), tuple(EVALS)),
    **dict.fromkeys(
        ("rsft_successes", "rsft_strikes", "rsft_cap", "rsft_max_states", "rsft_epochs", "rsft_demo_fraction"),
        ("rsft",),
    ),
    **dict.fromkeys(("rsft_batch", "train_seed"), ("rsft", "spo")),
    **dict.fromkeys(("spo_iterations", "spo_groups", "spo_k", "spo_draw_factor", "spo_epochs"), ("spo",)),
    **dict.fromkeys(("spo_minibatch", "spo_lr", "spo_clip", "spo_state_pool", "spo_skip_uniform_for"), ("spo",)),
    "spo_trajectory_mean": ("spo",),
}
# Settings of R-SFT's fine-tune alone: when they are all that changes R-SFT, --reuse copies its collection (the
# scenes, attempts and successes: R-SFT's journal and buffer) and only the fine-tune runs again.
FINETUNE = ("rsft_epochs", "rsft_batch", "rsft_demo_fraction")
COLLECTION = ("journal", "buffer", "robot_journal", "collection.json")
# The paired differences of the evaluations (their trial i is the same scene): SR(a) - SR(b).
PAIRS = (("cso", "il"), ("rsft", "il"), ("cso", "rsft"))
INPUT = {"il": "demos", "eval_il": "il", "rsft": "il", "eval_rsft": "rsft", "spo": "rsft", "eval_cso": "spo"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    a = p.add_argument
    a("--tasks", default="press_button,cube_in_bowl", help="comma list of twin scenes")
    a("--work", type=Path, default=ROOT / "outputs" / "twin_table5", help="the stages' output folders")
    a("--results", type=Path, default=ROOT / "outputs" / "twin_table5.json")
    a("--threads", type=int, default=2, help="torch threads of the training steps (IL, R-SFT's and SPO's updates)")
    a("--dry-run", action="store_true", help="print the commands of the parts still to run, run nothing")
    a("--stop-after", choices=PARTS, help="end each task after this part")
    # recording
    a("--demos", type=int, default=50, help="demonstrations per task")
    a("--fps", type=int, default=10, help="control frequency of the demos, hence of every stage")
    a(
        "--demo-detour",
        type=float,
        default=0.0,
        help="m: each demo first arrives up to this far beside the object and corrects (piper_scripted detour_m)",
    )
    a(
        "--demo-regrasp",
        type=float,
        default=0.0,
        help="m: half of the demos first close on nothing up to this far beside the object (piper_scripted regrasp_m)",
    )
    a(
        "--demo-close-s",
        type=float,
        default=0.8,
        help="s: how long every close of a demo stays closed before the arm moves on (piper_scripted close_s)",
    )
    a("--image-size", type=int, default=64, help="front and wrist cameras, square")
    a("--cameras", default="front,wrist", help="the twin's views the policy reads")
    a("--demo-window-s", type=str, default="press_button=10,cube_in_bowl=18", help="LeRobot's episode_time_s")
    a(
        "--record-on",
        choices=("emulator", "sim"),
        default="emulator",
        help="piper-emulator --physics (real time) "
        "or piper_twin_sim (lerobot-record's loop paced in real time, the twin on simulated time)",
    )
    a(
        "--rest-pose",
        default=",".join(f"{v:g}" for v in REST_POSE),
        help="joint_1..6 (rad), gripper (m): where every demonstration and every trial starts",
    )
    a("--rest-time-s", type=float, default=3.0, help="the move to the rest pose before each episode (real arm: 3 s)")
    # IL
    a("--il-steps", type=int, default=4000)
    a("--il-ae-steps", type=int, default=1000, help="of --il-steps, the autoencoder's; the rest the prior's")
    a("--il-batch", type=int, default=64)
    a("--il-seed", type=int, default=1000)
    a("--ae-dim", type=int, default=POLICY["ae_dim"], help="the skill autoencoder's width")
    a("--image-shift", type=int, default=POLICY["image_shift"], help="random-shift augmentation of the images, pixels")
    # robot stages
    a("--episode-s", type=str, default="press_button=10,cube_in_bowl=20", help="the policy's time limit per episode")
    a("--rsft-successes", type=int, default=20)
    a("--rsft-strikes", type=int, default=4)
    a("--rsft-cap", type=int, default=2, help="max_successes_per_state (stop_state_at_cap)")
    a("--rsft-max-states", type=int, default=40)
    a("--rsft-epochs", type=int, default=20)
    a("--rsft-batch", type=int, default=64)
    a(
        "--rsft-demo-fraction",
        type=float,
        default=0.0,
        help="R-SFT's demo_fraction: this share of each fine-tune epoch's decisions from the task's demos",
    )
    a("--spo-iterations", type=int, default=4)
    a("--spo-groups", type=int, default=6)
    a("--spo-k", type=int, default=4)
    a("--spo-draw-factor", type=int, default=2)
    a("--spo-epochs", type=int, default=4)
    a("--spo-minibatch", type=int, default=24)
    a("--spo-lr", type=float, default=1e-4)
    a("--spo-clip", default=None, help="low,high: the ratio's clip range (default: the skill objective's)")
    a("--spo-state-pool", type=int, default=None, help="SPO's state_pool: draw from this many scenes, cycling")
    a("--spo-skip-uniform-for", type=int, default=0, help="SPO's skip_uniform_for (with --spo-state-pool)")
    a("--spo-trajectory-mean", action="store_true", help="SPO's trajectory_mean: every trajectory weighs the same")
    a("--trials", type=int, default=20, help="evaluation trials per checkpoint and task (Table 5: 20)")
    a("--demo-seed", type=int, default=0, help="demo k: seed demo_seed + k (re-recorded ones take the next)")
    a("--train-seed", type=int, default=5000, help="R-SFT's and SPO's state i: seed train_seed + i")
    a("--eval-seed", type=int, default=100000, help="trial i: seed eval_seed + i")
    a("--arrange-s", type=float, default=10.0, help="a person's time to place the objects (operator cost only)")
    a(
        "--reuse",
        type=Path,
        default=None,
        help="a results file of other settings: a task not yet in --results starts with a copy of its parts that "
        "no differing setting changes (their folders copied from --reuse-work)",
    )
    a("--reuse-work", type=Path, default=None, help="the --work of the --reuse run")
    args = p.parse_args(argv)
    args.tasks = [t for t in args.tasks.split(",") if t]
    unknown = [t for t in args.tasks if t not in TASKS]
    if unknown:
        p.error(f"unknown task(s) {unknown}; known: {', '.join(TASKS)}")
    args.cameras = [c for c in args.cameras.split(",") if c]
    try:
        args.rest_pose = [float(v) for v in args.rest_pose.split(",")]
    except ValueError:
        p.error(f"--rest-pose: expected 7 numbers, got {args.rest_pose!r}")
    if len(args.rest_pose) != 7:
        p.error(f"--rest-pose: expected 7 numbers (6 joints in rad, the gripper in m), got {len(args.rest_pose)}")
    args.demo_window_s = per_task(p, "--demo-window-s", args.demo_window_s)
    args.episode_s = per_task(p, "--episode-s", args.episode_s)
    if not 0 <= args.il_ae_steps < args.il_steps:
        p.error("--il-ae-steps must be in [0, --il-steps)")
    if args.ae_dim < 1 or args.ae_dim % POLICY["ae_heads"]:
        p.error(f"--ae-dim must be a positive multiple of {POLICY['ae_heads']} (the heads), got {args.ae_dim}")
    if args.image_shift < 0:
        p.error(f"--image-shift must be >= 0, got {args.image_shift}")
    for flag in ("demo_detour", "demo_regrasp"):
        if not 0 <= getattr(args, flag) < float("inf"):
            p.error(f"--{flag.replace('_', '-')} must be a finite number >= 0 (m), got {getattr(args, flag):g}")
    if not 0 < args.demo_close_s < float("inf"):
        p.error(f"--demo-close-s must be a finite number > 0 (s), got {args.demo_close_s:g}")
    if not 0 <= args.rsft_demo_fraction < 1:
        p.error(f"--rsft-demo-fraction must be in [0, 1), got {args.rsft_demo_fraction:g}")
    if args.spo_clip is not None:
        try:
            low, high = (float(v) for v in args.spo_clip.split(","))
        except ValueError:
            p.error(f"--spo-clip: expected low,high, got {args.spo_clip!r}")
        if not 0 < low <= 1 <= high:
            p.error(f"--spo-clip: expected 0 < low <= 1 <= high, got {args.spo_clip!r}")
        args.spo_clip = [low, high]
    if args.spo_state_pool is not None and args.spo_state_pool < 1:
        p.error(f"--spo-state-pool must be >= 1, got {args.spo_state_pool}")
    if args.spo_skip_uniform_for < 0:
        p.error(f"--spo-skip-uniform-for must be >= 0, got {args.spo_skip_uniform_for}")
    if (args.reuse is None) != (args.reuse_work is None):
        p.error("--reuse and --reuse-work go together")
    if args.reuse is not None and not args.reuse.is_file():
        p.error(f"--reuse: no results file at {args.reuse}")
    check_seeds(p, args)
    return args


def per_task(p: argparse.ArgumentParser, flag: str, text: str) -> dict[str, float]:
    """``task=seconds,...`` (or one number for every task)."""
    try:
        if "=" not in text:
            return dict.fromkeys(TASKS, float(text))
        values = {k: float(v) for k, v in (item.split("=") for item in text.split(","))}
    except ValueError:
        p.error(f"{flag}: expected task=seconds,... or one number, got {text!r}")
    missing = [t for t in TASKS if t not in values]
    if missing:
        p.error(f"{flag}: no value for {', '.join(missing)}")
    return values


def seed_ranges(args: argparse.Namespace) -> dict[str, range]:
    """The scene seeds each use may draw (upper bounds): the demos with every re-record allowed, R-SFT's states,
    SPO's groups with every redraw, the trials."""
    spo = args.spo_state_pool or args.spo_iterations * args.spo_groups * args.spo_draw_factor
    return {
        "demos": range(args.demo_seed, args.demo_seed + 2 * args.demos + 1),
        "train": range(args.train_seed, args.train_seed + max(args.rsft_max_states, spo)),
        "eval": range(args.eval_seed, args.eval_seed + args.trials),
    }


def check_seeds(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    ranges = list(seed_ranges(args).items())
    for i, (a, ra) in enumerate(ranges):
        for b, rb in ranges[i + 1 :]:
            if ra.start < rb.stop and rb.start < ra.stop:
                p.error(f"the {a} seeds {ra.start}..{ra.stop - 1} overlap the {b} seeds {rb.start}..{rb.stop - 1}")


def config_of(args: argparse.Namespace) -> dict[str, Any]:
    """The settings the results depend on."""
    cfg = {
        k: v
        for k, v in vars(args).items()
        if k not in RUNTIME and k not in POLICY_FLAGS and not (k in OPTIONAL and v == OPTIONAL[k])
    }
    return json.loads(json.dumps(cfg | {"policy": policy_of(args)}))


def policy_of(args: argparse.Namespace) -> dict[str, Any]:
    """POLICY with the fields its flags set."""
    return POLICY | {field: getattr(args, field) for field in POLICY_FLAGS}


# ---------------------------------------------------------------------------------------------------- results


def load_results(path: Path, config: dict[str, Any], command: str) -> dict[str, Any]:
    if path.is_file():
        results = json.loads(path.read_text())
        if results.get("config") != config:
            raise SystemExit(
                f"error: {path} holds results of other settings (its 'config' differs); move it aside or pass "
                "another --results"
            )
        if results["command"].split("; ")[-1] != command:
            results["command"] += "; " + command
        return results
    return {"config": config, "command": command, "tasks": {}}


def reusable_parts(config: dict[str, Any], other: dict[str, Any], task: str) -> tuple[list[str], bool, bool]:
    """The finished parts of ``task`` in results ``other`` that ``config`` would compute the same: those that no
    differing setting changes (CHANGES), directly or through the part they start from (INPUT); whether R-SFT's
    collection is reusable when R-SFT itself is not (only FINETUNE settings change it); and whether SPO's output
    can be continued (only ``spo_iterations`` differs for it, and grew: the stage continues a finished run)."""
    theirs = other["config"]
    differ = [k for k in config.keys() | theirs.keys() if config.get(k) != theirs.get(k)]
    changed = {part for k in differ for part in CHANGES.get(k, PARTS)}
    done = other["tasks"].get(task, {}).get("parts", {})
    reusable: list[str] = []
    for part in PARTS:  # in order: a part's INPUT comes before it
        if part in changed or part not in done or "failed" in done[part]:
            continue
        if part in INPUT and INPUT[part] not in reusable:
            continue
        reusable.append(part)
    collection = (
        "rsft" not in reusable
        and INPUT["rsft"] in reusable
        and "rsft" in done
        and "failed" not in done["rsft"]
        and all(k in FINETUNE for k in differ if "rsft" in CHANGES.get(k, PARTS))
    )
    grows = (
        "spo" not in reusable
        and INPUT["spo"] in reusable
        and "spo" in done
        and "failed" not in done["spo"]
        and [k for k in differ if "spo" in CHANGES.get(k, PARTS)] == ["spo_iterations"]
        and config["spo_iterations"] > theirs["spo_iterations"]
    )
    return reusable, collection, grows


def reuse(args: argparse.Namespace, config: dict[str, Any], task: str, entry: dict[str, Any], base: Path) -> None:
    """Start ``task`` from copies of the reusable parts of ``--reuse``: their folders from ``--reuse-work`` (copied
    under a temporary name, then renamed, so an interrupted copy is redone), then their records."""
    other = json.loads(args.reuse.read_text())
    parts, collection, grows = reusable_parts(config, other, task)
    names = {"demos": ["demos", "demos_attempts.jsonl"]}
    copies = [(part, name) for part in parts for name in names.get(part, [part])]
    copies += [("rsft", f"rsft/{name}") for name in COLLECTION] if collection else []
    copies += [("spo", "spo")] if grows else []
    for part, name in copies:
        source, target = args.reuse_work / task / name, base / name
        if not source.exists():
            raise SystemExit(f"error: --reuse-work has no {source} for the reused part {task} {part}")
        tmp = target.with_name(target.name + ".copying")
        target.parent.mkdir(parents=True, exist_ok=True)
        for stale in (tmp, target):
            if stale.is_dir():
                shutil.rmtree(stale)
            else:
                stale.unlink(missing_ok=True)
        if source.is_dir():
            shutil.copytree(source, tmp)
        else:
            shutil.copy2(source, tmp)
        os.replace(tmp, target)
    for part in parts:
        entry["parts"][part] = other["tasks"][task]["parts"][part] | {"reused_from": str(args.reuse)}
    if collection:
        il_policy = base / "il" / "checkpoints" / "last" / "pretrained_model"
        for name in ("journal", "robot_journal"):
            rebase_journal(base / "rsft" / name / "spec.json", il_policy)
        entry["rsft_collection_reused_from"] = str(args.reuse)
    if grows:  # the SPO command continues it to --spo-iterations, from the copied R-SFT
        rsft_policy = base / "rsft" / "pretrained_model"
        rebase_journal(base / "spo" / "robot_journal" / "spec.json", rsft_policy)
        rebase_record(base / "spo" / "stage.json", rsft_policy)
        entry["spo_continued_from"] = str(args.reuse)
    extra = (["R-SFT's collection"] if collection else []) + (["SPO to continue"] if grows else [])
    reused = ", ".join(parts + extra) or "nothing"
    print(f"[twin_table5] {task}: reused {reused} from {args.reuse}", flush=True)


def rebase_journal(spec_path: Path, policy: Path) -> None:
    """Point a copied journal at the copy of the checkpoint that made it: its ``policy`` path becomes ``policy``
    once that holds the same weights (the journals refuse another policy by its path)."""
    spec = json.loads(spec_path.read_text())
    made_by = Path(spec["policy"]) / "model.safetensors"
    if not made_by.is_file() or made_by.read_bytes() != (policy / "model.safetensors").read_bytes():
        raise SystemExit(f"error: {spec_path} was made by {made_by.parent}, which is gone or not the reused IL")
    spec["policy"] = str(policy)
    spec_path.write_text(json.dumps(spec, indent=2) + "\n")


def rebase_record(record_path: Path, policy: Path) -> None:
    """Point a copied stage record (``lerobot-cso``'s ``stage.json``) at the copy of its input checkpoint, once that
    holds the weights the record names by their sha256 (the stage refuses another input by its path)."""
    record = json.loads(record_path.read_text())
    digest = hashlib.sha256((policy / "model.safetensors").read_bytes()).hexdigest()[:16]
    if record["spec"]["policy"]["weights_sha256"] != digest:
        raise SystemExit(f"error: {record_path} was made from other weights than {policy}")
    record["spec"]["policy"]["path"] = str(policy.resolve())
    record_path.write_text(json.dumps(record, indent=2) + "\n")


def save_results(path: Path, results: dict[str, Any]) -> None:
    summarize(results)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=2) + "\n")
    os.replace(tmp, path)


def summarize(results: dict[str, Any]) -> None:
    """Per task and over the tasks: SR of IL, R-SFT, CSO, CSO - IL, the operator budget, the wall time."""
    sr: dict[str, dict[str, float]] = {}
    for task, entry in results["tasks"].items():
        parts = entry["parts"]
        entry["sr"] = {m: parts[p]["success_rate"] for p, m in EVALS.items() if p in parts}
        if {"il", "cso"} <= entry["sr"].keys():
            entry["cso_minus_il"] = entry["sr"]["cso"] - entry["sr"]["il"]
        entry["wall_s"] = sum(p["wall_s"] for p in parts.values())
        entry["operator"] = {
            "episodes": {p: parts[p]["operator"]["episodes"] for p in PARTS if p in parts},
            "hours": {p: parts[p]["operator"]["person_s"] / 3600 for p in PARTS if p in parts},
        }
        sr[task] = entry["sr"]
    complete = [t for t in sr if {"il", "rsft", "cso"} <= sr[t].keys()]
    results["mean"] = (
        {m: float(np.mean([sr[t][m] for t in complete])) for m in ("il", "rsft", "cso")} | {"tasks": complete}
        if complete
        else None
    )
    if results["mean"]:
        results["mean"]["cso_minus_il"] = results["mean"]["cso"] - results["mean"]["il"]
    results["wall_s"] = sum(e["wall_s"] for e in results["tasks"].values())


# ---------------------------------------------------------------------------------------------------- commands


def env(work: Path) -> dict[str, str]:
    """Offline, LeRobot's caches (calibration) under ``work``."""
    return os.environ | {
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(work / "lerobot_home"),
        "TOKENIZERS_PARALLELISM": "false",
        "PYTHONUNBUFFERED": "1",
    }


class StageFailed(RuntimeError):
    """A command of a part ended with a non-zero exit code; the message holds its ``error:`` line, if any."""


def run(command: list[str], work: Path, log: Path, threads: int | None = None) -> None:
    """Run ``command`` to its end, its output appended to ``log`` and echoed; a failure raises."""
    print("[twin_table5] " + shlex.join(command), flush=True)
    extra = {"OMP_NUM_THREADS": str(threads)} if threads else {}
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as out:
        out.write(f"\n$ {shlex.join(command)}\n")
        out.flush()
        process = subprocess.Popen(command, env=env(work) | extra, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        assert process.stdout is not None
        error = ""
        try:
            for raw in process.stdout:
                line = raw.decode(errors="replace")
                out.write(line)
                out.flush()
                if line.startswith("error: "):
                    error = line.strip()
        except BaseException:
            process.kill()
            raise
    if process.wait() != 0:
        name = Path(command[1] if command[0] == sys.executable else command[0]).name
        raise StageFailed(
            f"{name} failed with exit code {process.returncode} (see {log}){': ' + error if error else ''}"
        )


def camera_arg(args: argparse.Namespace, extra: str = "") -> str:
    size = args.image_size
    views = ", ".join(
        f"{c}: {{type: piper_twin, view: {c}, width: {size}, height: {size}{extra}}}" for c in args.cameras
    )
    return "{" + views + "}"


def vector(values: tuple[float, ...] | list[float]) -> str:
    return "[" + ",".join(f"{v:g}" for v in values) + "]"


def robot_args(args: argparse.Namespace, task: str, stage: str) -> list[str]:
    """``piper_twin_sim`` (faster than real time) and the twin operator, for a robot stage of ``task``."""
    seed = args.eval_seed if stage.startswith("eval") else args.train_seed
    return [
        "--robot.type=piper_twin_sim",
        f"--robot.channel=twin-table5-{task}-{stage}",  # an in-process bus: the name need only be unique in it
        f"--robot.scene={task}",
        f"--robot.fps={args.fps}",
        "--robot.motion_mode=position",
        "--robot.speed_percent=100",
        f"--robot.initial_pose={vector(args.rest_pose[:6])}",
        f"--robot.cameras={camera_arg(args)}",
        "--operator.type=twin",
        f"--operator.scene_seed={seed}",
        f"--operator.episode_time_s={args.episode_s[task]:g}",
        f"--operator.rest_time_s={args.rest_time_s:g}",
        f"--operator.rest_pose={vector(args.rest_pose)}",
        f"--tasks={TASKS[task]}",
    ]


def stage_command(args: argparse.Namespace, task: str, part: str, paths: dict[str, Path]) -> list[str]:
    cli = [str(BIN / "lerobot-cso")]
    common = robot_args(args, task, part)
    if part in EVALS:
        policy = {"eval_il": paths["il_policy"], "eval_rsft": paths["rsft_policy"], "eval_cso": paths["spo_policy"]}
        return [*cli, "eval", f"--policy.path={policy[part]}", *common, f"--episodes_per_task={args.trials}",
                f"--output_dir={paths[part]}"]  # fmt: skip
    if part == "rsft":
        return [
            *cli, "rsft", f"--policy.path={paths['il_policy']}", *common, f"--output_dir={paths['rsft']}",
            f"--n_strikes={args.rsft_strikes}", f"--max_successes_per_state={args.rsft_cap}",
            "--stop_state_at_cap=true", f"--successes_per_task={args.rsft_successes}", "--states_per_round=1",
            f"--max_states_per_task={args.rsft_max_states}", f"--epochs={args.rsft_epochs}",
            f"--batch_size={args.rsft_batch}", f"--train_threads={args.threads}",
            *([f"--demo_fraction={args.rsft_demo_fraction:g}", f"--demos_root={paths['demos']}",
               f"--demos_repo_id=local/twin_{task}"] if args.rsft_demo_fraction else []),
        ]  # fmt: skip
    assert part == "spo"
    return [
        *cli, "spo", f"--policy.path={paths['rsft_policy']}", *common, f"--output_dir={paths['spo']}",
        f"--iterations={args.spo_iterations}", f"--groups_per_iteration={args.spo_groups}",
        f"--group_size={args.spo_k}", f"--epochs={args.spo_epochs}",
        f"--minibatch_trajectories={args.spo_minibatch}", f"--max_draw_factor={args.spo_draw_factor}",
        f"--lr={args.spo_lr:g}", f"--train_threads={args.threads}",
        *([f"--clip_low={args.spo_clip[0]:g}", f"--clip_high={args.spo_clip[1]:g}"] if args.spo_clip else []),
        *([f"--state_pool={args.spo_state_pool}"] if args.spo_state_pool else []),
        *([f"--skip_uniform_for={args.spo_skip_uniform_for}"] if args.spo_skip_uniform_for else []),
        *(["--trajectory_mean=true"] if args.spo_trajectory_mean else []),
    ]  # fmt: skip


def il_command(args: argparse.Namespace, task: str, paths: dict[str, Path]) -> list[str]:
    """``python -m lerobot_cso.train`` (lerobot-train, frames from memory); ``--resume`` once a checkpoint exists."""
    out = paths["il"]
    common = [
        f"--output_dir={out}",
        f"--dataset.root={paths['demos']}",
        f"--dataset.repo_id=local/twin_{task}",
        "--dataset.video_backend=pyav",
        f"--steps={args.il_steps}",
        "--num_workers=0",
    ]
    last = out / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    if last.is_file():
        return [sys.executable, "-m", "lerobot_cso.train", "--resume=true", f"--config_path={last}", *common]
    policy = [f"--policy.{k}={v}" for k, v in policy_of(args).items()]
    return [
        sys.executable, "-m", "lerobot_cso.train", "--policy.type=cso", *common, f"--batch_size={args.il_batch}",
        f"--save_freq={min(1000, args.il_steps)}", f"--log_freq={min(200, args.il_steps)}", f"--seed={args.il_seed}",
        "--policy.push_to_hub=false", f"--policy.n_autoencoder_steps={args.il_ae_steps}", *policy,
    ]  # fmt: skip


# ---------------------------------------------------------------------------------------------------- parts


def demos_in(root: Path) -> int:
    info = root / "meta" / "info.json"
    return json.loads(info.read_text())["total_episodes"] if info.is_file() else 0


def unreadable_parquet(root: Path) -> str | None:
    """The first parquet file of a dataset that cannot be opened, with why; None when all open."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for path in sorted(root.rglob("*.parquet")):
        try:
            pq.read_metadata(path)
        except (OSError, pa.ArrowException) as exc:
            return f"{path}: {exc}"
    return None


def record_demos(args: argparse.Namespace, task: str, paths: dict[str, Path], log: Path) -> dict[str, Any]:
    """Part 1: the demonstrations, by ``lerobot-record`` (see the module doc); a rerun adds the ones still missing
    (``--resume=true``), and a recording that fails (a starved real-time process) is resumed up to 3 times in a
    row without progress."""
    root, attempts_log = paths["demos"], paths["demos_log"]
    stalled, have = 0, demos_in(root)
    if have and have < args.demos and (broken := unreadable_parquet(root)):
        raise RuntimeError(
            f"{task}: the {have} demonstrations in {root} cannot be resumed ({broken}): a recording that crashed "
            f"leaves LeRobot's files unfinished and their episodes lost; delete {root} and {attempts_log} to record "
            "them again"
        )
    while have < args.demos:
        if stalled == 3:
            raise RuntimeError(
                f"{task}: {have} of {args.demos} demonstrations after 3 tries of lerobot-record without progress "
                f"(see {log}); a real-time recording needs the CPU: rerun on a free machine, or with --record-on=sim"
            )
        hook = {
            "mode": args.record_on,
            "rest_pose": args.rest_pose,
            "rest_time_s": args.rest_time_s,
            "seed": args.demo_seed,
            "max_failures": args.demos,
            "log": str(attempts_log),
        }
        robot = ["--robot.motion_mode=position", "--robot.speed_percent=100"]
        emulator = None
        if args.record_on == "emulator":
            (group, port), (state_group, state_port) = unique_udp(), unique_udp()
            emulator = start_emulator(args, task, group, port, state_group, state_port, log)
            hook |= {"state_group": state_group, "state_port": state_port}
            robot += [
                "--robot.type=piper_follower", "--robot.interface=udp_multicast", f"--robot.channel={group}",
                f"--robot.port={port}", "--robot.feedback_timeout_s=1.0", "--robot.enable_timeout_s=5",
                f"--robot.cameras={camera_arg(args, f', group: {state_group}, port: {state_port}, max_age_s: 1.0')}",
            ]  # fmt: skip
            teleop = [f"--teleop.group={state_group}", f"--teleop.port={state_port}", "--teleop.max_age_s=1.0"]
        else:
            robot += [
                "--robot.type=piper_twin_sim", f"--robot.channel=twin-table5-record-{task}",
                f"--robot.scene={task}", f"--robot.scene_seed={args.demo_seed}", f"--robot.fps={args.fps}",
                f"--robot.initial_pose={vector(args.rest_pose[:6])}", f"--robot.cameras={camera_arg(args)}",
            ]  # fmt: skip
            teleop = []
        command = [
            sys.executable, str(Path(__file__).resolve()), "_record", json.dumps(hook), *robot,
            "--teleop.type=piper_scripted", "--teleop.cycle=false", f"--teleop.seed={args.demo_seed + have}",
            f"--teleop.detour_m={args.demo_detour:g}",
            f"--teleop.regrasp_m={args.demo_regrasp:g}",
            f"--teleop.close_s={args.demo_close_s:g}",
            *teleop, f"--dataset.repo_id=local/twin_{task}", f"--dataset.root={root}",
            f"--dataset.single_task={TASKS[task]}", f"--dataset.num_episodes={args.demos - have}",
            f"--dataset.episode_time_s={args.demo_window_s[task]:g}", "--dataset.reset_time_s=0",
            f"--dataset.fps={args.fps}", "--dataset.video=false", "--dataset.push_to_hub=false",
            "--dataset.no_stamp=true", "--display_data=false", "--play_sounds=false",
            *(["--resume=true"] if have else []),
        ]  # fmt: skip
        if not have and root.exists():
            shutil.rmtree(root)  # an empty dataset left by a failed first try: start it over
        try:
            run(command, paths["home"], log)
        except StageFailed as exc:
            print(f"[twin_table5] {exc}; {demos_in(root)} demonstrations on disk", flush=True)
        finally:
            if emulator is not None:
                emulator.terminate()
                try:
                    emulator.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    emulator.kill()
                    emulator.wait()
        stalled = 0 if demos_in(root) > have else stalled + 1
        have = demos_in(root)
    attempts = [json.loads(line) for line in attempts_log.read_text().splitlines()] if attempts_log.is_file() else []
    failed = [a for a in attempts if not a["success"]]
    lengths = episode_lengths(root)
    return {
        "episodes": len(lengths),
        "frames": int(sum(lengths)),
        "seconds": summary(np.array(lengths) / args.fps),
        "failed_attempts": len(failed),
        "seeds": [a["seed"] for a in attempts if a["success"]],
        "operator": operator_cost(
            args, [n / args.fps for n in lengths], extra_s=sum(a["twin_s"] for a in failed), extra_n=len(failed)
        ),
    }


def unique_udp() -> tuple[str, int]:
    """A random IPv4 multicast group and UDP port (Linux delivers by port: both unique)."""
    rng = random.SystemRandom()
    return f"239.{rng.randint(1, 254)}.{rng.randint(1, 254)}.{rng.randint(1, 254)}", rng.randint(20_000, 60_000)


def start_emulator(
    args: argparse.Namespace, task: str, group: str, port: int, state_group: str, state_port: int, log: Path
) -> subprocess.Popen:
    command = [
        str(BIN / "piper-emulator"), "--interface=udp_multicast", f"--channel={group}", f"--port={port}",
        "--physics", f"--scene={task}", f"--scene-seed={args.demo_seed}", f"--state-group={state_group}",
        f"--state-port={state_port}", f"--initial-pose={','.join(f'{v:g}' for v in args.rest_pose[:6])}",
        "--duration=14400",  # an emulator left behind by a killed driver ends by itself
    ]  # fmt: skip
    print("[twin_table5] " + shlex.join(command), flush=True)
    out = log.open("a")
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=out, text=True)
    assert process.stdout is not None
    line = process.stdout.readline()
    if "ready" not in line:
        process.kill()
        raise RuntimeError(f"piper-emulator did not start: {line!r} (see {log})")
    threading.Thread(target=lambda: [out.write(x) for x in process.stdout], daemon=True).start()  # type: ignore[union-attr]
    return process


def episode_lengths(root: Path) -> list[int]:
    """Frames of each episode of the LeRobot dataset at ``root``."""
    import pyarrow.parquet as pq

    lengths: list[int] = []
    for path in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        lengths += [int(n) for n in pq.read_table(path, columns=["length"]).column("length").to_pylist()]
    return lengths


def journal(out: Path) -> dict[str, tuple[bool, int]]:
    """(success, ticks) of every finished robot episode a stage journaled, by its journal name (an evaluation's trial
    names its scene)."""
    episodes = {}
    for path in sorted((out / "robot_journal" / "episodes").glob("*/*.npz")):
        with np.load(path) as data:
            episodes[path.stem] = (bool(data["success"]), int(data["length"]))
    return episodes


def paired_difference(a: dict[str, bool | int], b: dict[str, bool | int]) -> dict[str, Any]:
    """SR(a) - SR(b) over the same trials (outcomes by trial name): the mean, its 95 % CI (normal, from the
    per-trial differences), and the trials a won and lost."""
    d = [float(a[t]) - float(b[t]) for t in sorted(a)]
    won, lost = sum(x > 0 for x in d), sum(x < 0 for x in d)
    return mean_ci(d, student=False) | {"won": won, "lost": lost, "trials": len(d)}


def paired_differences(base: Path) -> dict[str, dict[str, Any]]:
    """:func:`paired_difference` per pair of PAIRS whose evaluations ran the same trials."""
    outcomes = {method: {t: ok for t, (ok, _) in journal(base / part).items()} for part, method in EVALS.items()}
    return {
        f"{a}_minus_{b}": paired_difference(outcomes[a], outcomes[b])
        for a, b in PAIRS
        if len(outcomes[a]) >= 2 and sorted(outcomes[a]) == sorted(outcomes[b])
    }


def summary(values: np.ndarray) -> dict[str, float] | None:
    if not len(values):
        return None
    return {"mean": float(np.mean(values)), "min": float(np.min(values)), "max": float(np.max(values))}


def operator_cost(
    args: argparse.Namespace, seconds: list[float], extra_s: float = 0.0, extra_n: int = 0
) -> dict[str, Any]:
    """What the episodes would cost a person at the real arm: each episode's seconds (the twin's time is the arm's),
    the rest move and the arranging of its scene; ``extra_*``: discarded tries (failed demonstrations)."""
    n = len(seconds) + extra_n
    episode_s = float(sum(seconds)) + extra_s
    return {
        "episodes": len(seconds),
        "discarded": extra_n,
        "episode_s": episode_s,
        "person_s": episode_s + n * (args.rest_time_s + args.arrange_s),
    }


def robot_part(args: argparse.Namespace, task: str, part: str, paths: dict[str, Path], log: Path) -> dict[str, Any]:
    out = paths[part]
    run(stage_command(args, task, part, paths), paths["home"], log)
    trials = journal(out)
    episodes = list(trials.values())
    seconds = [ticks / args.fps for _, ticks in episodes]
    entry: dict[str, Any] = {
        "episodes": len(episodes),
        "successes": sum(s for s, _ in episodes),
        "operator": operator_cost(args, seconds),
    }
    if part in EVALS:
        rate = json.loads((out / "eval.json").read_text())["success_rate"][TASKS[task]]["mean"]
        entry["success_rate"] = float(rate)
        entry["outcomes"] = {name: int(ok) for name, (ok, _) in trials.items()}
    elif part == "rsft":
        entry["collection"] = json.loads((out / "collection.json").read_text())[TASKS[task]]
    else:
        history = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
        entry["iterations"] = [
            {k: h.get(k) for k in ("episodes", "success_rate", "rejection_rate", "clip_fraction", "entropy")}
            for h in history
        ]
    return entry


def run_task(args: argparse.Namespace, task: str, results: dict[str, Any], path: Path) -> None:
    base = args.work / task
    paths = {
        "home": base,
        "demos": base / "demos",
        "demos_log": base / "demos_attempts.jsonl",
        "il": base / "il",
        "il_policy": base / "il" / "checkpoints" / "last" / "pretrained_model",
        "rsft": base / "rsft",
        "rsft_policy": base / "rsft" / "pretrained_model",
        "spo": base / "spo",
        "spo_policy": base / "spo" / "pretrained_model",
        **{p: base / p for p in EVALS},
    }
    log = base / "log.txt"
    base.mkdir(parents=True, exist_ok=True)
    entry = results["tasks"].setdefault(task, {"parts": {}})
    if args.reuse is not None and not entry["parts"] and not args.dry_run:
        reuse(args, results["config"], task, entry, base)
        save_results(path, results)
    for part in PARTS:
        if "failed" in entry["parts"].get("rsft", {}):
            print(
                f"[twin_table5] {task}: R-SFT failed ({entry['parts']['rsft']['failed']}); no SPO, no CSO", flush=True
            )
            break
        if part in entry["parts"] or args.dry_run:
            if part in entry["parts"]:
                print(f"[twin_table5] {task} {part}: done, skipped", flush=True)
            elif part == "il":
                print(shlex.join(il_command(args, task, paths)))
            elif part != "demos":
                print(shlex.join(stage_command(args, task, part, paths)))
            if part == args.stop_after:
                break
            continue
        started = time.perf_counter()
        if part == "demos":
            record = record_demos(args, task, paths, log)
        elif part == "il":
            if not (paths["il"] / "checkpoints" / "last").exists():
                shutil.rmtree(paths["il"], ignore_errors=True)  # killed before its first checkpoint: start over
            run(il_command(args, task, paths), base, log, threads=args.threads)
            step = json.loads(
                (paths["il"] / "checkpoints" / "last" / "training_state" / "training_step.json").read_text()
            )
            if step["step"] < args.il_steps:
                raise RuntimeError(f"{task}: lerobot-train stopped at step {step['step']} of {args.il_steps}")
            record = {"steps": step["step"], "operator": operator_cost(args, [])}
        else:
            try:
                record = robot_part(args, task, part, paths, log)
            except StageFailed as exc:
                if part != "rsft" or "successes after" not in str(exc):
                    raise
                # R-SFT found too few successes in --rsft-max-states scenes: no CSO for this task at this budget
                episodes = list(journal(paths["rsft"]).values())
                record = {
                    "failed": str(exc).split(": error: ", 1)[-1],
                    "episodes": len(episodes),
                    "successes": sum(ok for ok, _ in episodes),
                    "operator": operator_cost(args, [ticks / args.fps for _, ticks in episodes]),
                }
        record["wall_s"] = time.perf_counter() - started
        entry["parts"][part] = record
        save_results(path, results)
        rate = f", SR {100 * record['success_rate']:.0f} %" if "success_rate" in record else ""
        print(f"[twin_table5] {task} {part}: {record['wall_s']:.0f} s{rate}", flush=True)
        if part == args.stop_after:
            break
    if not args.dry_run and (pairs := paired_differences(base)):
        entry["paired"] = pairs
        save_results(path, results)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    args.work, args.results = args.work.resolve(), args.results.resolve()
    command = shlex.join(["python", "benchmarks/twin_table5.py", *(sys.argv[1:] if argv is None else argv)])
    results = load_results(args.results, config_of(args), command)
    for task in args.tasks:
        run_task(args, task, results, args.results)
    if results.get("mean"):
        m = results["mean"]
        print(
            f"[twin_table5] mean over {', '.join(m['tasks'])}: IL {100 * m['il']:.1f} %, "
            f"R-SFT {100 * m['rsft']:.1f} %, CSO {100 * m['cso']:.1f} %, "
            f"CSO - IL {100 * m['cso_minus_il']:+.1f} points",
            flush=True,
        )


# ---------------------------------------------------------------------------------------------------- recording


class PlantReceiver:
    """``piper_twin.state_channel.StateReceiver`` on the twin in this process (``--record-on=sim``): the scripted
    teleoperator and the between-episodes step read the plant of the ``piper_twin_sim`` robot directly."""

    robot: Any = None  # the piper_twin_sim that lerobot-record made

    def __init__(self, group: str = "", port: int = 0) -> None:
        pass

    def latest(self) -> Any:
        return self.robot.plant.snapshot()

    def wait(self, timeout_s: float) -> Any:
        return self.latest()

    def place(self, seed: int, timeout_s: float = 0.0) -> Any:
        self.robot.plant.place(seed)
        return self.latest()

    def close(self) -> None:
        pass


def record_main(hook: dict[str, Any], argv: list[str]) -> None:
    """``lerobot-record argv`` with the between-episodes step of a person (module doc) before each episode."""
    import piper_twin.state_channel as state_channel
    from lerobot.scripts import lerobot_record

    sim = hook["mode"] == "sim"
    if sim:  # the teleoperator (it imports StateReceiver when it connects) and this step watch the robot's plant
        make_robot = lerobot_record.make_robot_from_config

        def make_twin(config: Any) -> Any:
            PlantReceiver.robot = make_robot(config)
            return PlantReceiver.robot

        lerobot_record.make_robot_from_config = make_twin
        state_channel.StateReceiver = PlantReceiver  # type: ignore[misc]
        receiver: Any = PlantReceiver()
    else:
        receiver = state_channel.StateReceiver(hook["state_group"], hook["state_port"])
        if receiver.wait(10.0) is None:
            raise SystemExit("error: no twin state in 10 s")
    original = lerobot_record.record_loop
    rest = np.asarray(hook["rest_pose"], dtype=float)
    log = Path(hook["log"])
    attempts = [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []
    next_seed = max((a["seed"] + 1 for a in attempts), default=hook["seed"])
    failures = 0

    def to_rest(robot: Any, teleop: Any, fps: int) -> None:
        """The operator's move: straight in joint space from the measured pose, ``rest_time_s``, one step a tick.
        Meanwhile the twin's states are read and dropped, as the teleoperator does while it runs: a multicast socket
        not read for ~0.7 s (saving an episode) fills, and its newest state would then be seconds old."""
        drain = getattr(getattr(teleop, "_receiver", None), "latest", lambda: None)
        keys = list(robot.action_features)
        obs = robot.get_observation()
        start = np.array([obs[k] for k in keys], dtype=float)
        steps = max(1, round(hook["rest_time_s"] * fps))
        for step in range(1, steps + 1):
            t0 = time.perf_counter()
            drain(), receiver.latest()
            robot.send_action(dict(zip(keys, start + (rest - start) * step / steps, strict=True)))
            if not sim:
                time.sleep(max(0.0, 1 / fps - (time.perf_counter() - t0)))
        drain()

    def record_loop(**kwargs: Any) -> None:
        nonlocal failures, next_seed
        dataset, events, robot, teleop = kwargs.get("dataset"), kwargs["events"], kwargs["robot"], kwargs["teleop"]
        if dataset is None:  # LeRobot's reset window (reset_time_s=0): the reset is done before each episode
            return original(**kwargs)
        to_rest(robot, teleop, kwargs["fps"])
        seed, next_seed = next_seed, next_seed + 1
        placed = receiver.place(seed, timeout_s=5.0)
        if sim:
            robot.pass_time(SETTLE_S)
        else:
            deadline = time.monotonic() + 5.0
            while receiver.latest().time_s < placed.time_s + SETTLE_S and time.monotonic() < deadline:
                time.sleep(0.005)
        succeeded: list[float] = []
        last = [placed.time_s]
        demonstrate = teleop.get_action

        def get_action() -> dict[str, float]:  # the person watching: -> once the task is done (and a tail)
            s = receiver.latest()
            last[0] = s.time_s
            if s.placement >= placed.placement and s.seed == seed:
                if s.success and not succeeded:
                    succeeded.append(s.time_s)
                if succeeded and s.time_s >= succeeded[0] + SUCCESS_TAIL_S:
                    events["exit_early"] = True
            return demonstrate()

        teleop.get_action = get_action
        try:
            original(**kwargs)
        finally:
            del teleop.get_action
        events["exit_early"] = False
        success = bool(succeeded)
        with log.open("a") as f:
            f.write(json.dumps({"seed": seed, "success": success, "twin_s": last[0] - placed.time_s}) + "\n")
        print(f"[twin_table5] demonstration of seed {seed}: {'success' if success else 'failed, recorded again'}")
        if not success:
            failures += 1
            events["rerecord_episode"] = True
            if failures > hook["max_failures"]:
                events["stop_recording"] = True

    lerobot_record.record_loop = record_loop
    sys.argv = ["lerobot-record", *argv]
    try:
        lerobot_record.main()
    finally:
        receiver.close()


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "_record":
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))
        record_main(json.loads(sys.argv[2]), sys.argv[3:])
    else:
        main()
