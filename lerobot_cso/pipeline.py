"""``lerobot-cso pipeline --config_path=configs/<file>.yaml``: demos → IL → eval → R-SFT → eval → SPO → eval.

One draccus config holds a section per stage: ``demos`` (:class:`~lerobot_cso.demos.DemosConfig`), ``il``
(:class:`ILConfig`: the ``lerobot-train`` run), ``eval`` (:class:`~lerobot_cso.evaluation.EvalConfig`, used
for all three evaluations), ``rsft`` (:class:`~lerobot_cso.cso.rsft.RSFTConfig`) and ``spo``
(:class:`~lerobot_cso.cso.spo.SPOConfig`). The top-level ``tasks`` and ``output_dir`` propagate to every
stage (setting them, or ``policy``, inside a section is refused); each stage's policy is the previous one's.

Layout of ``output_dir``: ``demos/`` (the LeRobotDataset), ``il/`` (``lerobot-train``'s output dir),
``rsft/``, ``spo/``, ``eval/{il,rsft,cso}/``, ``stages/<stage>.json`` (the settings each stage ran with,
whether it completed, and when), and the final ``results.md`` / ``results.json``.

Resuming: a stage whose record says complete and whose output exists is skipped; an unfinished one is run
again and resumes by itself (demos and R-SFT from their journals, SPO from its last iteration, IL with
``lerobot-train --resume=true`` from its last checkpoint). A stage whose settings, or whose upstream stage's
completion, differ from the record is refused (evaluations are simply redone), so stale results are never
mixed with new ones.
"""

import dataclasses
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch
import yaml
from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig

from lerobot_cso.cso.rsft import RSFTConfig
from lerobot_cso.cso.spo import SPOConfig
from lerobot_cso.demos import DemosConfig
from lerobot_cso.durable import write_atomic
from lerobot_cso.envs.tasks import resolve_tasks, task_description
from lerobot_cso.errors import UsageError
from lerobot_cso.evaluation import EvalConfig
from lerobot_cso.policy.configuration_cso import CSOConfig

PROPAGATED = ("tasks", "output_dir", "policy")  # set by the pipeline, never inside a section
SECTIONS = {"demos": PROPAGATED[:2], "eval": PROPAGATED, "rsft": PROPAGATED, "spo": PROPAGATED}
# Policy fields the pipeline sets itself (or that the dataset fills in).
RESERVED_POLICY_KEYS = ("type", "path", "pretrained_path", "tasks", "n_autoencoder_steps")
EVALUATED = {"il": "IL", "rsft": "R-SFT", "cso": "CSO"}  # evaluation name → table column


@dataclass
class ILConfig:
    """The imitation-learning stage: ``lerobot-train --policy.type=cso`` on the demos, as a subprocess."""

    steps: int = 20_000
    # The first n_autoencoder_steps train the skill autoencoder, the rest the skill prior.
    n_autoencoder_steps: int = 5_000
    batch_size: int = 64
    num_workers: int = 2
    save_freq: int = 5_000
    log_freq: int = 200
    seed: int = 1000
    # Policy settings, passed as --policy.<key>=<value> (dims, learning rate, device, ...).
    policy: dict[str, Any] = field(default_factory=dict)
    # Further lerobot-train arguments, verbatim (e.g. "--wandb.enable=true").
    extra_args: list[str] = field(default_factory=list)

    def validate(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or self.save_freq < 1 or self.log_freq < 1:
            raise UsageError("il.steps, il.batch_size, il.save_freq and il.log_freq must be >= 1")
        if not 0 <= self.n_autoencoder_steps < self.steps:
            raise UsageError(
                f"il.n_autoencoder_steps must be in [0, il.steps={self.steps}) so that the prior trains too, "
                f"got {self.n_autoencoder_steps}"
            )
        if self.num_workers < 0:
            raise UsageError(f"il.num_workers must be >= 0, got {self.num_workers}")
        known = {f.name for f in dataclasses.fields(CSOConfig)}
        unknown = sorted(k for k in self.policy if k not in known)
        if unknown:
            raise UsageError(f"il.policy: unknown cso policy setting(s) {', '.join(unknown)}")
        reserved = sorted(k for k in self.policy if k in RESERVED_POLICY_KEYS)
        if reserved:
            raise UsageError(f"il.policy: {', '.join(reserved)} cannot be set here (the pipeline sets it)")
        try:
            CSOConfig(**{k: v for k, v in self.policy.items() if k != "push_to_hub"} | {"device": "cpu"})
        except (TypeError, ValueError) as e:
            raise UsageError(f"il.policy: {e}") from None


@dataclass
class PipelineConfig:
    """Settings of ``lerobot-cso pipeline`` (see the module docstring; examples in ``configs/``)."""

    # One task, a comma list, or a set (MT10, ML45-train, ...): every stage runs on these.
    tasks: str = "MT10"
    output_dir: Path = Path("outputs/pipeline")
    # CPU threads of torch in every stage (lerobot-train too, via OMP_NUM_THREADS); null: torch's default.
    # 1 is much faster on a few shared cores, where spinning threads wait for each other.
    torch_threads: int | None = None
    # Training seed of the whole run: when set, it replaces demos.seed, rsft.seed and spo.seed, and il.seed
    # becomes 1000 + seed (evaluation states stay those of eval.seeds). null: each section's own seed.
    seed: int | None = None
    demos: DemosConfig = field(default_factory=DemosConfig)
    il: ILConfig = field(default_factory=ILConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    rsft: RSFTConfig = field(default_factory=RSFTConfig)
    spo: SPOConfig = field(default_factory=SPOConfig)


def _cli_value(value: Any) -> str:
    """A yaml value as a draccus command-line value (lists, mappings and booleans as JSON)."""
    return (
        json.dumps(value, separators=(",", ":"))
        if isinstance(value, (list, dict, bool)) or value is None
        else str(value)
    )


def _settings(section: Any, runtime: tuple[str, ...] = ()) -> dict[str, Any]:
    """A section's settings as plain JSON data, without the propagated fields and the ``runtime`` ones
    (those that do not change the stage's result, so a rerun may change them, e.g. to resume with less memory)."""
    skip = runtime if isinstance(section, ILConfig) else (*PROPAGATED, *runtime)
    data = {f.name: getattr(section, f.name) for f in dataclasses.fields(section) if f.name not in skip}
    return json.loads(
        json.dumps(data, default=lambda o: dataclasses.asdict(o) if dataclasses.is_dataclass(o) else str(o))
    )


def _flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out |= _flatten(value, f"{prefix}.{key}" if prefix else key)
    return out


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
            self.tasks = resolve_tasks(cfg.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        if cfg.torch_threads is not None and cfg.torch_threads < 1:
            raise UsageError(f"torch_threads must be >= 1 or null, got {cfg.torch_threads}")
        self.seconds: dict[str, float] = {}
        self.validate()

    # Stage configs, with the propagated fields filled in.
    def demos_config(self) -> DemosConfig:
        return dataclasses.replace(self.cfg.demos, tasks=self.cfg.tasks, output_dir=self.out / "demos")

    def eval_config(self, name: str, policy: PreTrainedConfig) -> EvalConfig:
        return dataclasses.replace(
            self.cfg.eval, tasks=self.cfg.tasks, output_dir=self.out / "eval" / name, policy=policy
        )

    def rsft_config(self, policy: PreTrainedConfig) -> RSFTConfig:
        return dataclasses.replace(self.cfg.rsft, tasks=self.cfg.tasks, output_dir=self.out / "rsft", policy=policy)

    def spo_config(self, policy: PreTrainedConfig) -> SPOConfig:
        return dataclasses.replace(self.cfg.spo, tasks=self.cfg.tasks, output_dir=self.out / "spo", policy=policy)

    def validate(self) -> None:
        """Check every section before anything runs, with a stand-in for the policies still to be trained."""
        self.demos_config().validate()
        self.cfg.il.validate()
        stand_in = CSOConfig(tasks=[task_description(t) for t in self.tasks], device="cpu")
        stand_in.pretrained_path = self.out / "il"
        self.eval_config("il", stand_in).validate()
        self.rsft_config(stand_in).validate()
        self.spo_config(stand_in).validate()

    # Records.
    def record_path(self, stage: str) -> Path:
        return self.out / "stages" / f"{stage}.json"

    def record(self, stage: str) -> dict[str, Any] | None:
        path = self.record_path(stage)
        return json.loads(path.read_text()) if path.is_file() else None

    def finished_at(self, stage: str) -> str:
        return self.record(stage)["finished_at"]

    def stage(
        self,
        name: str,
        spec: dict[str, Any],
        output: Path,
        complete: Path,
        run: Callable[[], Any],
        redo_on_change: bool = False,
    ) -> Any:
        """Run ``run`` unless its record (same ``spec``) says it completed and ``complete`` exists."""
        record = self.record(name)
        if record is not None and record["spec"] != spec and output.exists() and not redo_on_change:
            old, new = _flatten(record["spec"]), _flatten(spec)
            changed = ", ".join(
                f"{k}: {old.get(k)} → {new.get(k)}" for k in sorted(old.keys() | new.keys()) if old.get(k) != new.get(k)
            )
            raise UsageError(
                f"{output} was made with other settings or inputs ({changed}); delete it and the stages after it, "
                "or choose another output_dir"
            )
        if record is not None and record["spec"] == spec and record["complete"] and complete.exists():
            print(f"[pipeline] {name}: complete, skipped ({output})", flush=True)
            self.seconds[name] = record["seconds"]
            return record["summary"]
        print(f"[pipeline] {name}: running → {output}", flush=True)
        self.record_path(name).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(self.record_path(name), json.dumps({"spec": spec, "complete": False}, indent=2).encode())
        started = time.perf_counter()
        summary = run()
        seconds = time.perf_counter() - started
        self.seconds[name] = seconds
        finished = {
            "spec": spec,
            "complete": True,
            "finished_at": dt.datetime.now().isoformat(),
            "seconds": seconds,
            "summary": summary,
        }
        write_atomic(self.record_path(name), json.dumps(finished, indent=2, default=str).encode())
        print(f"[pipeline] {name}: done in {seconds:.0f} s", flush=True)
        return summary

    # Stages.
    def run_demos(self) -> Path:
        from lerobot_cso.demos import generate_demos

        cfg = self.demos_config()
        spec = {"tasks": self.tasks, "demos": _settings(cfg, runtime=("num_envs",))}
        self.stage("demos", spec, cfg.output_dir, cfg.output_dir / "meta" / "info.json", lambda: generate_demos(cfg))
        return cfg.output_dir

    def run_il(self, dataset: Path) -> Path:
        il = self.cfg.il
        out = self.out / "il"
        policy = out / "checkpoints" / "last" / "pretrained_model"
        spec = {
            "il": _settings(il, runtime=("num_workers", "save_freq", "log_freq")),
            "after": {"demos": self.finished_at("demos")},
        }

        def steps_done() -> int:
            path = out / "checkpoints" / "last" / "training_state" / "training_step.json"
            return json.loads(path.read_text())["step"] if path.is_file() else 0

        def train() -> dict[str, Any]:
            common = [
                f"--output_dir={out}",
                f"--dataset.root={dataset}",
                f"--dataset.repo_id={self.cfg.demos.repo_id}",
                "--dataset.video_backend=pyav",  # no videos in the demos; skips probing torchcodec
                f"--steps={il.steps}",
                f"--num_workers={il.num_workers}",
            ]
            if steps_done() >= il.steps:
                args = None  # finished; only its record was missing
            elif (policy / "train_config.json").is_file():
                args = ["--resume=true", f"--config_path={policy / 'train_config.json'}", *common]
            else:
                shutil.rmtree(out, ignore_errors=True)  # killed before its first checkpoint: start over
                settings = {"push_to_hub": False, **il.policy, "n_autoencoder_steps": il.n_autoencoder_steps}
                args = [
                    "--policy.type=cso",
                    *common,
                    f"--batch_size={il.batch_size}",
                    f"--save_freq={min(il.save_freq, il.steps)}",
                    f"--log_freq={il.log_freq}",
                    f"--seed={il.seed}",
                    *(f"--policy.{k}={_cli_value(v)}" for k, v in settings.items()),
                    *il.extra_args,
                ]
            if args is not None:
                _lerobot_train(args, self.cfg.torch_threads)
            if steps_done() < il.steps:
                raise RuntimeError(f"lerobot-train stopped at step {steps_done()} of {il.steps}")
            return {"steps": steps_done(), "checkpoint": str(policy)}

        self.stage("il", spec, out, policy / "config.json", train)
        return policy

    def run_eval(self, name: str, policy_path: Path, upstream: str) -> dict[str, Any]:
        from lerobot_cso.evaluation import evaluate, markdown_table

        cfg = self.eval_config(name, policy_config(policy_path))
        spec = {"eval": _settings(cfg), "after": {upstream: self.finished_at(upstream)}}

        def run() -> dict[str, Any]:
            rows = evaluate(cfg)
            print(markdown_table(rows), flush=True)
            return rows

        self.stage(f"eval_{name}", spec, cfg.output_dir, cfg.output_dir / "eval.json", run, redo_on_change=True)
        return json.loads((cfg.output_dir / "eval.json").read_text())["success_rate"]

    def run_rsft(self, il_policy: Path) -> Path:
        from lerobot_cso.cso.rsft import run_rsft

        cfg = self.rsft_config(policy_config(il_policy))
        spec = {"rsft": _settings(cfg), "after": {"il": self.finished_at("il")}}
        out = cfg.output_dir / "pretrained_model"
        self.stage("rsft", spec, cfg.output_dir, out / "config.json", lambda: run_rsft(cfg))
        return out

    def run_spo(self, rsft_policy: Path) -> Path:
        from lerobot_cso.cso.spo import run_spo

        cfg = self.spo_config(policy_config(rsft_policy))
        spec = {"spo": _settings(cfg), "after": {"rsft": self.finished_at("rsft")}}
        out = cfg.output_dir / "pretrained_model"
        self.stage("spo", spec, cfg.output_dir, out / "config.json", lambda: run_spo(cfg))
        return out

    def run(self) -> dict[str, Any]:
        """All stages in order; returns the results (also written to ``results.md`` / ``results.json``)."""
        started = time.perf_counter()
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)
        self.out.mkdir(parents=True, exist_ok=True)
        dataset = self.run_demos()
        il = self.run_il(dataset)
        rates = {"il": self.run_eval("il", il, "il")}
        rsft = self.run_rsft(il)
        rates["rsft"] = self.run_eval("rsft", rsft, "rsft")
        cso = self.run_spo(rsft)
        rates["cso"] = self.run_eval("cso", cso, "spo")
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
            "checkpoints": {"il": str(il), "rsft": str(rsft), "cso": str(cso)},
            "eval": {"episodes_per_task": self.cfg.eval.episodes_per_task, "seeds": self.cfg.eval.seeds},
            "stage_seconds": self.seconds,
            "table": table,
        }
        write_atomic(self.out / "results.json", json.dumps(results, indent=2).encode())
        seeds = len(self.cfg.eval.eval_seeds())
        noise = ", ".join(f"{EVALUATED[n]} ± {100 * rates[n]['overall']['se']:.1f}" for n in EVALUATED)
        caption = (
            f"Success rate (%) over {self.cfg.eval.episodes_per_task} evaluation episodes per task × {seeds} "
            f"evaluation seed(s), on held-out initial states; ± is one binomial standard error. Noise of the mean "
            f"over tasks (1 s.e., points): {noise}."
        )
        history = [json.loads(line) for line in (self.out / "spo" / "log.jsonl").read_text().splitlines()]
        plot_results(self.out / "results.png", rates, history)
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


def _lerobot_train(args: list[str], threads: int | None) -> None:
    """Run ``lerobot-train`` (the one next to this interpreter) with our output streamed through."""
    exe = Path(sys.executable).parent / "lerobot-train"
    command = [str(exe) if exe.exists() else "lerobot-train", *args]
    env = os.environ | ({"OMP_NUM_THREADS": str(threads)} if threads else {})
    print("[pipeline] " + " ".join(command), flush=True)
    returncode = subprocess.run(command, env=env).returncode
    if returncode != 0:
        raise RuntimeError(f"lerobot-train failed with exit code {returncode} (its output is above)")


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
    """Run (or resume) the whole pipeline; returns the results."""
    return Pipeline(cfg).run()


@parser.wrap()
def pipeline_main(cfg: PipelineConfig) -> None:
    """Entry point of ``lerobot-cso pipeline``."""
    check_sections(sys.argv[1:], parser.parse_arg("config_path"))
    run_pipeline(cfg)
