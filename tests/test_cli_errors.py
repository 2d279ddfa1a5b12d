"""Issue 35: every command refuses what it cannot honour, up front, with one ``error:`` line (exit 2).

Most checks run ``validate()`` or ``cli.main`` in this process (one CLI subprocess costs ~10 s of imports); a
subprocess is used only where the process itself is what is tested (its exit code on Ctrl-C, its start time).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import importlib
import importlib.util
import json
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from cso_fakes import TASKS, ScriptedEngine, mixed, save_tiny_metaworld_policy
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils import import_utils
from lerobot.utils.import_utils import get_safe_default_video_backend

import lerobot_policy_cso
from lerobot_cso import cli, records, rollout_stage
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso.rsft import RSFTConfig, run_rsft
from lerobot_cso.cso.spo import SPOConfig, SPOStage
from lerobot_cso.demos import DemosConfig
from lerobot_cso.durable import EpisodeJournal, output_lock, replace_dir
from lerobot_cso.errors import EnvWorkerError, UsageError, check_number
from lerobot_cso.evaluation import EvalConfig
from lerobot_cso.pipeline import Pipeline, PipelineConfig, policy_config
from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.robot.operator import OperatorConfig

NAN, INF = math.nan, math.inf


def stand_in_policy() -> CSOConfig:
    """A policy config that passes the stages' checks without any file (as the pipeline's stand-in)."""
    policy = CSOConfig(tasks=[task_description("reach-v3")], device="cpu")
    policy.pretrained_path = Path("/nonexistent/pretrained_model")
    return policy


def rollout_config(cls: type, **settings):
    return cls(**{"tasks": "reach-v3", "policy": stand_in_policy(), "output_dir": Path("/tmp/unused")} | settings)


@pytest.mark.parametrize("bad", [NAN, INF, -INF])
@pytest.mark.parametrize(
    ("make", "name"),
    [
        (lambda v: rollout_config(EvalConfig, sampling=Sampling(temperature=v)), "sampling.temperature"),
        (lambda v: rollout_config(SPOConfig, sampling=Sampling(temperature=v)), "sampling.temperature"),
        (lambda v: rollout_config(SPOConfig, lr=v), "lr"),
        (lambda v: rollout_config(SPOConfig, weight_decay=v), "weight_decay"),
        (lambda v: rollout_config(SPOConfig, grad_clip_norm=v), "grad_clip_norm"),
        (lambda v: rollout_config(SPOConfig, clip_low=v), "clip_low"),
        (lambda v: rollout_config(SPOConfig, clip_high=v), "clip_high"),
        (lambda v: rollout_config(SPOConfig, target_kl=v), "target_kl"),
        (lambda v: rollout_config(RSFTConfig, lr=v), "lr"),
        (lambda v: rollout_config(RSFTConfig, min_lr=v), "min_lr"),
        (lambda v: rollout_config(RSFTConfig, demo_fraction=v), "demo_fraction"),
        (lambda v: DemosConfig(tasks="reach-v3", noise_std=v), "noise_std"),
        (lambda v: OperatorConfig(episode_time_s=v), "operator.episode_time_s"),
        (lambda v: OperatorConfig(rest_time_s=v), "operator.rest_time_s"),
    ],
)
def test_nan_and_inf_settings_are_refused_before_any_work(make, name, bad):
    with pytest.raises(UsageError, match=rf"^{name} must be a finite number"):
        make(bad).validate()


@pytest.mark.parametrize(
    "name",
    [
        "temperature",
        "ae_dropout",
        "prior_dropout",
        "decoder_loss_scale",
        "optimizer_lr",
        "optimizer_min_lr",
        "optimizer_weight_decay",
        "optimizer_grad_clip_norm",
    ],
)
def test_the_policy_config_refuses_nan_in_every_float_setting(name):
    """``lerobot-train --policy.type=cso --policy.temperature=nan`` saved NaN into config.json."""
    with pytest.raises(ValueError, match=rf"^{name} must be a finite number"):
        CSOConfig(device="cpu", **{name: NAN})
    with pytest.raises(ValueError, match="optimizer_betas must be a finite number"):
        CSOConfig(device="cpu", optimizer_betas=(0.9, NAN))


def test_the_pipeline_refuses_nan_in_any_section_before_running(tmp_path):
    cfg = PipelineConfig(tasks="reach-v3", output_dir=tmp_path / "run")
    for section, settings in (("spo", {"lr": NAN}), ("rsft", {"min_lr": NAN}), ("demos", {"noise_std": NAN})):
        bad = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **settings)})
        with pytest.raises(UsageError, match=f"^{next(iter(settings))} must be a finite number"):
            Pipeline(bad)
    bad = dataclasses.replace(cfg, il=dataclasses.replace(cfg.il, policy={"temperature": "nan"}))
    with pytest.raises(UsageError, match="^il.policy: temperature must be a finite number"):
        Pipeline(bad)
    assert not (tmp_path / "run").exists()


def test_check_number_names_the_setting_its_bounds_and_the_value():
    check_number("x", 0.5, gt=0, lt=1)
    check_number("x", None, gt=0, optional=True)
    with pytest.raises(UsageError, match=r"^x must be a finite number >= 0 and < 1 \(or null\), got nan$"):
        check_number("x", NAN, ge=0, lt=1, optional=True)
    with pytest.raises(ValueError, match=r"^x must be a finite number > 0, got -1$"):
        check_number("x", -1, gt=0, error=ValueError)


@pytest.fixture(scope="module")
def two_policies(tmp_path_factory) -> tuple[Path, Path]:
    """Two tiny saved policies of the same shape with other weights."""
    root = tmp_path_factory.mktemp("policies")
    return tuple(save_tiny_metaworld_policy(root / f"policy{seed}" / "pretrained_model", seed) for seed in (0, 1))


def run_cli(args: list[str], capsys) -> tuple[int, str, str]:
    """``lerobot-cso ARGS`` in this process: exit code, stdout and the last stderr line."""
    code = cli.main(args)
    out, err = capsys.readouterr()
    return code, out, (err.strip().splitlines() or [""])[-1]


@pytest.fixture
def scripted_rollouts(monkeypatch):
    """Every stage rolls out on a ScriptedEngine (mixed outcomes) instead of MetaWorld."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.setattr(
        rollout_stage, "stage_engine", lambda policy, pre, post, cfg: ScriptedEngine(mixed, policy=policy)
    )


def test_standalone_spo_continues_only_what_it_can_honour(two_policies, tmp_path, capsys, scripted_rollouts):
    """Issue 35, item 1: a rerun of ``lerobot-cso spo`` with another policy, objective, K or lr, or fewer
    iterations, was resumed or called complete; now each difference is refused by name."""
    first, other = two_policies
    out = tmp_path / "spo"
    spo = ["spo", f"--tasks={','.join(TASKS)}", f"--output_dir={out}", "--groups_per_iteration=2", "--epochs=1"]
    spo += ["--minibatch_trajectories=4", "--lr=0.001"]
    assert run_cli([*spo, f"--policy.path={first}", "--group_size=4", "--iterations=1"], capsys)[0] == 0
    code, stdout, _ = run_cli([*spo, f"--policy.path={first}", "--group_size=4", "--iterations=1"], capsys)
    assert code == 0 and f"spo: complete, skipped ({out})" in stdout
    code, stdout, _ = run_cli([*spo, f"--policy.path={first}", "--group_size=4", "--iterations=2"], capsys)
    assert code == 0 and "spo: continuing (spo.iterations: 1 → 2)" in stdout
    refused = {
        ("--group_size=4", "--iterations=1"): "(spo.iterations: 2 → 1)",
        ("--group_size=3", "--iterations=3", "--objective=token"): "spo.group_size: 4 → 3, spo.iterations: 2 → 3, "
        "spo.objective: skill → token)",
    }
    for args, named in refused.items():
        code, _, err = run_cli([*spo, f"--policy.path={first}", *args], capsys)
        assert code == 2 and err.startswith(f"error: {out} was made with other settings or inputs (") and named in err
    code, _, err = run_cli([*spo, f"--policy.path={other}", "--group_size=4", "--iterations=3"], capsys)
    assert code == 2 and f"policy.path: {first.resolve()} → {other.resolve()}" in err
    assert "policy.weights_sha256" in err and "delete it or choose another --output_dir" in err
    assert json.loads((out / "stage.json").read_text())["summary"][-1]["iteration"] == 2


def test_policy_overrides_are_part_of_a_standalone_stages_record(two_policies, tmp_path, capsys, scripted_rollouts):
    """Issue 58, item 5: a finished stage was skipped, or an SPO run continued, under other ``--policy.*`` settings
    than it was made with, which were silently dropped; where the policy runs (``--policy.device``) binds nothing."""
    out = tmp_path / "spo"
    spo = ["spo", f"--policy.path={two_policies[0]}", f"--tasks={','.join(TASKS)}", f"--output_dir={out}"]
    spo += ["--groups_per_iteration=2", "--epochs=1", "--minibatch_trajectories=4", "--group_size=4", "--lr=0.001"]
    assert run_cli([*spo, "--iterations=1", "--policy.temperature=0.5"], capsys)[0] == 0
    code, _, err = run_cli([*spo, "--iterations=1"], capsys)
    assert code == 2 and "(policy.overrides.temperature: 0.5 → None)" in err, err
    code, _, err = run_cli([*spo, "--iterations=2", "--policy.temperature=0.7"], capsys)
    assert code == 2 and "policy.overrides.temperature: 0.5 → 0.7, spo.iterations: 1 → 2)" in err, err
    code, stdout, _ = run_cli([*spo, "--iterations=2", "--policy.temperature=0.5", "--policy.device=cpu"], capsys)
    assert code == 0 and "spo: continuing (spo.iterations: 1 → 2)" in stdout


def test_standalone_rsft_is_complete_only_for_the_same_settings_and_policy(
    two_policies, tmp_path, capsys, scripted_rollouts
):
    """A finished ``lerobot-cso rsft`` said "already complete" for any settings or policy."""
    first, other = two_policies
    out = tmp_path / "rsft"
    rsft = ["rsft", f"--tasks={','.join(TASKS)}", f"--output_dir={out}", "--successes_per_task=1", "--n_strikes=4"]
    rsft += ["--epochs=1", "--batch_size=8", "--lr=0.001", "--min_lr=0.0001"]
    assert run_cli([*rsft, f"--policy.path={first}"], capsys)[0] == 0
    code, stdout, _ = run_cli([*rsft, f"--policy.path={first}"], capsys)
    assert code == 0 and f"rsft: complete, skipped ({out})" in stdout
    code, _, err = run_cli([*rsft, f"--policy.path={first}", "--n_strikes=5"], capsys)
    assert code == 2 and "(rsft.n_strikes: 4 → 5)" in err
    code, _, err = run_cli([*rsft, f"--policy.path={other}"], capsys)
    assert code == 2 and f"policy.path: {first.resolve()} → {other.resolve()}" in err


def test_standalone_rsft_stopped_at_its_state_budget_continues_into_a_larger_one(
    two_policies, tmp_path, capsys, monkeypatch
):
    """An R-SFT that ran out of states (``max_states_per_task``) was refused when rerun with a larger budget, so
    its episodes were lost; now it continues from its journal, rolling out no state twice."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    engines: list[ScriptedEngine] = []

    def engine(policy, pre, post, cfg) -> ScriptedEngine:
        engines.append(ScriptedEngine(mixed, policy=policy))
        return engines[-1]

    monkeypatch.setattr(rollout_stage, "stage_engine", engine)
    first, _ = two_policies
    out = tmp_path / "rsft"
    rsft = ["rsft", f"--tasks={TASKS[0]}", f"--output_dir={out}", f"--policy.path={first}", "--successes_per_task=2"]
    rsft += ["--n_strikes=4", "--max_successes_per_state=1", "--stop_state_at_cap=true", "--states_per_round=1"]
    rsft += ["--epochs=1", "--batch_size=8", "--lr=0.001", "--min_lr=0.0001"]
    assert cli.main([*rsft, "--max_states_per_task=1"]) == 2  # one state keeps at most one success
    err = capsys.readouterr().err
    assert re.search(rf"\n(\r.*)?error: {TASKS[0]}: only [01] successes after 1 initial states;", err)
    tried = {s.seed for call in engines[0].calls for s in call}
    assert len(tried) == 1
    code, stdout, _ = run_cli([*rsft, "--max_states_per_task=8"], capsys)
    assert code == 0 and "rsft: continuing (rsft.max_states_per_task: 1 → 8)" in stdout
    assert not tried & {s.seed for call in engines[1].calls for s in call}  # the first state is not rolled again
    assert (out / "pretrained_model" / "config.json").is_file()
    code, _, err = run_cli([*rsft, "--max_states_per_task=4"], capsys)
    assert code == 2 and "(rsft.max_states_per_task: 8 → 4)" in err


def test_rsft_keeps_a_task_it_never_solves_short_and_refuses_to_pass_that_off_as_a_larger_budget(
    two_policies, tmp_path, capsys, monkeypatch
):
    """``--keep_short_tasks``: a task never solved within its state budget keeps no success and the run finishes on
    the others; the finished output is then not relabelled as a larger budget's, which would have tried more."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    engines: list[ScriptedEngine] = []

    def engine(policy, pre, post, cfg) -> ScriptedEngine:
        engines.append(ScriptedEngine(lambda task, seed, sample: task == TASKS[1], policy=policy))
        return engines[-1]

    monkeypatch.setattr(rollout_stage, "stage_engine", engine)
    out = tmp_path / "rsft"
    rsft = ["rsft", f"--tasks={','.join(TASKS)}", f"--output_dir={out}", f"--policy.path={two_policies[0]}"]
    rsft += ["--successes_per_task=1", "--n_strikes=2", "--states_per_round=1", "--keep_short_tasks=true"]
    rsft += ["--epochs=1", "--batch_size=8", "--lr=0.001", "--min_lr=0.0001"]
    code, stdout, _ = run_cli([*rsft, "--max_states_per_task=2"], capsys)
    assert code == 0 and f"R-SFT: {TASKS[0]} keeps 0 of 1 successes, its budget of 2 initial states" in stdout
    assert len({s.seed for call in engines[0].calls for s in call if s.task == TASKS[0]}) == 2
    report = json.loads((out / "collection.json").read_text())
    assert (report[TASKS[0]]["kept"], report[TASKS[0]]["states_tried"], report[TASKS[1]]["kept"]) == (0, 2, 1)
    code, _, err = run_cli([*rsft, "--max_states_per_task=3"], capsys)
    assert code == 2 and f"finished with {TASKS[0]} short of successes after 2 initial states" in err


def test_work_without_its_own_record_is_never_adopted(two_policies, tmp_path, capsys, scripted_rollouts):
    """Issue 58, item 1: an SPO or R-SFT output without its own record (made by the pipeline, or before the record
    existed) was continued or skipped under any policy and settings, and a pipeline adopted a standalone command's
    SPO checkpoint as its CSO result. Only an R-SFT collection whose journal holds this run's settings is adopted."""
    first, other = two_policies
    out = tmp_path / "run" / "spo"
    spo = ["spo", f"--tasks={','.join(TASKS)}", f"--output_dir={out}", "--groups_per_iteration=2", "--epochs=1"]
    spo += ["--minibatch_trajectories=4", "--lr=0.001", "--group_size=4", "--iterations=1"]
    assert run_cli([*spo, f"--policy.path={first}"], capsys)[0] == 0
    cfg = SPOConfig(tasks=",".join(TASKS), output_dir=out, policy=policy_config(first), iterations=1)
    with pytest.raises(UsageError, match=rf"^{out} holds the work of a stage run by its own command \({out}/stage"):
        records.run_recorded(SPOStage(cfg), tmp_path / "run" / "stages" / "spo.json", {}, "[pipeline] spo", "")
    (out / "stage.json").unlink()  # as the pipeline, or the code before the record, leaves it
    code, _, err = run_cli([*spo, f"--policy.path={other}", "--objective=token"], capsys)
    assert code == 2 and err.startswith(f"error: {out} holds work but no record of the settings, inputs and policy")
    assert f"({out / 'stage.json'} is missing" in err
    rsft = ["rsft", f"--tasks={','.join(TASKS)}", f"--policy.path={first}", "--successes_per_task=1", "--n_strikes=4"]
    rsft += ["--batch_size=8", "--lr=0.001", "--min_lr=0.0001"]
    made = tmp_path / "made"
    assert run_cli([*rsft, f"--output_dir={made}", "--epochs=1"], capsys)[0] == 0
    (made / "stage.json").unlink()
    code, _, err = run_cli([*rsft, f"--output_dir={made}", "--epochs=1"], capsys)
    assert code == 2 and err.startswith(f"error: {made} holds work but no record"), err
    reused = tmp_path / "reused"  # its collection alone, to be fine-tuned anew (benchmarks/twin_table5.py --reuse)
    for name in ("journal", "buffer", "collection.json"):
        (shutil.copytree if (made / name).is_dir() else shutil.copy)(made / name, reused / name)
    code, stdout, _ = run_cli([*rsft, f"--output_dir={reused}", "--epochs=2"], capsys)
    assert code == 0 and (reused / "pretrained_model" / "config.json").is_file(), stdout
    shutil.rmtree(reused / "pretrained_model")
    (reused / "stage.json").unlink()
    code, _, err = run_cli([*rsft, f"--output_dir={reused}", "--epochs=2", "--n_strikes=5"], capsys)
    assert code == 2 and err.startswith(f"error: {reused} holds work but no record"), err


def test_a_fresh_training_run_too_short_to_reach_the_prior_is_warned_about(caplog):
    """Issue 35, item 6: ``lerobot-train --policy.type=cso --steps=N`` with N <= n_autoencoder_steps trained no
    prior, silently; a run from a checkpoint (``--policy.path``, the stage-by-stage way) is not warned about."""
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    fresh = CSOConfig(device="cpu", n_autoencoder_steps=10).get_scheduler_preset()
    with caplog.at_level(logging.WARNING):
        fresh.build(optimizer, 20)
        assert not caplog.records
        fresh.build(optimizer, 10)
    assert "--steps=10 <= --policy.n_autoencoder_steps=10: this run trains only the skill autoencoder" in caplog.text
    caplog.clear()
    staged = CSOConfig(device="cpu", n_autoencoder_steps=10)
    staged.pretrained_path = Path("/some/checkpoint")
    with caplog.at_level(logging.WARNING):
        staged.get_scheduler_preset().build(optimizer, 5)
    assert not caplog.records
    with pytest.raises(ValueError, match="n_autoencoder_steps must be a finite number >= 0, got -1"):
        CSOConfig(device="cpu", n_autoencoder_steps=-1)


def test_ctrl_c_is_one_line_saying_where_it_stopped_and_how_to_resume(two_policies, tmp_path, capsys, monkeypatch):
    """Issue 35, item 7: Ctrl-C printed a 30-45-line KeyboardInterrupt traceback."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    crashing = lambda policy, pre, post, cfg: ScriptedEngine(mixed, crash_after=3, policy=policy)  # noqa: E731
    monkeypatch.setattr(rollout_stage, "stage_engine", crashing)
    out = tmp_path / "spo"
    code, _, err = run_cli(
        ["spo", f"--policy.path={two_policies[0]}", f"--tasks={','.join(TASKS)}", f"--output_dir={out}"], capsys
    )
    assert code == 130
    assert err == (
        f"interrupted: lerobot-cso spo stopped in stage spo, writing {out}; the work it finished is saved, and the "
        "same command resumes from it"
    )

    # Ctrl-C while the command still imports torch and LeRobot (seconds; minutes on a loaded machine): a traceback.
    def interrupted_import() -> None:
        raise KeyboardInterrupt

    with monkeypatch.context() as patched:
        patched.setattr(import_utils, "register_third_party_plugins", interrupted_import)
        code, _, err = run_cli(["eval", f"--policy.path={two_policies[0]}"], capsys)
    assert code == 130 and err.startswith("interrupted: lerobot-cso eval stopped; nothing is written")
    # An evaluation writes its output only at its end: the line said it resumed, and named no place.
    out = tmp_path / "eval"
    code, _, err = run_cli(
        ["eval", f"--policy.path={two_policies[0]}", f"--tasks={','.join(TASKS)}", f"--output_dir={out}"], capsys
    )
    assert code == 130
    assert err == (
        f"interrupted: lerobot-cso eval stopped in evaluating into {out}; nothing is written before it ends, so the "
        "same command starts it over"
    )


def test_a_value_of_the_wrong_type_is_one_error_line_and_exit_2(capsys, monkeypatch):
    """Issue 35, item 3: ``--episodes_per_task=abc`` exited 1 with draccus's message."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    code, _, err = run_cli(["demos", "--episodes_per_task=abc"], capsys)
    assert code == 2 and err.startswith("error: ") and "abc" in err


def test_help_and_a_misspelt_subcommand_import_neither_torch_nor_lerobot():
    """Issue 35, item 9: every lerobot-cso call, even --help, imported torch and LeRobot first (~8 s idle)."""
    code = (
        "import sys; from lerobot_cso import cli; assert cli.main(['--help']) == 0; assert cli.main(['demoz']) == 2; "
        "heavy = sorted(m for m in ('torch', 'lerobot.policies', 'metaworld') if m in sys.modules); print(heavy)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "[]"


def test_a_stages_help_and_an_unknown_option_answer_without_torch_once_the_help_is_kept(tmp_path, monkeypatch, capsys):
    """Issue 58, item 8: ``lerobot-cso spo --help``, a misspelt option and ``eval`` with no arguments took 6-8 s each
    (torch and LeRobot imported first); the help is now kept once made, the first two answer from it, and a missing
    ``--policy.path`` is said before the imports."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    assert cli.main(["spo", "--help"]) == 0  # made (here, where torch is imported already) and kept
    made = capsys.readouterr().out
    assert "--iterations int" in made and cli.help_cache("spo").read_text() == made
    code = (
        "import sys; from lerobot_cso import cli; assert cli.main(['spo', '--help']) == 0; "
        "assert cli.main(['spo', '--iteratoins=3', '--tasks=reach-v3']) == 2; assert cli.main(['eval']) == 2; "
        "print(sorted(m for m in ('torch', 'lerobot.configs', 'metaworld') if m in sys.modules), file=sys.stderr)"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], env=os.environ, capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0 and proc.stdout == made, proc.stderr
    assert proc.stderr.splitlines() == [
        "error: unrecognized arguments: --iteratoins=3",
        "error: --policy.path is required (a directory written by save_pretrained)",  # as validate() says it
        "[]",
    ]


def test_one_writer_per_output_dir_and_the_trainer_dies_with_its_pipeline(tmp_path):
    """Issue 35, item 5: two runs on one output dir crashed one of them; kill -9 of the pipeline left its
    lerobot-train child writing ``il/``."""
    out = tmp_path / "spo"
    with output_lock(out):  # a second opening of the lock file contends as another process's would
        with pytest.raises(UsageError, match=rf"^{out} is being written by another run \(pid {os.getpid()}: "):
            with output_lock(out):
                pass
    with output_lock(out):  # released with its holder
        pass
    (tmp_path / "a_file").write_text("not a directory")
    with (
        pytest.raises(UsageError, match="a_file is a file, not a directory$"),
        output_lock(tmp_path / "a_file" / "out"),
    ):
        pass
    parent = (
        "import sys; from lerobot_cso.il import run_tied; "
        "run_tied([sys.executable, '-c', 'import os, time; print(os.getpid(), flush=True); time.sleep(120)'], {})"
    )
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    child = int(proc.stdout.readline())
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    while alive(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive(child)


def test_the_lock_sees_through_links_and_into_a_pipelines_dir_and_leaves_no_file(tmp_path):
    """Issue 58, item 4: the lock was named from the path as given, so a symbolic link let two runs write one dir;
    a stage run alone could write inside a running pipeline's dir; refused runs left ``.lock`` files; and ``demos``
    into a link replaced it with a folder of its own and left ``<name>.old`` (``replace_dir``)."""
    real, link, pipeline = tmp_path / "real", tmp_path / "link", tmp_path / "pipeline"
    real.mkdir()
    link.symlink_to(real, target_is_directory=True)
    holder = rf"\(pid {os.getpid()}: "
    with output_lock(real):
        with pytest.raises(UsageError, match=rf"^{link} is being written by another run {holder}"), output_lock(link):
            pass
    with output_lock(pipeline):
        with pytest.raises(UsageError, match=rf"^{pipeline}/spo is inside {pipeline}, which is being written by"):
            with output_lock(pipeline / "spo"):
                pass
    with output_lock(pipeline / "spo"):
        with pytest.raises(UsageError, match=rf"^{pipeline} holds {pipeline}/spo, which is being written by"):
            with output_lock(pipeline):
                pass
    assert sorted(p.name for p in tmp_path.rglob("*.lock")) == []  # none left, by refused runs either
    (real / "old.txt").write_text("old")
    new = tmp_path / "link.partial" / "dataset"
    new.mkdir(parents=True)
    (new / "new.txt").write_text("new")
    replace_dir(new, link)
    assert link.is_symlink() and [p.name for p in real.iterdir()] == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "link.partial", "pipeline", "real"]


def test_ctrl_c_of_the_process_group_is_the_pipelines_to_report_not_its_trainers():
    """Issue 35, item 7: Ctrl-C reaches the whole process group; the pipeline's ``lerobot-train`` child printed its
    own KeyboardInterrupt traceback beside the pipeline's one line. The child now ignores it (it says so first:
    whether it prints before it is killed depends on the machine's load) and is killed."""
    child = "import signal, time; print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN, flush=True); time.sleep(120)"
    parent = (
        "import sys\nfrom lerobot_cso.il import run_tied\ntry:\n"
        f"    run_tied([sys.executable, '-c', {child!r}], {{}})\n"
        "except KeyboardInterrupt:\n    print('the parent alone reports it', file=sys.stderr)\n    sys.exit(130)\n"
    )
    # Session 38: once in a suite the parent ignored the Ctrl-C, waited out its child's 120 s and exited 0; SIGINT's
    # disposition and mask pass through fork and exec, so the parent starts as a shell starts a command, and a
    # failure says what this worker had.
    worker = (signal.getsignal(signal.SIGINT), signal.pthread_sigmask(signal.SIG_BLOCK, []))

    def as_from_a_shell() -> None:  # in the parent, before exec
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(
        [sys.executable, "-c", parent],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=as_from_a_shell,
    )
    ignores_ctrl_c = proc.stdout.readline()
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=300)  # a loaded 2-core VM starved the parent for over 60 s
    assert ignores_ctrl_c == "True\n"
    assert proc.returncode == 130 and err == "the parent alone reports it\n", f"the worker's SIGINT: {worker}"


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for init to reap it does not)."""
    try:
        return "\nState:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False


def test_what_would_fail_late_is_refused_before_any_work(two_policies, tmp_path, synthetic_dataset):
    """Issue 35, item 4: an output dir that is a file failed at the first write (eval lost its evaluation),
    ``spo --ratio_top_k=0`` after the rollouts, ``rsft --demos_root=<missing>`` after the whole collection."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    out = blocker / "out"
    for cls in (EvalConfig, RSFTConfig, SPOConfig):
        with pytest.raises(UsageError, match=f"^--output_dir={out}: {blocker} is a file, not a directory$"):
            rollout_config(cls, output_dir=out).validate()
    with pytest.raises(UsageError, match=f"^--output_dir={out}: {blocker} is a file"):
        DemosConfig(tasks="reach-v3", output_dir=out).validate()
    with pytest.raises(UsageError, match=f"^--output_dir={blocker}: {blocker} is a file"):
        Pipeline(PipelineConfig(tasks="reach-v3", output_dir=blocker))
    with pytest.raises(UsageError, match="^ratio_top_k must be a finite number >= 1 \\(or null\\), got 0$"):
        rollout_config(SPOConfig, ratio_top_k=0).validate()
    cfg = rollout_config(RSFTConfig, output_dir=tmp_path / "rsft", demo_fraction=0.5, demos_root=tmp_path / "none")
    cfg.policy.pretrained_path = two_policies[0]
    engines = []
    with pytest.raises(UsageError, match="--demos_root=.* is not a LeRobotDataset"):
        run_rsft(cfg, make_engine=lambda *args: engines.append(args) or ScriptedEngine(mixed))
    # Issue 58, item 2: demonstrations of another shape failed with a traceback after the whole collection.
    cfg = dataclasses.replace(
        cfg, demos_root=synthetic_dataset, demos_repo_id="local/synthetic", policy=policy_config(two_policies[0])
    )
    with pytest.raises(UsageError) as refused:
        run_rsft(cfg, make_engine=lambda *args: engines.append(args) or ScriptedEngine(mixed))
    assert str(refused.value).startswith(
        f"--demos_root={synthetic_dataset} does not fit the policy: it has 'observation.state' of shape (6,), the "
        "policy's is (39,), 'action' of shape (3,), the policy's is (4,), tasks the policy was not trained on ("
    )
    assert engines == []


def test_a_policy_of_another_action_size_is_refused_before_any_env(two_policies, tmp_path, capsys, scripted_rollouts):
    """Issue 58, item 3: ``eval`` / ``spo`` of a 3-d action policy on MetaWorld gave 48-112 lines of env worker
    tracebacks, and ``spo`` left its ``stage.json``."""
    policy = shutil.copytree(two_policies[0], tmp_path / "three_d" / "pretrained_model")
    config = json.loads((policy / "config.json").read_text())
    config["output_features"]["action"]["shape"] = [3]
    (policy / "config.json").write_text(json.dumps(config))
    for stage in ("eval", "spo"):
        out = tmp_path / stage
        code, _, err = run_cli([stage, f"--policy.path={policy}", f"--tasks={TASKS[0]}", f"--output_dir={out}"], capsys)
        assert code == 2 and err == (
            f"error: the policy's 'action' has shape (3,), metaworld's is (4,): --policy.path={policy} was trained "
            "for another world or robot"
        )
        assert not out.exists()
    with pytest.raises(UsageError, match=rf"^{policy}/model.safetensors does not fit the policy its config describes"):
        load_policy(policy)  # item 7: its weights are a 4-d action policy's


def test_impossible_sizes_and_places_are_refused_and_a_full_disk_is_named(two_policies, tmp_path, capsys, monkeypatch):
    """Issue 58, item 7: ``--num_envs`` had no upper bound, ``--output_dir=/`` and a ``videos`` path that is a file
    failed at their first write (after the whole evaluation), and a full disk (ENOSPC) was a traceback."""
    with pytest.raises(UsageError, match=r"^num_envs must be in \[1, 1024\], got 100000$"):
        rollout_config(EvalConfig, num_envs=100_000).validate()
    with pytest.raises(UsageError, match="^--output_dir=/ is the root of the file system"):
        rollout_config(SPOConfig, output_dir=Path("/")).validate()
    (tmp_path / "videos").write_text("a file")
    with pytest.raises(UsageError, match=f"^--video_episodes: its folder={tmp_path}/videos: .*videos is a file"):
        rollout_config(EvalConfig, output_dir=tmp_path, video_episodes=1).validate()

    def full_disk(*args) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "spo" / "state.tmp" / "optimizer.pt"))

    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.setattr(rollout_stage, "stage_engine", full_disk)
    code, _, err = run_cli(
        ["spo", f"--policy.path={two_policies[0]}", f"--tasks={TASKS[0]}", f"--output_dir={tmp_path / 'spo'}"], capsys
    )
    assert code == 1 and err == (
        f"error: lerobot-cso spo stopped: no space left on the device writing {tmp_path}/spo/state.tmp/optimizer.pt; "
        "free some and rerun: the work it finished is saved, and the same command resumes from it"
    )

    def failed_worker(*args) -> None:
        raise EnvWorkerError("env worker 1 failed: FileNotFoundError: [Errno 2] No such file or directory: 'x'")

    monkeypatch.setattr(rollout_stage, "stage_engine", failed_worker)
    code, _, err = run_cli(
        ["spo", f"--policy.path={two_policies[0]}", f"--tasks={TASKS[0]}", f"--output_dir={tmp_path / 'spo2'}"], capsys
    )
    assert code == 1 and err == (
        "error: lerobot-cso spo stopped: env worker 1 failed: FileNotFoundError: [Errno 2] No such file or directory: "
        "'x' (its traceback is above); the work it finished is saved, and the same command resumes from it"
    )


def damaged_copies(policy: Path, root: Path) -> dict[str, Path]:
    """Copies of a saved policy, each damaged in one way: name -> the policy dir."""
    copies = {}
    for name in ("truncated_weights", "empty_weights", "truncated_config", "no_preprocessor", "act_config"):
        copies[name] = shutil.copytree(policy, root / name / "pretrained_model")
    weights = copies["truncated_weights"] / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    (copies["empty_weights"] / "model.safetensors").write_bytes(b"")
    config = copies["truncated_config"] / "config.json"
    config.write_text(config.read_text()[:100])
    (copies["no_preprocessor"] / "policy_preprocessor.json").unlink()
    config = copies["act_config"] / "config.json"
    config.write_text(json.dumps(json.loads(config.read_text()) | {"type": "act"}))
    return copies


def test_damaged_or_foreign_inputs_are_one_line_naming_the_file(two_policies, tmp_path, capsys, scripted_rollouts):
    """Issue 35, item 3: a truncated or empty model.safetensors, a truncated config.json, a missing preprocessor,
    an ACT checkpoint and a corrupted stage record or journal episode each gave a traceback."""
    copies = damaged_copies(two_policies[0], tmp_path)
    expected = {
        "truncated_weights": f"error: {copies['truncated_weights'] / 'model.safetensors'} is damaged (",
        "empty_weights": f"error: {copies['empty_weights'] / 'model.safetensors'} is damaged (",
        "truncated_config": f"error: {copies['truncated_config'] / 'config.json'} is damaged (",
        "no_preprocessor": f"error: {copies['no_preprocessor'] / 'policy_preprocessor.json'} is missing",
        "act_config": f"error: --policy.path={copies['act_config']} is a 'act' policy; lerobot-cso post-trains cso",
    }
    for name, path in copies.items():
        code, _, err = run_cli(["eval", f"--policy.path={path}", f"--tasks={TASKS[0]}"], capsys)
        assert code == 2 and err.startswith(expected[name]), (name, err)
    out = tmp_path / "spo"
    out.mkdir()
    (out / "stage.json").write_text('{"spec": {"spo": ')
    spo = ["spo", f"--policy.path={two_policies[0]}", f"--tasks={','.join(TASKS)}", f"--output_dir={out}"]
    code, _, err = run_cli(spo, capsys)
    assert code == 2 and err.startswith(f"error: {out / 'stage.json'} is damaged (")
    episode = tmp_path / "journal" / "episodes" / "reach-v3" / "0000001.npz"
    episode.parent.mkdir(parents=True)
    episode.write_bytes(b"PK\x03\x04 cut short")
    with pytest.raises(UsageError, match=f"^{episode} is damaged"):
        EpisodeJournal.load(episode)


def test_eval_holds_its_output_dirs_lock_and_refuses_an_unwritable_one(
    two_policies, tmp_path, capsys, scripted_rollouts
):
    """Issue 35, items 4 and 5: a second ``eval`` on one output dir ran beside the first, and one that cannot be
    written (permission bits do not tell: root, a read-only mount) lost the whole evaluation at its first write."""
    out = tmp_path / "eval"
    evaluation = ["eval", f"--policy.path={two_policies[0]}", f"--tasks={TASKS[0]}", "--episodes_per_task=2"]
    with output_lock(out):
        code, _, err = run_cli([*evaluation, f"--output_dir={out}"], capsys)
    assert code == 2 and err.startswith(f"error: {out} is being written by another run (pid {os.getpid()}: ")
    unwritable = Path("/proc/lerobot_cso_eval")
    code, _, err = run_cli([*evaluation, f"--output_dir={unwritable}"], capsys)
    assert code == 2 and err.startswith(f"error: --output_dir={unwritable}: /proc is not writable (")


def test_an_empty_journal_takes_the_settings_of_a_corrected_command(tmp_path):
    """Issue 35, item 8: a robot that did not connect left an empty journal whose settings then refused the
    corrected command; a journal holding an episode is still refused."""
    root = tmp_path / "robot_journal"
    EpisodeJournal(root, {"fps": 10})
    journal = EpisodeJournal(root, {"fps": 20})
    assert json.loads((root / "spec.json").read_text()) == {"fps": 20}
    journal.save_episode("task", "0000000_001", {"success": np.bool_(True)})
    with pytest.raises(UsageError, match=f"^{root} holds a robot journal made with other settings"):
        EpisodeJournal(root, {"fps": 10}, what="a robot journal")


class FailingStage:
    """A checkpoint stage whose run opens its journal, saves ``episodes`` episodes, then fails (a robot that did
    not connect saves none)."""

    name, redo_on_change, grows = "rsft", False, ()

    def __init__(self, out: Path, episodes: int) -> None:
        self.out, self.episodes = out, episodes

    def output(self) -> Path:
        return self.out

    def complete(self) -> bool:
        return False

    def run(self) -> None:
        journal = EpisodeJournal(self.out / "robot_journal", {"fps": 30})
        for i in range(self.episodes):
            journal.save_episode("task", f"{i:07d}_001", {"success": np.bool_(True)})
        raise UsageError("robot piper_follower did not connect")


@pytest.mark.parametrize("episodes", [0, 1])
def test_a_stage_that_failed_before_any_work_binds_no_setting(tmp_path, episodes):
    """Issue 35, item 8: a standalone robot stage whose robot did not connect left ``stage.json``
    (``complete: false``), and its record refused a corrected command that changed a setting; once an episode
    exists, a changed setting is still refused."""
    out = tmp_path / "rsft"
    with pytest.raises(UsageError, match="did not connect"):
        records.run_recorded(FailingStage(out, episodes), out / "stage.json", {"n": 1}, "rsft", "delete it")
    if episodes:
        with pytest.raises(UsageError, match=r"was made with other settings or inputs \(n: 1 → 2\)"):
            records.run_recorded(FailingStage(out, 0), out / "stage.json", {"n": 2}, "rsft", "delete it")
    else:
        with pytest.raises(UsageError, match="did not connect"):
            records.run_recorded(FailingStage(out, 0), out / "stage.json", {"n": 2}, "rsft", "delete it")
        assert json.loads((out / "stage.json").read_text()) == {"spec": {"n": 2}, "complete": False}


def test_a_bad_config_file_or_a_damaged_staged_episode_or_log_is_one_line_naming_it(tmp_path, capsys, monkeypatch):
    """Issue 35, item 3: a missing, unreadable or malformed ``--config_path``, a damaged staged demo episode
    (``<output_dir>.partial/``), SPO ``log.jsonl`` and R-SFT ``collection.json`` each gave a traceback."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    broken, listing = tmp_path / "broken.yaml", tmp_path / "list.yaml"
    broken.write_text("tasks: [reach-v3\n  x: : :\n")
    listing.write_text("- reach-v3\n")
    cases = {
        tmp_path / "missing.yaml": ": No such file or directory",
        tmp_path: ": Is a directory",
        broken: " is not a valid config file (while parsing a flow sequence",
        listing: " must hold a mapping of settings (key: value), not a list",
    }
    for path, message in cases.items():
        code, _, err = run_cli(["eval", f"--config_path={path}"], capsys)
        assert code == 2 and err.startswith(f"error: --config_path={path}{message}"), err
    demos = DemosConfig(tasks="reach-v3", output_dir=tmp_path / "demos", episodes_per_task=1)
    staged = EpisodeJournal(tmp_path / "demos.partial", demos.spec())
    episode = staged.episode_path("reach-v3", "0000001")
    episode.parent.mkdir()
    episode.write_bytes(b"PK\x03\x04 cut short")
    code, _, err = run_cli(
        ["demos", "--tasks=reach-v3", f"--output_dir={demos.output_dir}", "--episodes_per_task=1"], capsys
    )
    assert code == 2 and err.startswith(f"error: {episode} is damaged ("), err
    log = tmp_path / "spo" / "log.jsonl"
    log.parent.mkdir()
    log.write_text('{"iteration": 1}\n{"iteration": 2, "succ')
    with pytest.raises(UsageError, match=f"^{log} is damaged"):
        SPOStage(rollout_config(SPOConfig, output_dir=log.parent)).history()
    report = tmp_path / "rsft" / "collection.json"  # read when the fine-tuned policy exists
    (report.parent / "pretrained_model").mkdir(parents=True)
    (report.parent / "pretrained_model" / "config.json").write_text("{}")
    report.write_text('{"tasks": {"reach-v3": ')
    with pytest.raises(UsageError, match=f"^{report} is damaged"):
        run_rsft(rollout_config(RSFTConfig, output_dir=report.parent))


def test_a_damaged_rsft_buffer_or_journal_episode_is_one_line_with_advice_that_holds(two_policies, tmp_path):
    """Issue 58, item 6: a truncated file of R-SFT's buffer gave a traceback, and a damaged journal episode said
    "delete it and the run redoes that episode", false for R-SFT (the rerun draws a new state: another checkpoint)."""
    out = tmp_path / "rsft"
    cfg = RSFTConfig(tasks=",".join(TASKS), output_dir=out, policy=policy_config(two_policies[0]))
    cfg = dataclasses.replace(cfg, successes_per_task=1, n_strikes=4, epochs=1, batch_size=8, lr=1e-3, min_lr=1e-4)
    engine = lambda *args: ScriptedEngine(mixed)  # noqa: E731
    run_rsft(cfg, make_engine=engine)
    before = LeRobotDataset(cfg.repo_id, root=out / "buffer").hf_dataset.to_pandas()
    for made in ("pretrained_model", "train_state"):  # as a run killed in its fine-tune leaves it
        shutil.rmtree(out / made)
    part = sorted((out / "buffer" / "data").rglob("*.parquet"))[0]
    part.write_bytes(part.read_bytes()[: part.stat().st_size // 2])
    with pytest.raises(UsageError) as damaged:
        run_rsft(cfg, make_engine=engine)
    assert re.fullmatch(
        f"{out / 'buffer'} is damaged \\(ArrowInvalid: .*\\); delete it and the rerun writes it again from "
        f"{out / 'journal'}, the same buffer",
        str(damaged.value),
    )
    shutil.rmtree(out / "buffer")  # as it advises
    run_rsft(cfg, make_engine=engine)
    assert LeRobotDataset(cfg.repo_id, root=out / "buffer").hf_dataset.to_pandas().equals(before)
    for made in ("pretrained_model", "train_state", "buffer"):
        shutil.rmtree(out / made)
    episode = sorted((out / "journal" / "episodes").rglob("*.npz"))[0]
    episode.write_bytes(episode.read_bytes()[:100])
    with pytest.raises(UsageError, match=f"^{episode} is damaged .*; R-SFT cannot redo one episode as it drew it: "):
        run_rsft(cfg, make_engine=engine)


def test_the_stateful_cli_tries_end_in_their_error_line_in_process(tmp_path, capsys, monkeypatch):
    """Issue 58, item 9: ``benchmarks/cli_tries.py`` held only bad command-line input, and ran outside the tests.
    Its stateful tries (rows 48-54: their states made as the script makes them, a lock held here where a try needs
    another run's) run here in process: each ends in its error line and exit code 2 (or 0 for ``--help``), without a
    traceback. The script runs them as processes."""
    script = Path(__file__).parents[1] / "benchmarks" / "cli_tries.py"
    spec = importlib.util.spec_from_file_location("cli_tries", script)
    cli_tries = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "cli_tries", cli_tries)  # its dataclasses look their module up
    spec.loader.exec_module(cli_tries)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.chdir(tmp_path)
    ran = 0
    for attempt in cli_tries.tries(tmp_path):
        if int(attempt.row) < 48:
            continue  # issue 35's bad command-line input, each tested above or in tests/hardware
        with output_lock(attempt.holds) if attempt.holds is not None else contextlib.nullcontext():
            code = cli.main(attempt.command[1:])
        err = capsys.readouterr().err
        assert "Traceback" not in err, (attempt.command, err)
        last = (err.strip().splitlines() or [""])[-1]
        assert code == (2 if attempt.error else 0) and last.startswith(attempt.error), (attempt.command, err)
        ran += 1
    assert ran == 12


def test_demos_of_tasks_without_an_expert_names_this_commands_flags():
    """Issue 35, item 9: ``lerobot-cso demos --tasks=libero_*`` suggested ``--demos.dataset_root``, the pipeline's."""
    with pytest.raises(
        UsageError, match="^LIBERO's scripted expert does .* with --dataset_root=<its folder> --repo_id="
    ):
        DemosConfig(tasks="libero_goal-0").validate()


def test_lerobots_torchcodec_probe_page_is_one_line_said_once(monkeypatch, caplog):
    """Issue 35, item 9: ``lerobot-train`` and ``piper-record`` opened with ~100 lines of libtorchcodec tracebacks
    (LeRobot's probe, at each of its calls, where FFmpeg is missing); the cso plugin, which both load, shortens it."""
    load = importlib.import_module

    def no_ffmpeg(name: str, *args):
        if name == "torchcodec":
            raise RuntimeError(
                "Could not load libtorchcodec. Likely causes:\n" + "Traceback (most recent call last):\n" * 30
            )
        return load(name, *args)

    monkeypatch.setattr(importlib, "import_module", no_ffmpeg)
    monkeypatch.setattr(lerobot_policy_cso.TORCHCODEC_PROBE, "said", False)
    monkeypatch.setattr(sys, "argv", ["lerobot-train", "--policy.type=cso"])
    with caplog.at_level(logging.WARNING, logger="lerobot.utils.import_utils"):
        assert get_safe_default_video_backend() == get_safe_default_video_backend() == "pyav"
    assert [r.getMessage() for r in caplog.records] == [
        "torchcodec cannot load here (no FFmpeg it supports): videos decode with pyav"
    ]
