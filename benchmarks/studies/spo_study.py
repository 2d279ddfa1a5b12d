"""SPO settings from one R-SFT checkpoint, compared on training-range states (never the evaluation range).

Every variant runs ``--config``'s SPO section from the R-SFT checkpoint of a finished pipeline
(``--pipeline_dir``, made with ``--config`` and ``--seed``), with one setting changed:

* ``i<M>``: M iterations. SPO's learning rate is constant and every iteration's draws depend only on the run's
  seed and the iteration's index, so a finished run continued to more iterations is the longer run: each
  ``i<M>`` after the first continues a copy of the one before it.
* ``lr<x>``: the learning rate x; ``g<B>``: B groups per iteration; ``k<K>``: K samples per group; ``t<T>``: the
  rollouts' sampling temperature T (also the one the ratios are computed at); ``p<P>``: a state pool of P
  training states per task; ``e<E>``: E epochs over each iteration's rollouts; ``rk<K>``: the ratios taken under
  the top-K-renormalised distribution (``ratio_top_k``; the rollouts sample top-k). Each runs as many iterations as
  the first ``i<M>`` (the baseline), from the R-SFT checkpoint.

Every resulting policy is rolled out from the states that ``rsft_study.py`` uses: the last ``--states`` of the
SPO training range per task, ``--k`` times each at evaluation's sampling. Prints the success rate per task and
mean (± one binomial standard error), the rollouts each variant's SPO ran, and its groups' SR, clip fraction
and approximate KL. Finished variants are kept in ``<output_dir>/study.json`` and not rerun.

    python benchmarks/studies/spo_study.py --pipeline_dir=outputs/pipeline/metaworld_demo \
        --variants=i10,lr5e-5,lr2e-4,g8,g24,k4,k16,t0.7,t1.3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import draccus
import numpy as np
import torch
from rsft_study import success_rates

from lerobot_cso.cso.spo import SPOConfig, run_spo
from lerobot_cso.pipeline import Pipeline, PipelineConfig, policy_config
from lerobot_cso.worlds.metaworld.tasks import resolve_tasks

SETTINGS = {
    "i": ("iterations", int),
    "lr": ("lr", float),
    "g": ("groups_per_iteration", int),
    "k": ("group_size", int),
    "t": ("temperature", float),
    "p": ("state_pool", int),
    "e": ("epochs", int),
    "rk": ("ratio_top_k", int),
}


def parse_variant(name: str) -> tuple[str, Any]:
    """``lr2e-4`` → ``("lr", 2e-4)``; raises ValueError for an unknown form."""
    for prefix in sorted(SETTINGS, key=len, reverse=True):
        if name.startswith(prefix):
            field, kind = SETTINGS[prefix]
            return field, kind(name.removeprefix(prefix))
    raise ValueError(
        f"unknown variant '{name}': i<iterations>, lr<lr>, g<groups>, k<group size>, t<temperature>, "
        "p<state pool>, e<epochs> or rk<ratio top-k>"
    )


def with_setting(cfg: SPOConfig, field: str, value: Any, output_dir: Path) -> SPOConfig:
    """``cfg`` writing to ``output_dir`` with one setting changed (the temperature is the sampling's)."""
    if field == "temperature":
        return dataclasses.replace(
            cfg, output_dir=output_dir, sampling=dataclasses.replace(cfg.sampling, temperature=value)
        )
    return dataclasses.replace(cfg, output_dir=output_dir, **{field: value})


def mean_of(history: list[dict[str, Any]], key: str) -> float | None:
    """The mean of ``key`` over the iterations that report it."""
    values = [h[key] for h in history if h.get(key) is not None]
    return float(np.mean(values)) if values else None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pipeline_dir", type=Path, required=True, help="a finished pipeline of --config")
    parser.add_argument("--config", type=Path, default=Path("configs/metaworld_demo.yaml"))
    parser.add_argument("--seed", type=int, default=0, help="the training seed the pipeline was made with")
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/spo_study"))
    parser.add_argument(
        "--variants", default="i10,i15,i20", help="i<M> (increasing), lr<x>, g<B>, k<K>, t<T>, p<P>, e<E>; i first"
    )
    parser.add_argument("--states", type=int, default=100)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--num_envs", type=int, default=48)
    args = parser.parse_args()
    names = args.variants.split(",")
    try:
        parsed = [parse_variant(n) for n in names]
    except ValueError as exc:
        parser.error(str(exc))
    iterations = [value for field, value in parsed if field == "iterations"]
    if parsed[0][0] != "iterations" or iterations != sorted(iterations):
        parser.error("--variants must start with an i<M>, and its i<M> must be in increasing order")
    torch.set_num_threads(1)
    with open(args.config) as f:
        cfg = draccus.load(PipelineConfig, f)
    pipeline = Pipeline(dataclasses.replace(cfg, output_dir=args.pipeline_dir, seed=args.seed))
    rsft = pipeline.out / "rsft" / "pretrained_model"
    if not (rsft / "config.json").is_file():
        parser.error(f"{args.pipeline_dir} has no finished R-SFT checkpoint ({rsft})")
    base = dataclasses.replace(pipeline.spo_config(policy_config(rsft)), iterations=iterations[0])
    tasks = resolve_tasks(pipeline.cfg.tasks)
    results_file = args.output_dir / "study.json"
    rows = json.loads(results_file.read_text()) if results_file.is_file() else {}
    previous: Path | None = None
    for name, (field, value) in zip(names, parsed, strict=True):
        out = args.output_dir / name
        if field == "iterations" and previous is not None and not out.exists():
            shutil.copytree(previous, out)
        history = run_spo(with_setting(base, field, value, out))
        if field == "iterations":
            previous = out
        if name not in rows:
            rows[name] = {
                "spo_dir": str(out),
                "settings": {field: value},
                "groups_sr": [h["success_rate"] for h in history],
                "episodes": sum(h["episodes"] for h in history),
                "clip_fraction": mean_of(history, "clip_fraction"),
                "approx_kl": mean_of(history, "approx_kl"),
                "entropy": [h.get("entropy") for h in history],
                "ratio_mean": mean_of(history, "ratio_mean"),
                "rejection_rate": mean_of(history, "rejection_rate"),
                "successes": success_rates(out / "pretrained_model", tasks, args.states, args.k, args.num_envs),
            }
            args.output_dir.mkdir(parents=True, exist_ok=True)
            results_file.write_text(json.dumps(rows, indent=2))
    n = args.states * args.k
    print(f"\nSuccess rate (%) over {args.states} training-range states × {args.k} per task (± 1 s.e.)")
    header = " | ".join(tasks)
    print(
        f"| variant | {header} | mean | SPO episodes | clip fraction | approx. KL | mean ratio | prior entropy, "
        "first → last iteration | groups' SR, last 3 iterations |"
    )
    print("|---|" + "---:|" * (len(tasks) + 5) + "---|---|")
    for name in names:
        row = rows[name]
        p = np.array([sum(row["successes"][t]) / n for t in tasks])
        se = np.sqrt((p * (1 - p) / n).sum()) / len(tasks)
        last = ", ".join(f"{x:.2f}" for x in row["groups_sr"][-3:])
        cells = " | ".join(f"{100 * x:.1f}" for x in p)
        clip, kl = row["clip_fraction"], row["approx_kl"]
        entropy = [e for e in row.get("entropy", []) if e is not None]
        spread = f"{entropy[0]:.2f} → {entropy[-1]:.2f}" if entropy else "-"
        ratio = f"{row['ratio_mean']:.3f}" if row.get("ratio_mean") is not None else "-"
        print(
            f"| {name} | {cells} | {100 * p.mean():.1f} ± {100 * se:.1f} | {row['episodes']} | {clip:.3f} | "
            f"{kl:.4f} | {ratio} | {spread} | {last} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
