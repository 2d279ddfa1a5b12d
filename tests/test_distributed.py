"""SPO and R-SFT on two processes (accelerate launch, gloo on CPU) against one process, on scripted rollouts."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from cso_fakes import save_tiny_metaworld_policy
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso.rsft import SEED_KEY
from lerobot_cso.policy.configuration_cso import SKILL_START_KEY, SKILL_TOKENS_KEY

TESTS = Path(__file__).parent
ACCELERATE = Path(sys.executable).parent / "accelerate"
# The scripted episodes are seeded with hash(str): every process must hash alike.
ENV = {**os.environ, "PYTHONHASHSEED": "0", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(TESTS)}


def digests_of(out: Path, length: int, processes: int) -> Path:
    return out.with_name(out.name + f"_digests_{length}_{processes}")


def stage_run(stage: str, policy: Path, out: Path, length: int, processes: int) -> list[dict[str, torch.Tensor]]:
    """Run tests/distributed_stage.py on ``processes`` processes; returns each process's final weights."""
    digests = digests_of(out, length, processes)
    script = [str(TESTS / "distributed_stage.py"), stage, str(policy), str(out), str(length), str(digests)]
    launch = [str(ACCELERATE), "launch", "--multi_gpu", f"--num_processes={processes}", "--num_machines=1"]
    launch += ["--mixed_precision=no", "--dynamo_backend=no", "--main_process_port=0"]
    command = [*launch, *script] if processes > 1 else [sys.executable, *script]
    proc = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return [torch.load(digests / f"rank{r}.pt") for r in range(processes)]


@pytest.fixture(scope="module")
def frozen_policy(tmp_path_factory) -> Path:
    path = save_tiny_metaworld_policy(tmp_path_factory.mktemp("frozen") / "pretrained_model", seed=1)
    policy, _, _ = load_policy(path)
    policy.set_encoders_frozen(True)
    policy.save_pretrained(path)
    return path


def assert_same_step(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], start: dict[str, torch.Tensor]) -> None:
    """``a`` and ``b`` moved from ``start`` alike: per tensor within 2 % of the step. (Adam divides by the
    gradients' RMS, so float-order noise in a gradient that is zero in exact arithmetic, e.g. attention's key
    bias, becomes a visible step; the loss scale itself is checked through grad_norm.)"""
    assert a.keys() == b.keys()
    for key in a:
        step = (a[key] - start[key]).abs().max()
        torch.testing.assert_close(a[key], b[key], atol=float(0.02 * step) + 1e-7, rtol=0, msg=key)


def test_two_processes_take_the_one_process_step_and_write_once(frozen_policy, tmp_path):
    [single] = stage_run("spo", frozen_policy, tmp_path / "one", length=1, processes=1)
    rank0, rank1 = stage_run("spo", frozen_policy, tmp_path / "two", length=1, processes=2)
    assert all(torch.equal(rank0[k], rank1[k]) for k in rank0)  # the replicas are bit-identical
    before = load_policy(frozen_policy)[0].prior.state_dict()
    assert any(not torch.equal(before[k], single[k]) for k in single)  # the update did move the prior
    assert_same_step(rank0, single, before)  # the one-process update on the same groups
    saved = load_policy(tmp_path / "two" / "pretrained_model")[0].prior.state_dict()
    assert all(torch.equal(saved[k], rank0[k]) for k in rank0)
    one, two = ([json.loads(x) for x in (tmp_path / d / "log.jsonl").read_text().splitlines()] for d in ("one", "two"))
    assert len(two) == 1  # rank 0 alone wrote the log
    for key in ("success_rate", "rejection_rate", "episodes", "env_steps", "updates"):
        assert two[0][key] == one[0][key], key
    for key in ("loss", "clip_fraction", "approx_kl", "grad_norm"):
        assert two[0][key] == pytest.approx(one[0][key], rel=1e-4, abs=1e-7), key
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == ["log.jsonl", "pretrained_model", "spo.png", "state"]


def test_a_two_process_run_resumes_on_one_process(frozen_policy, tmp_path):
    [after_one] = stage_run("spo", frozen_policy, tmp_path / "resumed", length=1, processes=2)[:1]
    [resumed] = stage_run("spo", frozen_policy, tmp_path / "resumed", length=2, processes=1)
    stage_run("spo", frozen_policy, tmp_path / "straight", length=2, processes=1)
    assert any(not torch.equal(after_one[k], resumed[k]) for k in resumed)  # iteration 2 trained on top
    logs, progress = {}, {}
    for name in ("resumed", "straight"):
        logs[name] = [json.loads(x) for x in (tmp_path / name / "log.jsonl").read_text().splitlines()]
        progress[name] = json.loads((tmp_path / name / "state" / "progress.json").read_text())
    # The same states were drawn whatever the number of processes (outcomes depend only on the state here).
    assert progress["resumed"]["cursor"] == progress["straight"]["cursor"] and len(logs["resumed"]) == 2
    for key in ("success_rate", "rejection_rate", "episodes", "env_steps"):
        assert [r[key] for r in logs["resumed"]] == [r[key] for r in logs["straight"]], key


def test_rsft_on_two_processes_keeps_every_success_once_and_identical_replicas(frozen_policy, tmp_path):
    rank0, rank1 = stage_run("rsft", frozen_policy, tmp_path / "rsft", length=2, processes=2)
    assert all(torch.equal(rank0[k], rank1[k]) for k in rank0)  # data-parallel fine-tune: same replicas
    before = load_policy(frozen_policy)[0].state_dict()
    assert any(not torch.equal(before[k], rank0[k]) for k in rank0)
    saved = load_policy(tmp_path / "rsft" / "pretrained_model")[0].state_dict()
    assert all(torch.equal(saved[k], rank0[k]) for k in rank0)
    report = json.loads((tmp_path / "rsft" / "collection.json").read_text())
    assert {task: r["kept"] for task, r in report.items()} == dict.fromkeys(report, 3) and len(report) == 2
    files = sorted((tmp_path / "rsft" / "journal" / "episodes").glob("*/*.npz"))
    assert len({(f.parent.name, f.name) for f in files}) == len(files) == 6  # each kept success once
    assert json.loads((tmp_path / "rsft" / "train_state" / "progress.json").read_text()) == {"epochs_done": 2}


def test_advantage_weighted_rsft_on_two_processes_shards_the_weighted_draws(frozen_policy, tmp_path):
    rank0, rank1 = stage_run("rsft_adv", frozen_policy, tmp_path / "adv", length=2, processes=2)
    assert all(torch.equal(rank0[k], rank1[k]) for k in rank0)
    drawn = [torch.load(digests_of(tmp_path / "adv", 2, 2) / f"drawn_rank{r}.pt") for r in (0, 1)]
    table = LeRobotDataset("local/cso_rsft_buffer", root=tmp_path / "adv" / "buffer").hf_dataset.with_format("numpy")[:]
    starts = table[SKILL_START_KEY].reshape(-1) == 1
    decisions = zip(table[SKILL_TOKENS_KEY][starts].tolist(), table[SEED_KEY][starts].reshape(-1), strict=True)
    seed_of = {tuple(tokens): int(seed) for tokens, seed in decisions}
    # Per task: 2 successes of an odd seed (2 of 4 attempts: Eq. 8 advantage 0.5) and 1 of a seed solved on every
    # attempt (advantage 0), 3 decisions each: 18 decisions, 12 of them with weight.
    assert len(seed_of) == 18 and sum(s % 2 for s in seed_of.values()) == 12
    for tokens in drawn:  # each process draws its share of each epoch's 18, only from the weighted decisions
        assert len(tokens) == 2 * 3 * 4  # 5 batches of 4 split over 2 processes: 3 each (accelerate evens them)
        assert all(seed_of[tuple(t)] % 2 == 1 for t in tokens.tolist())
    assert not torch.equal(drawn[0], drawn[1])  # the shards differ: not one draw made twice
