"""SPO budgets from one finished SPO run, compared on training-range states (never the evaluation range).

SPO's learning rate is constant and every iteration's draws depend only on the run's seed and the iteration's
index, so a finished M-iteration run continued to M' iterations is the M'-iteration run. Each variant here
is such a continuation of a copy of the shorter one (``--spo_dir``, made with ``--config``'s SPO section, is
the first), and every resulting policy is rolled out from the states that ``rsft_study.py`` uses: the last
``--states`` of the SPO training range per task, ``--k`` times each at evaluation's sampling. Prints the
success rate per task and mean (± one binomial standard error) and the groups' SR of the added iterations.

    python benchmarks/spo_study.py --spo_dir=outputs/pipeline/metaworld_demo/spo --variants=i10,i15,i20
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path

import draccus
import numpy as np
import torch
from rsft_study import success_rates

from lerobot_cso.cso.spo import run_spo
from lerobot_cso.envs.tasks import resolve_tasks
from lerobot_cso.pipeline import Pipeline, PipelineConfig, policy_config


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spo_dir", type=Path, required=True, help="a finished SPO run of the pipeline config")
    parser.add_argument("--config", type=Path, default=Path("configs/metaworld_demo.yaml"))
    parser.add_argument("--seed", type=int, default=0, help="the training seed the SPO run was made with")
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/spo_study"))
    parser.add_argument("--variants", default="i10,i15,i20", help="iterations, as i<M>, in increasing order")
    parser.add_argument("--states", type=int, default=100)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--num_envs", type=int, default=48)
    args = parser.parse_args()
    names = args.variants.split(",")
    iterations = [int(n.removeprefix("i")) for n in names]
    if iterations != sorted(iterations):
        parser.error("--variants must be in increasing order of iterations")
    torch.set_num_threads(1)
    with open(args.config) as f:
        cfg = draccus.load(PipelineConfig, f)
    pipeline = Pipeline(dataclasses.replace(cfg, output_dir=args.spo_dir.parent, seed=args.seed))
    done = json.loads((args.spo_dir / "state" / "progress.json").read_text())["iteration"]
    if done != iterations[0]:
        parser.error(f"{args.spo_dir} ran {done} iterations; the first variant must be i{done}")
    tasks = resolve_tasks(pipeline.cfg.tasks)
    results_file = args.output_dir / "study.json"
    rows = json.loads(results_file.read_text()) if results_file.is_file() else {}
    previous = args.spo_dir
    for name, m in zip(names, iterations, strict=True):
        out = previous if m == iterations[0] else args.output_dir / name
        if m != iterations[0] and not out.exists():
            shutil.copytree(previous, out)
        spo_cfg = pipeline.spo_config(policy_config(pipeline.out / "rsft" / "pretrained_model"))
        history = run_spo(dataclasses.replace(spo_cfg, iterations=m, output_dir=out))
        if name not in rows:
            rows[name] = {
                "spo_dir": str(out),
                "groups_sr": [h["success_rate"] for h in history],
                "successes": success_rates(out / "pretrained_model", tasks, args.states, args.k, args.num_envs),
            }
            args.output_dir.mkdir(parents=True, exist_ok=True)
            results_file.write_text(json.dumps(rows, indent=2))
        previous = out
    n = args.states * args.k
    print(f"\nSuccess rate (%) over {args.states} training-range states × {args.k} per task (± 1 s.e.)")
    print("| iterations | " + " | ".join(tasks) + " | mean | groups' SR, last 5 iterations |")
    print("|---|" + "---:|" * (len(tasks) + 1) + "---|")
    for name in names:
        row = rows[name]
        p = np.array([sum(row["successes"][t]) / n for t in tasks])
        se = np.sqrt((p * (1 - p) / n).sum()) / len(tasks)
        last = ", ".join(f"{x:.2f}" for x in row["groups_sr"][-5:])
        cells = " | ".join(f"{100 * x:.1f}" for x in p)
        print(f"| {name.removeprefix('i')} | {cells} | {100 * p.mean():.1f} ± {100 * se:.1f} | {last} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
