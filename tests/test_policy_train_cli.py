"""`lerobot-train --policy.type=cso` as a real subprocess: both phases, checkpoint, resume, staging, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from safetensors.torch import load_file
from tiny_data import TINY_POLICY_ARGS, make_synthetic_dataset

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}


def train(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [str(BIN / "lerobot-train"), "--batch_size=8", "--num_workers=0", "--log_freq=1", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"lerobot-train failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def logged_steps(proc: subprocess.CompletedProcess) -> dict[int, str]:
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if " step:" in line]
    return {int(line.split(" step:")[1].split()[0]): line for line in lines}


@pytest.fixture(scope="module")
def two_phase_run(synthetic_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("train") / "run"
    proc = train(
        "--policy.type=cso",
        "--dataset.repo_id=local/synthetic",
        f"--dataset.root={synthetic_dataset}",
        f"--output_dir={out}",
        "--steps=6",
        "--save_freq=3",
        "--policy.n_autoencoder_steps=3",
        *TINY_POLICY_ARGS,
    )
    return out, proc


def test_one_run_trains_both_phases_and_checkpoints(two_phase_run):
    out, proc = two_phase_run
    steps = logged_steps(proc)
    assert all("phase:0.000" in steps[s] and "recon_l1" in steps[s] for s in (1, 2, 3))
    assert all("phase:1.000" in steps[s] and "nll:" in steps[s] for s in (4, 5, 6))
    model = out / "checkpoints" / "000006" / "pretrained_model"
    config = json.loads((model / "config.json").read_text())
    assert config["type"] == "cso"
    assert config["tasks"] == ["move the block left", "move the block right"]
    weights = load_file(model / "model.safetensors")
    assert int(weights["autoencoder_steps_done"]) == 3
    assert int(load_file(out / "checkpoints/000003/pretrained_model/model.safetensors")["autoencoder_steps_done"]) == 3


def test_resume_continues_in_the_prior_phase(synthetic_dataset, tmp_path):
    out = tmp_path / "run"
    common = [f"--dataset.root={synthetic_dataset}", "--dataset.repo_id=local/synthetic"]
    train(
        "--policy.type=cso",
        *common,
        f"--output_dir={out}",
        "--steps=4",
        "--save_freq=2",
        "--policy.n_autoencoder_steps=3",
        *TINY_POLICY_ARGS,
    )
    # Resume from step 2 (still phase 0, one autoencoder step left) — the phase buffer must carry over.
    (out / "checkpoints" / "last").unlink()
    (out / "checkpoints" / "last").symlink_to("000002")
    cfg = out / "checkpoints" / "000002" / "pretrained_model" / "train_config.json"
    proc = train("--resume=true", f"--config_path={cfg}", "--steps=5")
    steps = logged_steps(proc)
    assert sorted(steps) == [3, 4, 5]
    assert "phase:0.000" in steps[3]
    assert "phase:1.000" in steps[4] and "phase:1.000" in steps[5]


def test_stage_by_stage_with_policy_path(two_phase_run, synthetic_dataset, tmp_path):
    out, _ = two_phase_run
    stage1 = out / "checkpoints" / "000003" / "pretrained_model"
    proc = train(
        f"--policy.path={stage1}",
        "--policy.push_to_hub=false",
        "--policy.device=cpu",
        "--dataset.repo_id=local/synthetic",
        f"--dataset.root={synthetic_dataset}",
        f"--output_dir={tmp_path / 'stage2'}",
        "--steps=2",
    )
    steps = logged_steps(proc)
    assert "phase:1.000" in steps[1] and "phase:1.000" in steps[2]


def test_dataset_without_action_is_a_clear_error(tmp_path):
    root = tmp_path / "noaction"
    make_synthetic_dataset(root, episode_lengths=(10,), with_action=False)
    proc = train(
        "--policy.type=cso",
        "--dataset.repo_id=local/noaction",
        f"--dataset.root={root}",
        f"--output_dir={tmp_path / 'o'}",
        "--steps=1",
        *TINY_POLICY_ARGS,
        check=False,
    )
    assert proc.returncode != 0
    assert "the dataset has no 'action' feature" in proc.stderr + proc.stdout


def test_action_dim_differing_from_checkpoint_is_a_clear_error(two_phase_run, tmp_path):
    out, _ = two_phase_run
    root = tmp_path / "wide"
    make_synthetic_dataset(root, episode_lengths=(40,), action_dim=5)
    proc = train(
        f"--policy.path={out / 'checkpoints/000006/pretrained_model'}",
        "--policy.push_to_hub=false",
        "--dataset.repo_id=local/wide",
        f"--dataset.root={root}",
        f"--output_dir={tmp_path / 'o'}",
        "--steps=1",
        check=False,
    )
    assert proc.returncode != 0
    assert "feature 'action' has shape (5,) but the checkpoint was trained with (3,)" in proc.stderr + proc.stdout
