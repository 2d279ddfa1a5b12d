"""`lerobot-cso pipeline` as a real subprocess: a tiny end-to-end run, a rerun that skips every stage, bad configs."""

import dataclasses
import functools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import draccus
import pytest
import torch
from benchmark_scripts import benchmark_module

from lerobot_cso.cli import main
from lerobot_cso.pipeline import Pipeline, PipelineConfig

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
STAGES = ("demos", "il", "eval_il", "rsft", "eval_rsft", "spo", "eval_cso")
TASKS = ("drawer-close-v3", "button-press-v3")

# Two easy tasks and a tiny policy: IL solves drawer-close and sometimes button-press, so R-SFT finds
# successes on both. The stages roll out in this process (sync), which gives the same episodes as the worker
# processes (tests/test_sharded.py) without starting them for four envs.
TINY = """
tasks: {tasks}
output_dir: {out}
torch_threads: 1
demos: {{episodes_per_task: 8, num_envs: 2}}
il:
  steps: 200
  n_autoencoder_steps: 80
  batch_size: 16
  num_workers: 1
  save_freq: 100
  log_freq: 50
  policy: {{device: cpu, ae_dim: 32, ae_heads: 2, ae_encoder_layers: 1, ae_decoder_layers: 1, prior_dim: 48,
           prior_heads: 2, prior_layers: 2, state_embed_dim: 16, optimizer_lr: 0.001, optimizer_min_lr: 0.0001}}
eval: {{episodes_per_task: 4, num_envs: 4, vectorization: sync, max_steps: 150}}
rsft: {{successes_per_task: 2, n_strikes: 4, states_per_round: 1, max_states_per_task: 20, num_envs: 4,
       vectorization: sync, epochs: 1, batch_size: 16}}
spo: {{iterations: 1, groups_per_iteration: 2, group_size: 4, epochs: 1, minibatch_trajectories: 4, num_envs: 4,
      vectorization: sync, max_draw_factor: 4}}
"""


def pipeline(*args: str) -> subprocess.CompletedProcess:
    cmd = [str(BIN / "lerobot-cso"), "pipeline", *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=900)


def final_table(stdout: str) -> str:
    lines = stdout.splitlines()
    start = max(i for i, line in enumerate(lines) if line.startswith("| task | IL | R-SFT | CSO |"))
    return "\n".join(lines[start : start + len(TASKS) + 3])


@pytest.fixture
def tiny_config(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.format(tasks=",".join(TASKS), out=tmp_path / "run"))
    return path


def test_stopped_end_to_end_then_continued_then_rerun_skips_every_stage(tiny_config, tmp_path):
    out = tmp_path / "run"
    stopped = pipeline(f"--config_path={tiny_config}", "--stop_after=eval_il")
    assert stopped.returncode == 0, stopped.stdout[-3000:] + stopped.stderr[-3000:]
    assert [s for s in STAGES if f"[pipeline] {s}: running" in stopped.stdout] == ["demos", "il", "eval_il"]
    assert "[pipeline] stopped after eval_il (stop_after)" in stopped.stdout
    assert not (out / "rsft").exists() and not (out / "results.json").exists()
    # run again in this process, stopped where it stopped: every stage is skipped, and IL's evaluation is reported
    cfg = draccus.parse(PipelineConfig, args=[f"--config_path={tiny_config}", "--stop_after=eval_il"])
    again = Pipeline(cfg).run()
    assert again["stopped_after"] == "eval_il" and list(again["success_rate"]) == ["il"]

    first = pipeline(f"--config_path={tiny_config}")  # the same command without stop_after continues
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    assert all(f"[pipeline] {stage}: complete, skipped" in first.stdout for stage in STAGES[:3])
    assert all(f"[pipeline] {stage}: running" in first.stdout for stage in STAGES[3:])
    results = json.loads((out / "results.json").read_text())
    table = final_table(first.stdout)
    print(table)
    assert results["table"] == table and (out / "results.md").read_text().startswith(table)
    assert results["success_rate"]["il"] == again["success_rate"]["il"]
    for name in ("il", "rsft", "cso"):
        rates = results["success_rate"][name]
        assert set(rates) == {*TASKS, "overall"} and all(0 <= r["mean"] <= 1 for r in rates.values())
    assert results["success_rate"]["il"]["drawer-close-v3"]["mean"] > 0
    gain = results["cso_minus_il"]
    il, cso = results["success_rate"]["il"]["overall"], results["success_rate"]["cso"]["overall"]
    assert gain["mean"] == pytest.approx(cso["mean"] - il["mean"])
    assert gain["ci95_high"] - gain["mean"] == pytest.approx(1.96 * (il["se"] ** 2 + cso["se"] ** 2) ** 0.5)
    assert (out / "results.png").stat().st_size > 1000
    assert json.loads((out / "rsft" / "pretrained_model" / "config.json").read_text())["freeze_encoders"]
    assert len((out / "spo" / "log.jsonl").read_text().splitlines()) == 1  # one SPO iteration

    second = pipeline(f"--config_path={tiny_config}")
    assert second.returncode == 0, second.stderr[-3000:]
    assert all(f"[pipeline] {stage}: complete, skipped" in second.stdout for stage in STAGES)
    assert ": running" not in second.stdout
    assert final_table(second.stdout) == table
    # The pipeline's own time, after the imports (the command's wall time is mostly LeRobot's import: 20 s alone
    # on a slow 2-core VM, 78 s there under the parallel suite): skipping every stage costs about a second (the
    # results plot), the four stages it skips ~20 s. Judged against the run that did them, on the same loaded
    # machine: an absolute 5 s read 6 s in CI under the parallel suite.
    ran, skipped = (int(re.search(r"\[pipeline\] done in (\d+) s", run.stdout).group(1)) for run in (first, second))
    assert skipped <= ran / 4, (skipped, ran)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--rsft.tasks=reach-v3"], "rsft.tasks: set tasks and output_dir at the top level only"),
        (["--il.policy={prior_dimm: 8}"], "il.policy: unknown cso policy setting(s) prior_dimm"),
        (["--il.n_autoencoder_steps=200"], "il.n_autoencoder_steps must be in [0, il.steps=200)"),
        (["--spo.group_size=1"], "group_size must be >= 2"),
        (["--tasks=reach-v9"], "unknown MetaWorld task 'reach-v9'"),
        (["--train_threads=0"], "train_threads must be >= 1 or null, got 0"),
        (["--spo.train_threads=0"], "train_threads must be >= 1 or null, got 0"),
        (["--eval.train_threads=2"], "unrecognized arguments: --eval.train_threads=2"),  # evaluation trains nothing
        (["--stop_after=eval_cso"], "stop_after must be one of demos, il, eval_il, rsft, eval_rsft, spo or null"),
    ],
)
def test_bad_config_is_one_error_line_before_anything_runs(tiny_config, tmp_path, args, message, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # the CLI hands its arguments to the parser via sys.argv
    assert main(["pipeline", f"--config_path={tiny_config}", *args]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"error: {message}")
    assert not (tmp_path / "run").exists()


def test_top_level_seed_reaches_every_training_stage(tiny_config):
    with open(tiny_config) as f:
        cfg = draccus.load(PipelineConfig, f)
    seeded = Pipeline(dataclasses.replace(cfg, seed=3)).cfg
    assert (seeded.demos.seed, seeded.il.seed, seeded.rsft.seed, seeded.spo.seed) == (3, 1003, 3, 3)
    unseeded = Pipeline(cfg).cfg
    assert (unseeded.il.seed, unseeded.spo.seed) == (cfg.il.seed, cfg.spo.seed)


def test_train_threads_reach_every_training_stage_but_no_spec(tiny_config):
    with open(tiny_config) as f:
        cfg = draccus.load(PipelineConfig, f)
    plain, threaded = Pipeline(cfg), Pipeline(dataclasses.replace(cfg, train_threads=2))
    assert (plain.train_threads(), threaded.train_threads()) == (1, 2)  # IL's lerobot-train: torch_threads by default
    for make in ("rsft_config", "spo_config"):
        base, other = getattr(plain, make)(None), getattr(threaded, make)(None)
        assert (base.train_threads, other.train_threads) == (None, 2)
        assert other.stage_spec() == base.stage_spec()  # a finished stage is not redone for another thread count
    torch.set_num_threads(1)
    with other.training():
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == 1
    with base.training():  # null: the process's setting
        assert torch.get_num_threads() == 1


def test_a_simulated_stages_spec_holds_no_world_settings(tiny_config):
    """Naming the world the tasks imply must not redo a stage, and the robot's settings exist on the robot world
    only (a simulated stage's spec has none of them)."""
    from lerobot_cso.worlds.metaworld.world import MetaWorldConfig

    with open(tiny_config) as f:
        cfg = draccus.load(PipelineConfig, f)
    base = Pipeline(cfg).rsft_config(None)
    named = dataclasses.replace(base, world=MetaWorldConfig())
    assert named.stage_spec() == base.stage_spec()
    assert not {"world", "robot", "teleop", "operator", "display_data"} & set(base.stage_spec())
    assert "epochs" in base.stage_spec()
    assert dataclasses.replace(base, epochs=base.epochs + 1).stage_spec() != base.stage_spec()


def test_rsft_mixes_in_the_pipelines_own_demonstrations(tiny_config, tmp_path):
    with open(tiny_config) as f:
        cfg = draccus.load(PipelineConfig, f)
    assert Pipeline(cfg).rsft_config(None).demos_root is None  # the paper's fine-tune: the buffer alone
    mixing = dataclasses.replace(cfg, rsft=dataclasses.replace(cfg.rsft, demo_fraction=0.5))
    rsft = Pipeline(mixing).rsft_config(None)
    assert (rsft.demos_root, rsft.demos_repo_id) == (tmp_path / "run" / "demos", cfg.demos.repo_id)


class CountingStage:
    """A stage whose output is a directory and whose spec is ``{"spo": settings}``, as SPO's."""

    name, redo_on_change, grows = "spo", False, ("spo.iterations",)

    def __init__(self, out: Path, **settings: int) -> None:
        self.out, self.settings, self.runs = out, settings, 0

    def spec(self) -> dict:
        return {"spo": self.settings}

    def output(self) -> Path:
        return self.out

    def complete(self) -> bool:
        return self.out.is_dir()

    def run(self) -> dict:
        self.runs += 1
        self.out.mkdir(exist_ok=True)
        return dict(self.settings)


def test_more_iterations_continue_a_finished_stage_and_any_other_change_is_refused(tiny_config, tmp_path, capsys):
    from lerobot_cso.cso.spo import SPOStage
    from lerobot_cso.errors import UsageError

    assert SPOStage.grows == ("spo.iterations",)
    with open(tiny_config) as f:
        runner = Pipeline(draccus.load(PipelineConfig, f))
    out = tmp_path / "spo"
    first = CountingStage(out, iterations=10, lr=1)
    runner.execute(first)
    runner.execute(first)
    assert first.runs == 1  # complete under the same spec: skipped
    longer = CountingStage(out, iterations=20, lr=1)
    assert runner.execute(longer) == {"iterations": 20, "lr": 1} and longer.runs == 1
    assert "[pipeline] spo: continuing (spo.iterations: 10 → 20)" in capsys.readouterr().out
    for changed in ({"iterations": 15, "lr": 1}, {"iterations": 30, "lr": 2}):
        with pytest.raises(UsageError, match="was made with other settings or inputs"):
            runner.execute(CountingStage(out, **changed))


def test_a_record_made_before_a_setting_existed_matches_that_settings_behave_as_before_value(tiny_config, tmp_path):
    """An output recorded before ``advantage_weighted`` existed resumes under a spec holding its default (False)
    and is refused under any other value, the change named."""
    from lerobot_cso.errors import UsageError
    from lerobot_cso.stage import ADDED_SETTINGS

    assert ADDED_SETTINGS["advantage_weighted"] is False
    with open(tiny_config) as f:
        runner = Pipeline(draccus.load(PipelineConfig, f))
    out = tmp_path / "spo"
    runner.execute(CountingStage(out, iterations=10))
    later = CountingStage(out, iterations=10, advantage_weighted=False)
    assert runner.execute(later) == {"iterations": 10} and later.runs == 0  # the old record's summary: skipped
    with pytest.raises(UsageError, match=r"\(spo.advantage_weighted: None → True\)"):
        runner.execute(CountingStage(out, iterations=10, advantage_weighted=True))
    longer = CountingStage(out, iterations=20, advantage_weighted=False)
    assert runner.execute(longer)["iterations"] == 20 and longer.runs == 1  # still continues


ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mw_proxy():
    """``benchmarks/mw_proxy.py`` as a module, its folder on ``sys.path`` as when it runs (it imports ``harness``)."""
    with benchmark_module("mw_proxy") as module:
        yield module


def test_committed_mw_proxy_results_resume_with_their_own_config(mw_proxy):
    """benchmarks/results/mw_proxy.json resumes from configs/mw_proxy.yaml (the driver's default: the demo's config
    with --rsft.successes_per_task=200 --rsft.advantage_weighted=true, nothing else), mw_proxy_demo.json from the
    demo's config, mw_proxy_n200.json from it with --rsft.successes_per_task=200, mw_proxy_s7.json from
    configs/mw_proxy_s7.yaml and mw_vision.json from configs/metaworld_vision.yaml: each recorded config is that
    file's spec (settings added later, at their behave-as-before values, left out); another config is refused; a
    resuming command is appended to the file's commands, its latest one is not repeated."""
    parse = functools.cache(lambda name, overrides: mw_proxy.pipeline_config(ROOT / "configs" / name, list(overrides)))

    def config(name: str, *overrides: str, **changes) -> dict:
        cfg = dataclasses.replace(parse(name, overrides), **changes)
        return json.loads(json.dumps(mw_proxy.config_spec(cfg), default=str))

    n200, adv = "--rsft.successes_per_task=200", "--rsft.advantage_weighted=true"
    assert config("mw_proxy.yaml") == config("metaworld_demo.yaml", n200, adv)

    for results, own, others, seeds in (
        (
            "mw_proxy.json",
            config("mw_proxy.yaml"),
            [config("metaworld_demo.yaml"), config("metaworld_demo.yaml", n200), config("metaworld_demo.yaml", adv)],
            5,
        ),
        (
            "mw_proxy_demo.json",
            config("metaworld_demo.yaml"),
            [
                config("metaworld_demo.yaml", train_threads=1),
                config("mw_proxy_s7.yaml"),
                config("metaworld_demo.yaml", n200),
                config("mw_proxy.yaml"),
            ],
            5,
        ),
        ("mw_proxy_n200.json", config("metaworld_demo.yaml", n200), [config("metaworld_demo.yaml")], 5),
        (
            "mw_proxy_s7.json",
            config("mw_proxy_s7.yaml"),
            [config("mw_proxy_s7.yaml", train_threads=2), config("metaworld_demo.yaml")],
            3,
        ),
    ):
        path = ROOT / "benchmarks" / "results" / results
        loaded = mw_proxy.load(path, "test", own)
        # every method on every seed, but cso_no_freeze: the files predate it (added with the camera benchmark)
        expected = dict.fromkeys(mw_proxy.METHODS, seeds) | {"cso_no_freeze": 0}
        assert {m: len(e["per_seed"]) for m, e in loaded["methods"].items()} == expected
        last = loaded["command"].split("; ")[-2]  # the file's latest command, then this one appended
        assert loaded["command"] == json.loads(path.read_text())["command"] + "; test"
        assert mw_proxy.load(path, last, own)["command"] == json.loads(path.read_text())["command"]
        for other in others:
            with pytest.raises(SystemExit, match="holds results of another config"):
                mw_proxy.load(path, "test", other)
    # The camera benchmark's results resume from configs/metaworld_vision.yaml, not from the demo's smaller budget.
    vision = ROOT / "benchmarks" / "results" / "mw_vision.json"
    assert mw_proxy.load(vision, "test", config("metaworld_vision.yaml"))["methods"]["cso"]["per_seed"]
    with pytest.raises(SystemExit, match="holds results of another config"):
        mw_proxy.load(vision, "test", config("metaworld_vision_demo.yaml"))
    # Settings given on the command line over --config reach the config.
    assert mw_proxy.pipeline_config(ROOT / "configs" / "metaworld_demo.yaml", [n200]).rsft.successes_per_task == 200


def test_one_seeds_methods_are_paired_on_the_episodes_both_ran_from_the_same_states(mw_proxy):
    """With one training seed there is no CI over seeds; the evaluation's own noise is the paired difference over
    the episodes two methods ran from the same initial states (hand count: differences 1, 0, 0, 1 over the four
    shared episodes; s = √(1/3); half width 1.96 · s / 2)."""
    results = {"methods": {
        "rsft": {"outcomes_per_seed": {"0": {"t/0/0": 1, "t/0/1": 1, "t/0/2": 0, "t/0/3": 1}}},
        "il": {"outcomes_per_seed": {"0": {"t/0/0": 0, "t/0/1": 1, "t/0/2": 0, "t/0/3": 0, "t/0/4": 1}}},
        "cso": {},
    }}  # fmt: skip
    d = mw_proxy.paired_episodes(results, "rsft", "il")["0"]
    half = 1.96 * (1 / 3) ** 0.5 / 2
    assert d["episodes"] == 4 and d["mean"] == 0.5 and d["ci95"] == pytest.approx([0.5 - half, 0.5 + half])
    assert mw_proxy.paired_episodes(results, "cso", "il") is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--rsft.nosuch=1"], "mw_proxy.py: error: unrecognized arguments: --rsft.nosuch=1"),
        (["--config=configs/nosuch.yaml"], "mw_proxy.py: error: no config file configs/nosuch.yaml"),
        (
            ["--methods=il,nosuch"],
            "mw_proxy.py: error: unknown methods ['nosuch']; known: il, rsft, spo_only, cso, cso_no_freeze, token, "
            "trajectory, ript",
        ),
        (
            ["--stop_after=eval_cso"],
            "mw_proxy.py: error: stop_after must be one of demos, il, eval_il, rsft, eval_rsft, spo or null, got "
            "'eval_cso'",
        ),
    ],
)
def test_mw_proxy_bad_input_is_one_error_line_after_its_usage(mw_proxy, monkeypatch, capsys, tmp_path, args, message):
    """A bad setting over --config is the driver's own usage and one error line, not draccus's every option, and
    writes no results file."""
    results = tmp_path / "results.json"
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", ["mw_proxy.py", f"--results={results}", f"--work={tmp_path}", *args])
    with pytest.raises(SystemExit) as exit_:
        mw_proxy.main()
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and err[0].startswith("usage: mw_proxy.py") and err[-1] == message
    assert len(err) <= 3 and not results.exists()


def test_mw_proxy_stopped_records_the_evaluations_done_and_the_same_command_continues(mw_proxy, tmp_path, monkeypatch):
    """With --stop_after, a seed's pipeline records what it evaluated (here IL: overall and per task) and its stage
    times, and leaves the other methods to the same command without it, which then records them."""
    il = {"task-a": {"mean": 0.5}, "task-b": {"mean": 0.0}, "overall": {"mean": 0.25}}
    rows = {"il": il, "rsft": {"overall": {"mean": 0.5}}, "cso": {"overall": {"mean": 0.75}}}
    ran: list[str | None] = []

    class Stopped:  # the pipeline of one seed, stopped after IL's evaluation or run to its end
        def __init__(self, cfg: PipelineConfig) -> None:
            self.cfg = cfg

        def evaluated(self, method: str, successes: list[bool]) -> None:  # eval.json's episodes, as eval writes it
            episodes = [{"seed": 0, "task": "task-a", "init_seed": i, "success": s} for i, s in enumerate(successes)]
            folder = self.cfg.output_dir / "eval" / method
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "eval.json").write_text(json.dumps({"episodes": episodes}))

        def run(self) -> dict:
            ran.append(self.cfg.stop_after)
            seconds = {"demos": 1.0, "il": 2.0, "eval_il": 3.0}
            self.evaluated("il", [True, False])
            if self.cfg.stop_after == "eval_il":
                return {"stopped_after": "eval_il", "stage_seconds": seconds, "success_rate": {"il": rows["il"]}}
            self.evaluated("rsft", [True, True])
            self.evaluated("cso", [True, True])
            (self.cfg.output_dir / "rsft" / "collection.json").parent.mkdir(parents=True)
            (self.cfg.output_dir / "rsft" / "collection.json").write_text(json.dumps({"task-a": {"kept": 1}}))
            spo = self.cfg.output_dir / "spo"
            spo.mkdir(parents=True)
            (spo / "log.jsonl").write_text(
                json.dumps({"success_rate": 0.5, "clip_fraction": 0.1, "approx_kl": 0.0, "rejection_rate": 0.0}) + "\n"
            )
            return {"stage_seconds": seconds | {"spo": 4.0}, "success_rate": rows, "checkpoints": {}}

    monkeypatch.setattr(mw_proxy, "Pipeline", Stopped)
    cfg = mw_proxy.pipeline_config(ROOT / "configs" / "metaworld_demo.yaml", [])
    path = tmp_path / "results.json"
    results = mw_proxy.load(path, "test", mw_proxy.config_spec(cfg))
    stopped = dataclasses.replace(cfg, stop_after="eval_il")
    mw_proxy.run_seed(stopped, 0, tmp_path, results, path, ("il", "rsft", "cso"))
    saved = json.loads(path.read_text())
    assert {m: e["per_seed"] for m, e in saved["methods"].items() if e["per_seed"]} == {"il": {"0": 0.25}}
    assert saved["methods"]["il"]["mean"] == 0.25 and saved["stage_seconds"]["0"]["eval_il"] == 3.0
    assert saved["methods"]["il"]["per_task_per_seed"] == {"0": {"task-a": 0.5, "task-b": 0.0}}
    mw_proxy.run_seed(cfg, 0, tmp_path, results, path, ("il", "rsft", "cso"))
    saved = json.loads(path.read_text())
    assert {m: saved["methods"][m]["per_seed"] for m in rows} == {
        m: {"0": r["overall"]["mean"]} for m, r in rows.items()
    }
    assert saved["stage_seconds"]["0"]["spo"] == 4.0 and ran == ["eval_il", None]
    assert saved["methods"]["rsft"]["outcomes_per_seed"] == {"0": {"task-a/0/0": 1, "task-a/0/1": 1}}
    paired = saved["rsft_minus_il_per_seed_episodes"]["0"]  # differences 0, 1: s = √0.5, half width 1.96 · s / √2
    assert (paired["mean"], paired["episodes"]) == (0.5, 2) and paired["ci95"] == pytest.approx([0.5 - 0.98, 1.48])
    assert saved["rsft_collection"] == {"0": {"task-a": {"kept": 1}}}
    mw_proxy.run_seed(cfg, 0, tmp_path, results, path, ("il", "rsft", "cso"))  # complete: nothing runs
    assert ran == ["eval_il", None]
