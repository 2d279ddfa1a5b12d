"""``lerobot-cso pipeline --config_path=configs/<file>.yaml``: demos → IL → eval → R-SFT → eval → SPO → eval.

One draccus config holds a section per stage: ``demos`` (:class:`~lerobot_cso.demos.DemosConfig`),
``il`` (:class:`~lerobot_cso.il.ILConfig`: the ``lerobot-train`` run), ``eval``
(:class:`~lerobot_cso.evaluation.EvalConfig`, used for all three evaluations), ``rsft``
(:class:`~lerobot_cso.cso.rsft.RSFTConfig`) and ``spo`` (:class:`~lerobot_cso.cso.spo.SPOConfig`). The
top-level ``tasks`` and ``output_dir`` propagate to every stage (setting them, or ``policy``, inside a
section is refused); each stage's policy is the previous one's.

The demo stage generates demonstrations with the world's scripted expert (MetaWorld's; LIBERO-Object's), or, with
``demos.dataset_root`` (and ``demos.repo_id``), checks an existing LeRobotDataset and hands it to IL instead: the
way to run on tasks without an expert, or on one's own data (``--tasks=libero_spatial --demos.dataset_root=...
--demos.repo_id=...``).

Layout of ``output_dir``: ``demos/`` (the generated LeRobotDataset), ``il/`` (``lerobot-train``'s output
dir), ``rsft/``, ``spo/``, ``eval/{il,rsft,cso}/``, ``stages/<stage>.json`` (the settings each stage ran with,
whether it completed, and when), and the final ``results.md`` / ``results.json``.

Every stage implements :class:`~lerobot_cso.stage.Stage` (its spec, its output, whether it is complete,
run); :meth:`Pipeline.execute` keeps the records. Resuming: a stage whose record says complete and that is
complete is skipped; an unfinished one is run
again and resumes by itself (demos and R-SFT from their journals, SPO from its last iteration, IL with
``lerobot-train --resume=true`` from its last checkpoint). A stage whose settings, or whose upstream stage's
completion, differ from the record is refused (evaluations are simply redone), so stale results are never
mixed with new ones. ``stop_after`` ends a run after one stage (e.g. ``--stop_after=il`` for an IL checkpoint and
nothing else); the same command without it continues from there.

The rollout stages (the evaluations, R-SFT, SPO) run inside :func:`~lerobot_cso.rollout.pool.kept_pools`: stages
with the same rollout settings share one env pool, whose worker processes and MuJoCo models are built once.
"""

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch
import yaml
from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig

from lerobot_cso.cso.rsft import RSFTConfig, RSFTStage
from lerobot_cso.cso.spo import SPOConfig, SPOStage
from lerobot_cso.demos import DemosConfig, demos_stage
from lerobot_cso.durable import output_lock, read_json, write_atomic, write_json
from lerobot_cso.errors import UsageError, check_output_dir
from lerobot_cso.evaluation import EvalConfig, EvalStage
from lerobot_cso.il import ILConfig, ILStage
from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.records import run_recorded
from lerobot_cso.rollout.pool import kept_pools
from lerobot_cso.stage import PIPELINE_FIELDS, Stage
from lerobot_cso.worlds.base import WorldConfig
from lerobot_cso.worlds.registry import default_world

SECTIONS = {"demos": PIPELINE_FIELDS[:2], "eval": PIPELINE_FIELDS, "rsft": PIPELINE_FIELDS, "spo": PIPELINE_FIELDS}
EVALUATED = {"il": "IL", "rsft": "R-SFT", "cso": "CSO"}  # evaluation name → table column
STAGES = ("demos", "il", "eval_il", "rsft", "eval_rsft", "spo", "eval_cso")  # in the order they run


@dataclass
class PipelineConfig:
    """Settings of ``lerobot-cso pipeline`` (see the module docstring; examples in ``configs/``)."""

    # The world every stage runs in (--world.type=...); null: the world whose tasks --tasks names.
    world: WorldConfig | None = None
    # One task, a comma list, or a set (MT10, ML45-train, ...): every stage runs on these.
    tasks: str = "MT10"
    output_dir: Path = Path("outputs/pipeline")
    # CPU threads of torch in every stage (lerobot-train too, via OMP_NUM_THREADS); null: torch's default.
    # 1 is much faster on a few shared cores, where spinning threads wait for each other.
    torch_threads: int | None = None
    # CPU threads of torch while a stage trains (IL's lerobot-train, R-SFT's fine-tune, SPO's updates), in place
    # of torch_threads; it replaces rsft.train_threads and spo.train_threads. null: torch_threads throughout.
    train_threads: int | None = None
    # Training seed of the whole run: when set, it replaces demos.seed, rsft.seed and spo.seed, and il.seed
    # becomes 1000 + seed (evaluation states stay those of eval.seeds). null: each section's own seed.
    seed: int | None = None
    # The last stage to run (one of STAGES but the last); null: every stage. The later ones are left for a rerun
    # without it.
    stop_after: str | None = None
    demos: DemosConfig = field(default_factory=DemosConfig)
    il: ILConfig = field(default_factory=ILConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    rsft: RSFTConfig = field(default_factory=RSFTConfig)
    spo: SPOConfig = field(default_factory=SPOConfig)


def check_sections(args: list[str], config_path: str | None) -> None:
    """Refuse ``tasks``, ``output_dir`` or ``policy`` inside a section (yaml or command line)."""
    given: list[str] = []
    if config_path:
        data = yaml.safe_load(Path(config_path).read_text()) or {}
        for section, keys in SECTIONS.items():
            given += [f"{section}.{k}" for k in (data.get(section) or {}) if k in keys]
    for arg in args:
        key = arg.removeprefix("--").split("=")[0].split(".")
        if len(key) >= 2 and key[1] in SECTIONS.get(key[0], ()):
            given.append(f"{key[0]}.{key[1]}")
    if given:
        raise UsageError(
            f"{', '.join(sorted(set(given)))}: set tasks and output_dir at the top level only; each stage's "
            "policy is the previous stage's output"
        )


class StoppedAfter(Exception):
    """Raised by :meth:`Pipeline.execute` once the stage named by ``stop_after`` is complete."""


class Pipeline:
    """The stages of one pipeline config, each run or skipped according to its record."""

    def __init__(self, cfg: PipelineConfig) -> None:
        if cfg.seed is not None:
            cfg = dataclasses.replace(
                cfg,
                demos=dataclasses.replace(cfg.demos, seed=cfg.seed),
                il=dataclasses.replace(cfg.il, seed=1000 + cfg.seed),
                rsft=dataclasses.replace(cfg.rsft, seed=cfg.seed),
                spo=dataclasses.replace(cfg.spo, seed=cfg.seed),
            )
        self.cfg = cfg
        self.out = cfg.output_dir
        try:
            self.tasks = self.world_settings().build(cfg.tasks, None, cfg.output_dir).resolve_tasks(cfg.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        for name in ("torch_threads", "train_threads"):
            if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
                raise UsageError(f"{name} must be >= 1 or null, got {getattr(cfg, name)}")
        if cfg.stop_after not in (None, *STAGES[:-1]):  # after the last stage is the whole run: null
            raise UsageError(f"stop_after must be one of {', '.join(STAGES[:-1])} or null, got {cfg.stop_after!r}")
        self.seconds: dict[str, float] = {}
        self.rates: dict[str, dict[str, Any]] = {}  # evaluation name → its success rates, as they finish
        self.validate()

    def world_settings(self) -> WorldConfig:
        return self.cfg.world if self.cfg.world is not None else default_world(self.cfg.tasks)

    # Stage configs, with the propagated fields filled in.
    def demos_config(self) -> DemosConfig:
        return dataclasses.replace(
            self.cfg.demos, world=self.cfg.world, tasks=self.cfg.tasks, output_dir=self.out / "demos"
        )

    def eval_config(self, name: str, policy: PreTrainedConfig) -> EvalConfig:
        return dataclasses.replace(
            self.cfg.eval,
            world=self.cfg.world,
            tasks=self.cfg.tasks,
            output_dir=self.out / "eval" / name,
            policy=policy,
        )

    def train_threads(self) -> int | None:
        """Threads of the IL stage's lerobot-train."""
        return self.cfg.train_threads or self.cfg.torch_threads

    def rsft_config(self, policy: PreTrainedConfig) -> RSFTConfig:
        out = self.out / "rsft"
        cfg = dataclasses.replace(
            self.cfg.rsft, world=self.cfg.world, tasks=self.cfg.tasks, output_dir=out, policy=policy
        )
        if self.cfg.train_threads:
            cfg = dataclasses.replace(cfg, train_threads=self.cfg.train_threads)
        if cfg.demo_fraction:  # the demonstrations IL trained on
            demos = demos_stage(self.demos_config()).output()
            cfg = dataclasses.replace(cfg, demos_root=demos, demos_repo_id=self.cfg.demos.repo_id)
        return cfg

    def spo_config(self, policy: PreTrainedConfig) -> SPOConfig:
        out = self.out / "spo"
        cfg = dataclasses.replace(
            self.cfg.spo, world=self.cfg.world, tasks=self.cfg.tasks, output_dir=out, policy=policy
        )
        if self.cfg.train_threads:
            cfg = dataclasses.replace(cfg, train_threads=self.cfg.train_threads)
        return cfg

    def validate(self) -> None:
        """Check every section before anything runs, with a stand-in for the policies still to be trained."""
        check_output_dir(self.out)
        self.demos_config().validate()
        self.cfg.il.validate()
        describe = self.world_settings().build(self.cfg.tasks, None, self.out).task_description
        stand_in = CSOConfig(tasks=[describe(t) for t in self.tasks], device="cpu")
        stand_in.pretrained_path = self.out / "il"
        self.eval_config("il", stand_in).validate()
        self.rsft_config(stand_in).validate()
        self.spo_config(stand_in).validate()

    # Records.
    def record_path(self, stage: str) -> Path:
        return self.out / "stages" / f"{stage}.json"

    def finished_at(self, stage: str) -> str:
        return read_json(self.record_path(stage))["finished_at"]

    def execute(self, stage: Stage, after: str | None = None) -> Any:
        """Run ``stage`` unless its record (same spec, ``after`` the same run of its upstream stage) says it
        completed and it is complete; a changed spec over an existing output is refused unless the stage
        is simply redone (``redo_on_change``) or only grows in one of the stage's ``grows`` keys (it continues).
        Raises :class:`StoppedAfter` when ``stage`` is the config's ``stop_after``."""
        summary = self._execute(stage, after)
        if stage.name == self.cfg.stop_after:
            raise StoppedAfter(stage.name)
        return summary

    def _execute(self, stage: Stage, after: str | None) -> Any:
        spec = stage.spec() | ({"after": {after: self.finished_at(after)}} if after else {})
        elsewhere = "delete it and the stages after it, or choose another output_dir"
        label = f"[pipeline] {stage.name}"
        summary, self.seconds[stage.name] = run_recorded(stage, self.record_path(stage.name), spec, label, elsewhere)
        return summary

    def evaluate(self, label: str, policy: Path, upstream: str) -> dict[str, Any]:
        stage = EvalStage(label, self.eval_config(label, policy_config(policy)))
        try:
            self.execute(stage, after=upstream)
        except StoppedAfter:  # complete: a stopped run reports it too
            self.rates[label] = stage.success_rate()
            raise
        self.rates[label] = stage.success_rate()
        return self.rates[label]

    def run(self) -> dict[str, Any]:
        """All stages in order; returns the results (also written to ``results.md`` / ``results.json``), or, with
        ``stop_after``, ``{"stopped_after": stage, "stage_seconds": ..., "success_rate": ...}`` once that stage is
        complete (the success rates of the evaluations done by then)."""
        try:
            return self._run()
        except StoppedAfter as stop:
            print(f"[pipeline] stopped after {stop} (stop_after); the same command without it continues", flush=True)
            return {"stopped_after": str(stop), "stage_seconds": self.seconds, "success_rate": self.rates}

    def _run(self) -> dict[str, Any]:
        started = time.perf_counter()
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)
        self.out.mkdir(parents=True, exist_ok=True)
        demos = demos_stage(self.demos_config())
        self.execute(demos)
        il = ILStage(self.cfg.il, demos.output(), self.cfg.demos.repo_id, self.out / "il", self.train_threads())
        self.execute(il, after="demos")
        with kept_pools():  # the rollout stages share their env pools (workers and models built once)
            self.evaluate("il", il.policy(), "il")
            rsft = RSFTStage(self.rsft_config(policy_config(il.policy())))
            self.execute(rsft, after="il")
            self.evaluate("rsft", rsft.policy(), "rsft")
            spo = SPOStage(self.spo_config(policy_config(rsft.policy())))
            self.execute(spo, after="rsft")
            self.evaluate("cso", spo.policy(), "spo")
        rates = self.rates
        table = results_table(self.tasks, rates)
        results = {
            "tasks": self.tasks,
            "output_dir": str(self.out),
            "success_rate": rates,
            "cso_minus_il": dict(
                zip(
                    ("mean", "ci95_low", "ci95_high"),
                    gain_interval(rates["il"]["overall"], rates["cso"]["overall"]),
                    strict=True,
                )
            ),
            "checkpoints": {"il": str(il.policy()), "rsft": str(rsft.policy()), "cso": str(spo.policy())},
            "eval": {"episodes_per_task": self.cfg.eval.episodes_per_task, "seeds": self.cfg.eval.seeds},
            "stage_seconds": self.seconds,
            "table": table,
        }
        write_json(self.out / "results.json", results)
        seeds = len(self.cfg.eval.eval_seeds())
        noise = ", ".join(f"{EVALUATED[n]} ± {100 * rates[n]['overall']['se']:.1f}" for n in EVALUATED)
        caption = (
            f"Success rate (%) over {self.cfg.eval.episodes_per_task} evaluation episodes per task × {seeds} "
            f"evaluation seed(s), on held-out initial states; ± is one binomial standard error. Noise of the mean "
            f"over tasks (1 s.e., points): {noise}."
        )
        plot_results(self.out / "results.png", rates, spo.history())
        timing = ", ".join(f"{k} {v:.0f} s" for k, v in self.seconds.items())
        write_atomic(self.out / "results.md", f"{table}\n\n{caption}\n\nStage wall times: {timing}.\n".encode())
        print(
            f"\n{table}\n\n{caption}\n[pipeline] done in {time.perf_counter() - started:.0f} s; "
            f"wrote {self.out / 'results.md'}, results.json and results.png",
            flush=True,
        )
        return results


def policy_config(path: Path) -> PreTrainedConfig:
    config = PreTrainedConfig.from_pretrained(path)
    config.pretrained_path = path
    return config


def _cell(row: dict[str, Any]) -> str:
    return f"{100 * row['mean']:.1f} ± {100 * row['se']:.1f}"


def gain_interval(il: dict[str, Any], cso: dict[str, Any]) -> tuple[float, float, float]:
    """CSO − IL and its 95 % confidence interval (normal approximation; the two evaluations are treated as
    independent, which is conservative since they share their initial states)."""
    gain = cso["mean"] - il["mean"]
    half = 1.96 * float(np.hypot(il["se"], cso["se"]))
    return gain, gain - half, gain + half


def results_table(tasks: list[str], rates: dict[str, dict[str, Any]]) -> str:
    """Markdown table: per task and the mean over tasks, the success rate ± its standard error of IL, R-SFT
    and CSO, and CSO − IL with its 95 % confidence interval."""
    lines = ["| task | " + " | ".join(EVALUATED.values()) + " | CSO − IL [95 % CI] |", "|---|---:|---:|---:|---:|"]
    for task in [*tasks, "overall"]:
        cells = [_cell(rates[name][task]) for name in EVALUATED]
        gain, low, high = (100 * v for v in gain_interval(rates["il"][task], rates["cso"][task]))
        name = "**mean**" if task == "overall" else task
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {gain:+.1f} [{low:+.1f}, {high:+.1f}] |")
    return "\n".join(lines)


def plot_results(path: Path, rates: dict[str, dict[str, Any]], spo_history: list[dict[str, Any]]) -> None:
    """PNG: mean success rate per stage (± 1 s.e.), and SPO's per-iteration group success and clip fraction."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    names = list(EVALUATED)
    means = [100 * rates[n]["overall"]["mean"] for n in names]
    errors = [100 * rates[n]["overall"]["se"] for n in names]
    left.bar([EVALUATED[n] for n in names], means, yerr=errors, capsize=4, color=["tab:gray", "tab:blue", "tab:green"])
    left.set_ylabel("mean success rate (%)")
    left.set_ylim(0, 105)
    left.set_title("evaluation, mean over tasks (± 1 s.e.)")
    iterations = [h["iteration"] for h in spo_history]
    right.plot(iterations, [100 * h["success_rate"] for h in spo_history], marker="o", label="group success (%)")
    right.plot(iterations, [100 * h["clip_fraction"] for h in spo_history], marker="s", label="clip fraction (%)")
    right.set_xlabel("SPO iteration")
    right.set_ylim(0, 105)
    right.legend()
    right.set_title("SPO rollouts")
    for ax in (left, right):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_pipeline(cfg: PipelineConfig) -> dict[str, Any]:
    """Run (or resume) the whole pipeline, the only writer of its output dir; returns the results."""
    pipeline = Pipeline(cfg)
    with output_lock(pipeline.out):
        return pipeline.run()


@parser.wrap()
def pipeline_main(cfg: PipelineConfig) -> None:
    """Entry point of ``lerobot-cso pipeline``."""
    check_sections(sys.argv[1:], parser.parse_arg("config_path"))
    run_pipeline(cfg)
