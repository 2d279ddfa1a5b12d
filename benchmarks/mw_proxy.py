"""MW-proxy: IL, R-SFT only, SPO only, CSO, CSO without the encoder freeze and the token / trajectory / RIPT
objectives on MetaWorld, per seed.

Per training seed ``s`` (IL seed, R-SFT seed and SPO seed all derive from it): the pipeline of
``--config`` (demos → IL → eval → R-SFT → eval → SPO → eval) gives ``il``, ``rsft`` and ``cso``; SPO from the IL
checkpoint gives ``spo_only``; SPO with ``--objective=token|trajectory|ript`` from the same R-SFT checkpoint,
with the same SPO settings (iterations, groups, K, draws, lr) and each objective's own default clip range
(a clip range in the config is the skill objective's), gives ``token``, ``trajectory``, ``ript``; the skill
objective from the R-SFT checkpoint with ``encoder_freeze=false`` (SPO updates the observation encoders too)
gives ``cso_no_freeze``, the paper's ablation of the freeze (R-SFT's freeze only marks the checkpoint: its
weights are the same, so the ablation needs no second R-SFT run). Every
evaluation is the config's ``eval`` section (held-out evaluation seed range). Env steps and episodes of every
SPO run are counted and printed.

Each finished (method, seed) is written at once to ``--results`` (default ``outputs/mw_proxy.json``; the
committed results are ``benchmarks/results/mw_proxy.json``, which a run extends only when ``--results`` names it),
and skipped when the command is run again, from this clone or another; unfinished stages resume from ``--work``
(their own records). All the rollout stages of a run share their env pools
(:func:`~lerobot_cso.rollout.pool.kept_pools`), as in the pipeline.
SPO's health per iteration (clip fraction, approximate KL, rejection rate) is kept for every SPO run.

    python benchmarks/mw_proxy.py             # configs/mw_proxy.yaml, seeds 0-2
    python benchmarks/mw_proxy.py --seeds=0   # one seed
    python benchmarks/mw_proxy.py --methods=il,rsft,cso   # the pipelines of every seed first

``--stop_after=<stage>`` ends each seed's pipeline after that stage and records the evaluations done by then (e.g.
``--stop_after=eval_il`` for IL alone); the same command without it continues.

Further arguments are pipeline settings over ``--config``, as ``lerobot-cso pipeline`` takes them; they are part
of the config the results file is tied to:

    python benchmarks/mw_proxy.py --results=outputs/mw_proxy_n200.json --rsft.successes_per_task=200

The camera benchmark (issue 33) is this driver on the camera config (the camera demo is it at a smaller budget):

    python benchmarks/mw_proxy.py --config=configs/metaworld_vision.yaml --work=outputs/mw_vision \
        --results=benchmarks/results/mw_vision.json --methods=il,rsft,cso,spo_only,cso_no_freeze
"""

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import draccus
import matplotlib
import numpy as np
from harness import mean_ci, provenance

from lerobot_cso.cso.spo import run_spo
from lerobot_cso.durable import write_atomic
from lerobot_cso.errors import UsageError, parse_errors_as_usage_errors
from lerobot_cso.evaluation import evaluate
from lerobot_cso.pipeline import Pipeline, PipelineConfig, policy_config
from lerobot_cso.rollout.pool import kept_pools
from lerobot_cso.stage import settings_spec, without_added_settings

METHODS = ("il", "rsft", "spo_only", "cso", "cso_no_freeze", "token", "trajectory", "ript")
# method -> (the checkpoint SPO starts from, objective, encoder_freeze)
SPO_RUNS = {
    "spo_only": ("il", "skill", True),
    "cso_no_freeze": ("rsft", "skill", False),
    "token": ("rsft", "token", True),
    "trajectory": ("rsft", "trajectory", True),
    "ript": ("rsft", "ript", True),
}
HEALTH = ("clip_fraction", "approx_kl", "rejection_rate")  # SPO's health, kept per iteration
DIFFERENCES = (("cso", "il"), ("rsft", "il"), ("cso", "spo_only"), ("cso", "cso_no_freeze"))  # paired, with a CI


def pipeline_config(path: Path, overrides: list[str]) -> PipelineConfig:
    """The pipeline config of the file at ``path`` with ``overrides`` (``--section.setting=value``) applied; a
    setting the config does not have raises ``UsageError``."""
    with parse_errors_as_usage_errors():
        return draccus.parse(PipelineConfig, args=[f"--config_path={path}", *overrides])


def config_spec(cfg: PipelineConfig) -> dict[str, Any]:
    """The settings the results depend on: the config without its output paths (some default to a timestamp),
    its seed (the driver's) and ``stop_after``, and without the settings added later at their behave-as-before
    values (so earlier results stay valid)."""

    def strip(value: Any) -> Any:
        return {k: strip(v) for k, v in value.items() if k != "output_dir"} if isinstance(value, dict) else value

    # the demo settings left to the world (null) as the world resolves them, as the demos stage records them
    demos = dataclasses.replace(cfg.demos, world=cfg.world, tasks=cfg.tasks).resolved()
    cfg = dataclasses.replace(cfg, demos=dataclasses.replace(demos, world=cfg.demos.world, tasks=cfg.demos.tasks))
    return without_added_settings(strip(settings_spec(cfg, exclude=("seed", "stop_after"))))


def load(path: Path, command: str, config: dict[str, Any]) -> dict[str, Any]:
    """The results so far, with ``command`` appended to the commands that made them (``"; "``-separated);
    a file made with another config is refused, so runs of two configs never mix. Its config is read as
    :func:`config_spec` writes one now (settings added or moved since, at their behave-as-before values, left out)."""
    if path.is_file():
        results = json.loads(path.read_text())
        if without_added_settings(results.get("config")) != config:
            raise SystemExit(
                f"error: {path} holds results of another config (its 'config' differs from --config's); "
                "move it aside or pass another --results"
            )
        if results["command"].split("; ")[-1] != command:
            results["command"] += "; " + command
        for method in METHODS:  # files made before a method existed
            results["methods"].setdefault(method, {"per_seed": {}})
        return results
    return {
        "config": config,
        "methods": {m: {"per_seed": {}} for m in METHODS},
        "env_steps": {},
        "episodes": {},
        "seconds": {},
        "spo_history": {},
        "command": command,
    }


def save(path: Path, results: dict[str, Any]) -> None:
    for method in METHODS:
        entry = results["methods"][method]
        values = list(entry["per_seed"].values())
        entry["mean"] = float(np.mean(values)) if values else None
        entry["std"] = float(np.std(values, ddof=1)) if len(values) > 1 else None
    for a, b in DIFFERENCES:
        results[f"{a}_minus_{b}"] = paired_difference(results, a, b)
        results[f"{a}_minus_{b}_per_seed_episodes"] = paired_episodes(results, a, b)
    il, cso = (results["methods"][m]["mean"] for m in ("il", "cso"))
    # the share of IL's gap to 100 % that CSO closes (the paper: 82 % on ML45)
    results["gap_closed"] = None if il is None or cso is None or il == 1 else (cso - il) / (1 - il)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(results, indent=2).encode())


def paired_difference(results: dict[str, Any], a: str, b: str) -> dict[str, Any] | None:
    """Mean over seeds of SR(a) − SR(b) with a Student-t 95 % CI (seeds paired), or None before 2 seeds."""
    common = sorted(set(results["methods"][a]["per_seed"]) & set(results["methods"][b]["per_seed"]))
    diffs = [results["methods"][a]["per_seed"][s] - results["methods"][b]["per_seed"][s] for s in common]
    if not diffs:
        return None
    return mean_ci(diffs, student=True) | {"seeds": common}


def paired_episodes(results: dict[str, Any], a: str, b: str) -> dict[str, Any] | None:
    """Per seed, the mean of success(a) − success(b) over the evaluation episodes both ran from the same initial
    state, with a normal 95 % CI: the evaluation's noise alone (not the training seed's), or None without them."""
    out = {}
    for seed, mine in results["methods"][a].get("outcomes_per_seed", {}).items():
        theirs = results["methods"][b].get("outcomes_per_seed", {}).get(seed)
        if theirs:
            common = sorted(mine.keys() & theirs.keys())
            out[seed] = mean_ci([mine[k] - theirs[k] for k in common], student=False) | {"episodes": len(common)}
    return out or None


def spo_summary(history: list[dict[str, Any]]) -> tuple[float, int, int]:
    return (
        float(np.mean([h["clip_fraction"] for h in history])),
        sum(h.get("env_steps", 0) for h in history),
        sum(h.get("episodes", 0) for h in history),
    )


def record_rates(results: dict[str, Any], method: str, key: str, rows: dict[str, Any], eval_dir: Path) -> None:
    """A method's evaluation on seed ``key``: the overall rate, each task's (``per_task_per_seed``) and each episode's
    success by task, evaluation seed and initial state (``outcomes_per_seed``, from ``eval_dir``'s eval.json)."""
    entry = results["methods"][method]
    entry["per_seed"][key] = rows["overall"]["mean"]
    entry.setdefault("per_task_per_seed", {})[key] = {t: row["mean"] for t, row in rows.items() if t != "overall"}
    episodes = json.loads((eval_dir / "eval.json").read_text())["episodes"]
    entry.setdefault("outcomes_per_seed", {})[key] = {
        f"{e['task']}/{e['seed']}/{e['init_seed']}": int(e["success"]) for e in episodes
    }


def run_seed(
    cfg: PipelineConfig, seed: int, work: Path, results: dict[str, Any], path: Path, methods: tuple[str, ...]
) -> None:
    key = str(seed)
    if all(key in results["methods"][m]["per_seed"] for m in methods):
        print(f"[mw_proxy] seed {seed}: complete, skipped")
        return
    started = time.perf_counter()
    pipeline = Pipeline(dataclasses.replace(cfg, output_dir=work / f"seed{seed}", seed=seed))
    cfg = pipeline.cfg
    out = pipeline.run()
    for method, rows in out["success_rate"].items():  # every evaluation done, even in a stopped run
        record_rates(results, method, key, rows, cfg.output_dir / "eval" / method)
    results.setdefault("stage_seconds", {})[key] = out["stage_seconds"]
    if (collection := cfg.output_dir / "rsft" / "collection.json").is_file():  # R-SFT's report (the paper's Table 7)
        results.setdefault("rsft_collection", {})[key] = json.loads(collection.read_text())
    if "stopped_after" in out:
        save(path, results)
        print(f"[mw_proxy] seed {seed}: stopped after {out['stopped_after']}; the same command without it continues")
        return
    checkpoints = {name: Path(p) for name, p in out["checkpoints"].items()}
    history = [json.loads(line) for line in (cfg.output_dir / "spo" / "log.jsonl").read_text().splitlines()]
    record_spo(results, "cso", key, history)
    results["seconds"].setdefault(key, {})["pipeline"] = time.perf_counter() - started  # keeps earlier runs
    save(path, results)
    for method, (source, objective, freeze) in SPO_RUNS.items():
        if method not in methods or key in results["methods"][method]["per_seed"]:
            continue
        t0 = time.perf_counter()
        spo_cfg = dataclasses.replace(
            pipeline.spo_config(policy_config(checkpoints[source])),
            objective=objective,
            clip_low=cfg.spo.clip_low if objective == "skill" else None,
            clip_high=cfg.spo.clip_high if objective == "skill" else None,
            encoder_freeze=freeze,
            output_dir=cfg.output_dir / method,
        )
        history = run_spo(spo_cfg)
        eval_cfg = pipeline.eval_config(method, policy_config(spo_cfg.output_dir / "pretrained_model"))
        rows = evaluate(eval_cfg)
        record_rates(results, method, key, rows, eval_cfg.output_dir)
        record_spo(results, method, key, history)
        results["seconds"][key][method] = time.perf_counter() - t0
        save(path, results)
        print(f"[mw_proxy] seed {seed} {method}: SR {100 * rows['overall']['mean']:.1f} %", flush=True)


def record_spo(results: dict[str, Any], method: str, key: str, history: list[dict[str, Any]]) -> None:
    clip, steps, episodes = spo_summary(history)
    entry = results["methods"][method]
    entry.setdefault("clip_fraction_per_seed", {})[key] = clip
    entry["clip_fraction"] = float(np.mean(list(entry["clip_fraction_per_seed"].values())))
    results["env_steps"].setdefault(method, {})[key] = steps
    results["episodes"].setdefault(method, {})[key] = episodes
    results["spo_history"].setdefault(method, {})[key] = [h["success_rate"] for h in history]
    results.setdefault("spo_health", {}).setdefault(method, {})[key] = {k: [h[k] for h in history] for k in HEALTH}


def table(results: dict[str, Any]) -> str:
    lines = [
        "| method | SR mean ± std (%) | per seed | clip fraction | SPO env steps | SPO episodes |",
        "|---|---:|---|---:|---:|---:|",
    ]
    for method in METHODS:
        e = results["methods"][method]
        if e["mean"] is None:
            continue
        spread = "" if e["std"] is None else f" ± {100 * e['std']:.1f}"
        seeds = ", ".join(f"{100 * v:.1f}" for v in e["per_seed"].values())
        clip = f"{e['clip_fraction']:.3f}" if "clip_fraction" in e else "–"
        steps = sum(results["env_steps"].get(method, {}).values()) or "–"
        episodes = sum(results["episodes"].get(method, {}).values()) or "–"
        lines.append(f"| {method} | {100 * e['mean']:.1f}{spread} | {seeds} | {clip} | {steps} | {episodes} |")
    for name in (f"{a}_minus_{b}" for a, b in DIFFERENCES):
        d = results.get(name)
        if d:
            ci = "" if d["ci95"] is None else f" [95 % CI {100 * d['ci95'][0]:+.1f}, {100 * d['ci95'][1]:+.1f}]"
            lines.append(
                f"\n{name.replace('_minus_', ' − ')}: {100 * d['mean']:+.1f} points{ci} over seeds {d['seeds']}"
            )
    return "\n".join(lines)


def plot(results: dict[str, Any], path: Path) -> None:
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for method, per_seed in results["spo_history"].items():
        curves = [np.array(c) for c in per_seed.values()]
        n = min(len(c) for c in curves)
        ax.plot(range(1, n + 1), 100 * np.mean([c[:n] for c in curves], axis=0), marker="o", label=method)
    ax.set_xlabel("SPO iteration")
    ax.set_ylabel("success rate of the collected groups (%)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("configs/mw_proxy.yaml"))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--methods", default=",".join(METHODS), help="a subset runs first (il, rsft, cso always)")
    parser.add_argument("--work", type=Path, default=Path("outputs/mw_proxy"))
    parser.add_argument("--results", type=Path, default=Path("outputs/mw_proxy.json"))
    args, overrides = parser.parse_known_args()
    command = "python benchmarks/mw_proxy.py " + " ".join(sys.argv[1:])
    methods = tuple(args.methods.split(","))
    if unknown := sorted(set(methods) - set(METHODS)):
        parser.error(f"unknown methods {unknown}; known: {', '.join(METHODS)}")
    if not args.config.is_file():
        parser.error(f"no config file {args.config}")
    try:
        cfg = pipeline_config(args.config, overrides)
        Pipeline(cfg)  # checks the settings (tasks, stop_after, threads) before any results are touched
    except UsageError as e:
        parser.error(str(e))
    results = load(args.results, command, config_spec(cfg))
    started = time.perf_counter()
    finished = sum(len(e["per_seed"]) for e in results["methods"].values())
    with kept_pools():
        for seed in (int(s) for s in args.seeds.split(",")):
            run_seed(cfg, seed, args.work, results, args.results, methods)
    # a rerun with nothing left to do leaves the file (its commands, wall time and plot) as it was
    if sum(len(e["per_seed"]) for e in results["methods"].values()) > finished:
        results["wall_seconds_this_run"] = time.perf_counter() - started
        results |= provenance()  # the commit, machine and date of the latest run that added results
        save(args.results, results)
        if results["spo_history"]:  # the curves of SPO runs: none before a seed's SPO (e.g. --stop_after=eval_il)
            plot(results, args.results.with_suffix(".png"))
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
