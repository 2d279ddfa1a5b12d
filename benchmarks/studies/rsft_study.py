"""R-SFT settings from one IL checkpoint, compared on training-range states (never the evaluation range).

Runs R-SFT once per variant (the R-SFT section of ``--config``, the demo's by default, with the variant's
settings replaced) from ``--il_path``, then rolls out every resulting policy, and the IL policy itself, from
the same ``--states`` initial states per task taken from the far end of the SPO training range (those SPO's
pool and R-SFT's collection never reach), ``--k`` times each at evaluation's sampling (T 1, top-5). Prints
one table: the success rate per task and mean (± one binomial standard error), the states the successes were
kept from and the successes per kept state. Finished variants are skipped on a rerun; ``--json`` saves the table.
A variant that changes only the fine-tune (``COLLECTION_FROM``) fine-tunes a copy of another variant's
collection; one that mixes in demonstrations takes those of the IL checkpoint's pipeline (``<out>/demos``).

An IL checkpoint alone comes from the pipeline stopped after its IL stage (``./run.sh demo --stop_after=il``).

    python benchmarks/studies/rsft_study.py \\
        --il_path=outputs/pipeline/metaworld_demo/il/checkpoints/last/pretrained_model \\
        --output_dir=outputs/rsft_study --variants=keep_all,cap2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import draccus
import numpy as np
import torch

from lerobot_cso import seeds
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso.rsft import run_rsft
from lerobot_cso.pipeline import Pipeline, PipelineConfig, policy_config
from lerobot_cso.rollout.engine import RolloutEngine
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.tasks import resolve_tasks, task_description
from lerobot_cso.worlds.metaworld.world import policy_pool

KEEP_ALL = {"max_successes_per_state": None}  # the paper's rule
VARIANTS: dict[str, dict[str, Any]] = {
    "keep_all": KEEP_ALL,
    "cap1": {"max_successes_per_state": 1},
    "cap2": {"max_successes_per_state": 2},
    "t1_top5": KEEP_ALL | {"sampling": Sampling(temperature=1.0, top_k=5)},
    "e3": KEEP_ALL | {"epochs": 3},
    "cap2_demos50": {"max_successes_per_state": 2, "demo_fraction": 0.5},
    "cap2_lr3e4": {"max_successes_per_state": 2, "lr": 3e-4, "min_lr": 3e-5},
    "cap2_stop": {"max_successes_per_state": 2, "stop_state_at_cap": True},
    "cap2_adv": {"max_successes_per_state": 2, "advantage_weighted": True},
    "cap2_n200": {"max_successes_per_state": 2, "successes_per_task": 200},
    "cap2_n200_adv": {"max_successes_per_state": 2, "successes_per_task": 200, "advantage_weighted": True},
}
# Variants that differ from another only in the fine-tune start from a copy of its collection (same spec).
COLLECTION_FROM = {
    "cap2_demos50": "cap2",
    "cap2_lr3e4": "cap2",
    "cap2_adv": "cap2",
    "cap2_n200_adv": "cap2_n200",
}


def timed_rsft(
    pipeline: Pipeline, il_path: Path, out: Path, settings: dict[str, Any], source: Path | None
) -> float | None:
    """R-SFT of one variant (skipped when its checkpoint exists: None); seconds taken. With ``source`` (a
    variant with the same collection spec), its journal and buffer are copied first: only the fine-tune runs."""
    if (out / "pretrained_model" / "config.json").is_file():
        return None
    variant = Pipeline(dataclasses.replace(pipeline.cfg, rsft=dataclasses.replace(pipeline.cfg.rsft, **settings)))
    cfg = dataclasses.replace(variant.rsft_config(policy_config(il_path)), output_dir=out)
    if source is not None and not (out / "buffer").exists():
        if not (source / "buffer" / "meta" / "info.json").is_file():
            raise SystemExit(f"{out.name} fine-tunes {source.name}'s collection: run {source.name} first")
        for part in ("journal", "buffer"):
            shutil.copytree(source / part, out / part)
    start = time.perf_counter()
    run_rsft(cfg)
    return time.perf_counter() - start


def success_rates(policy_path: Path, tasks: list[str], n_states: int, k: int, num_envs: int) -> dict[str, list[int]]:
    """Successes per initial state (0 … k) of each task, from the last ``n_states`` SPO training states."""
    policy, pre, post = load_policy(policy_path)
    first = len(seeds.TRAIN) // 2 - n_states
    states = [(t, s) for t in tasks for s in seeds.training_seeds("spo", first, n_states)]
    pool = policy_pool(policy.config.input_features, num_envs, max_steps=200, frames="decisions")  # camera or state
    with RolloutEngine(policy, pre, post, pool, task_description) as engine:
        result = engine.rollout(states, k=k, sampling=Sampling(), seed=11, progress=str(policy_path.parent.name))
    return {t: [sum(e.success for e in g) for g in result.groups() if g[0].task == t] for t in tasks}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--il_path", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/metaworld_demo.yaml"))
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/rsft_study"))
    parser.add_argument("--variants", default="keep_all,cap2")
    parser.add_argument("--states", type=int, default=100)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--num_envs", type=int, default=48)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    names = args.variants.split(",")
    if unknown := [n for n in names if n not in VARIANTS]:
        parser.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    torch.set_num_threads(1)
    with open(args.config) as f:
        cfg = draccus.load(PipelineConfig, f)
    # The IL checkpoint's own pipeline output (<out>/il/checkpoints/last/pretrained_model): its demos are the
    # ones a demo-mixing variant mixes in.
    pipeline = Pipeline(dataclasses.replace(cfg, output_dir=args.il_path.parents[3]))
    tasks = resolve_tasks(pipeline.cfg.tasks)
    rows = {}
    results_file = args.output_dir / "study.json"
    if results_file.is_file():
        rows = json.loads(results_file.read_text())
    for name in ["il", *names]:
        if name in rows:
            continue
        path, row = args.il_path, {"settings": {}}
        if name != "il":
            out = args.output_dir / name
            settings = VARIANTS[name]
            row = {"settings": {k: str(v) for k, v in settings.items()}}
            source = COLLECTION_FROM.get(name)
            if source:
                row["collection_copied_from"] = source
            source_dir = args.output_dir / source if source else None
            row["rsft_seconds"] = timed_rsft(pipeline, args.il_path, out, settings, source_dir)
            row["collection"] = json.loads((out / "collection.json").read_text())
            files = {t: list((out / "journal" / "episodes" / t).glob("*.npz")) for t in tasks}
            kept = {t: len(files[t]) for t in tasks}
            states = {t: len({p.stem.split("_")[0] for p in files[t]}) for t in tasks}
            row["kept_states"] = states
            row["successes_per_kept_state"] = {t: kept[t] / max(states[t], 1) for t in tasks}
            path = out / "pretrained_model"
        row["successes"] = success_rates(path, tasks, args.states, args.k, args.num_envs)
        rows[name] = row
        args.output_dir.mkdir(parents=True, exist_ok=True)
        results_file.write_text(json.dumps(rows, indent=2))
    n = args.states * args.k
    print(f"\nSuccess rate (%) over {args.states} training-range states × {args.k} per task (± 1 s.e.)")
    print("| variant | " + " | ".join(tasks) + " | mean | kept states | successes per kept state |")
    print("|---|" + "---:|" * (len(tasks) + 3))
    for name, row in rows.items():
        p = np.array([sum(row["successes"][t]) / n for t in tasks])
        se = np.sqrt((p * (1 - p) / n).sum()) / len(tasks)
        cells = [f"{100 * x:.1f}" for x in p]
        kept = "/".join(str(row.get("kept_states", {}).get(t, "–")) for t in tasks)
        per = "/".join(f"{row['successes_per_kept_state'][t]:.1f}" for t in tasks) if "kept_states" in row else "–"
        print(f"| {name} | " + " | ".join(cells) + f" | {100 * p.mean():.1f} ± {100 * se:.1f} | {kept} | {per} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
