"""Evaluation: ``lerobot-cso eval`` and ``lerobot-eval --env.type=cso_metaworld`` on a tiny trained policy,
the summary arithmetic, and bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from metaworld_fixtures import shared_policy

from lerobot_cso import cli, seeds
from lerobot_cso.evaluation import markdown_table, summarize

ENV = {**os.environ, "HF_HUB_OFFLINE": "1"}


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory) -> Path:
    return shared_policy(tmp_path_factory)


def test_summary_mean_and_std_over_seeds_hand_computed():
    rows = summarize({"a": {0: 0.5, 1: 1.0}, "b": {0: 0.0, 1: 0.5}})
    assert rows["a"]["mean"] == pytest.approx(0.75) and rows["a"]["std"] == pytest.approx(0.353553, abs=1e-6)
    assert rows["overall"]["per_seed"] == {"0": 0.25, "1": 0.75} and rows["overall"]["mean"] == pytest.approx(0.5)
    table = markdown_table(rows).splitlines()
    assert table[0] == "| task | seed 0 | seed 1 | mean ± std |"
    assert "| a | 50.0 | 100.0 | 75.0 ± 35.4 |" in table and "| **overall** | 25.0 | 75.0 | 50.0 ± 35.4 |" in table
    noisy = summarize({"a": {0: 0.5, 1: 1.0}, "b": {0: 0.0, 1: 0.5}}, episodes_per_task=8)
    # a: p = 0.75 over 16 episodes -> sqrt(0.75 * 0.25 / 16); b: p = 0.25, the same; overall: sqrt(2 se²) / 2
    assert noisy["a"]["se"] == pytest.approx(0.108253, abs=1e-6) and noisy["b"]["se"] == noisy["a"]["se"]
    assert noisy["overall"]["se"] == pytest.approx(0.108253 / 2**0.5, abs=1e-6)
    single = summarize({"a": {3: 0.4}})
    assert single["a"]["std"] is None and "| a | 40.0 | 40.0 |" in markdown_table(single)


def test_lerobot_cso_eval_writes_table_json_csv_png(policy_path, tmp_path):
    out = tmp_path / "eval"
    args = [
        f"--policy.path={policy_path}",
        "--tasks=reach-v3,button-press-v3",
        "--episodes_per_task=2",
        "--seeds=0,1",
        "--max_steps=24",
        "--num_envs=4",
        f"--output_dir={out}",
    ]
    proc = subprocess.run(
        [sys.executable, "-m", "lerobot_cso.cli", "eval", *args], env=ENV, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert "| task | seed 0 | seed 1 | mean ± std |" in lines
    assert any(line.startswith("| reach-v3 |") for line in lines)
    assert any(line.startswith("| **overall** |") for line in lines)
    record = json.loads((out / "eval.json").read_text())
    assert record["seeds"] == [0, 1] and record["sampling"] == {"temperature": 1.0, "top_k": 5, "greedy": False}
    assert set(record["success_rate"]) == {"reach-v3", "button-press-v3", "overall"}
    for s in (0, 1):
        used = {(e["task"], e["init_seed"]) for e in record["episodes"] if e["seed"] == s}
        assert used == {(t, i) for t in ("reach-v3", "button-press-v3") for i in seeds.eval_seeds(2, s)}
    assert all(e["init_seed"] in seeds.EVAL and e["length"] <= 24 for e in record["episodes"])
    csv_lines = (out / "eval.csv").read_text().splitlines()
    assert csv_lines[0] == "task,seed_0,seed_1,mean,std" and len(csv_lines) == 4
    assert (out / "eval.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_lerobot_eval_runs_the_cso_metaworld_env(policy_path, tmp_path):
    out = tmp_path / "lerobot_eval"
    lerobot_eval = Path(sys.executable).parent / "lerobot-eval"
    args = [
        f"--policy.path={policy_path}",
        "--env.type=cso_metaworld",
        "--env.task=reach-v3",
        "--env.episode_length=24",
        "--eval.n_episodes=2",
        "--eval.batch_size=2",
        f"--output_dir={out}",
    ]
    proc = subprocess.run([str(lerobot_eval), *args], env=ENV, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    info = json.loads((out / "eval_info.json").read_text())
    assert info["per_group"]["reach-v3"]["n_episodes"] == 2
    assert 0.0 <= info["overall"]["pc_success"] <= 100.0


def test_bad_input_is_one_clear_error(policy_path, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    out = tmp_path / "never"
    cases = {
        (): "error: --policy.path is required",
        ("--policy.path=/nonexistent/policy",): "is not a saved policy",
        (f"--policy.path={policy_path}", "--tasks=door-open-v3"): (
            "not trained on door-open-v3; it knows: 'Reach a goal position'; 'Press a button'"
        ),
        (f"--policy.path={policy_path}", "--tasks=reach-v3", "--seeds=0,x"): "seeds must be a comma list of integers",
        (f"--policy.path={policy_path}", "--tasks=reach-v3", "--episodes_per_task=0"): "episodes_per_task must be in",
        (f"--policy.path={policy_path}", "--tasks=nope-v3"): "unknown MetaWorld task 'nope-v3'",
    }
    for args, message in cases.items():
        assert cli.main(["eval", *args, f"--output_dir={out}"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("error: ") and message in err[-1], (args, err[-1])
    assert not out.exists()
