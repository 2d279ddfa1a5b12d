"""R-SFT: N-strikes collection with state switching, durability across a crash, the LeRobotDataset buffer,
Eq. 6 fine-tuning with frozen-encoder checkpoint, and pushing the buffer to a stand-in Hub."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from cso_fakes import TASKS, ScriptedEngine, TorchWhereCudaIsAvailable, save_tiny_metaworld_policy
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.scripts import lerobot_train
from tiny_data import make_synthetic_dataset

from lerobot_cso import distributed
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso import rsft
from lerobot_cso.errors import UsageError
from lerobot_cso.policy.configuration_cso import SKILL_START_KEY, SKILL_STEP_KEY, SKILL_TOKENS_KEY
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.tasks import task_description

S = 1_000_000  # first R-SFT initial-state seed
OUTCOMES = {  # (task, seed) -> samples that succeed
    ("reach-v3", S): set(),
    ("reach-v3", S + 1): {1, 3},
    ("reach-v3", S + 2): {0, 1, 2, 3},
    ("reach-v3", S + 3): {0},
    ("button-press-v3", S): {2},
    ("button-press-v3", S + 1): set(),
    ("button-press-v3", S + 2): {0, 1, 2, 3},
    ("button-press-v3", S + 3): set(),
}
EXPECTED_FILES = {
    "reach-v3": ["1000001_001", "1000001_003", "1000002_000"],
    "button-press-v3": ["1000000_002", "1000002_000", "1000002_001"],
}
# Hand count: reach tried 4 states x 4 attempts, saw 0+2+4+1 successes, kept 3, struck out on S.
EXPECTED_REPORT = {
    "reach-v3": {"rollouts": 16, "successes": 7, "kept": 3, "states_tried": 4, "states_struck_out": 1},
    "button-press-v3": {"rollouts": 16, "successes": 5, "kept": 3, "states_tried": 4, "states_struck_out": 2},
}


def outcome(task: str, seed: int, sample: int) -> bool:
    return sample in OUTCOMES[(task, seed)]


@pytest.fixture(scope="module")
def il_policy(tmp_path_factory) -> Path:
    return save_tiny_metaworld_policy(tmp_path_factory.mktemp("il") / "pretrained_model")


def make_cfg(il_policy: Path, out: Path, **kw) -> rsft.RSFTConfig:
    settings = dict(successes_per_task=3, n_strikes=4, states_per_round=2, epochs=10, batch_size=8, lr=1e-3)
    cfg = rsft.RSFTConfig(tasks=",".join(TASKS), output_dir=out, min_lr=1e-4, **(settings | kw))
    cfg.policy = load_policy(il_policy)[0].config
    cfg.policy.pretrained_path = il_policy
    return cfg


def kept_files(journal: rsft.Journal) -> dict[str, list[str]]:
    return {t: [p.stem for p in journal.episode_files(t)] for t in TASKS}


@pytest.fixture(scope="module")
def collected(il_policy, tmp_path_factory):
    cfg = make_cfg(il_policy, tmp_path_factory.mktemp("rsft") / "out")
    journal = rsft.Journal(cfg.output_dir / "journal", cfg.spec())
    engine = ScriptedEngine(outcome)
    rsft.collect(cfg, list(TASKS), engine, journal)
    return cfg, journal, engine


def test_n_strikes_keeps_successes_and_switches_states(collected):
    cfg, journal, engine = collected
    assert kept_files(journal) == EXPECTED_FILES
    assert rsft.collection_report(journal, list(TASKS)) == EXPECTED_REPORT
    # Two rounds of two new states per unfinished task; every state is one group of n_strikes attempts.
    assert [[(s.task, s.seed) for s in call] for call in engine.calls] == [
        [("reach-v3", S), ("reach-v3", S + 1), ("button-press-v3", S), ("button-press-v3", S + 1)],
        [("reach-v3", S + 2), ("reach-v3", S + 3), ("button-press-v3", S + 2), ("button-press-v3", S + 3)],
    ]


@pytest.mark.parametrize(
    ("cap", "expected"),
    [
        (None, {"reach-v3": ["1000001_001", "1000001_003"], "button-press-v3": ["1000000_002", "1000002_000"]}),
        (1, {"reach-v3": ["1000001_001", "1000002_000"], "button-press-v3": ["1000000_002", "1000002_000"]}),
    ],
)
def test_a_cap_per_state_spreads_the_successes_over_more_states(il_policy, tmp_path, cap, expected):
    # Two successes per task: uncapped, reach's S + 1 gives both; capped at one, the second comes from S + 2
    # (round 2 tries S + 2 and S + 3: 0 + 2 + 4 + 1 successes seen).
    cfg = make_cfg(il_policy, tmp_path / "out", successes_per_task=2, max_successes_per_state=cap)
    journal = rsft.Journal(cfg.output_dir / "journal", cfg.spec())
    rsft.collect(cfg, list(TASKS), ScriptedEngine(outcome), journal)
    assert kept_files(journal) == expected
    assert rsft.collection_report(journal, list(TASKS))["reach-v3"]["successes"] == (2 if cap is None else 7)


def test_crash_mid_collection_then_rerun_loses_and_duplicates_nothing(il_policy, tmp_path):
    cfg = make_cfg(il_policy, tmp_path / "out")
    journal = rsft.Journal(cfg.output_dir / "journal", cfg.spec())
    with pytest.raises(KeyboardInterrupt):  # dies after 10 finished episodes of the first round
        rsft.collect(cfg, list(TASKS), ScriptedEngine(outcome, crash_after=10), journal)
    assert kept_files(journal)["reach-v3"] == ["1000001_001", "1000001_003"]  # durable the moment they finished
    assert rsft.collection_report(journal, list(TASKS))["reach-v3"]["states_tried"] == 0
    rsft.collect(cfg, list(TASKS), ScriptedEngine(outcome), rsft.Journal(cfg.output_dir / "journal", cfg.spec()))
    assert kept_files(journal) == EXPECTED_FILES
    assert rsft.collection_report(journal, list(TASKS)) == EXPECTED_REPORT


def test_a_journal_with_other_settings_is_refused(il_policy, tmp_path):
    assert "stop_state_at_cap" not in make_cfg(il_policy, tmp_path).spec()  # as journals made before it existed
    assert make_cfg(il_policy, tmp_path, stop_state_at_cap=True).spec()["stop_state_at_cap"] is True
    other = make_cfg(il_policy, tmp_path, sampling=Sampling(temperature=0.7)).spec()
    rsft.Journal(tmp_path / "journal", make_cfg(il_policy, tmp_path).spec())
    rsft.Journal(tmp_path / "journal", other)  # nothing collected yet: a corrected command takes the journal over
    rsft.Journal(tmp_path / "journal", other).save_state("reach-v3", S, attempts=3, successes=1)
    with pytest.raises(UsageError, match="other settings"):
        rsft.Journal(tmp_path / "journal", make_cfg(il_policy, tmp_path).spec())


def test_a_task_never_solved_is_a_clear_error(il_policy, tmp_path):
    cfg = make_cfg(il_policy, tmp_path / "out", max_states_per_task=3)
    journal = rsft.Journal(cfg.output_dir / "journal", cfg.spec())
    with pytest.raises(UsageError, match="reach-v3: only 0 successes after 3 initial states"):
        rsft.collect(cfg, ["reach-v3"], ScriptedEngine(lambda *_: False), journal)


@pytest.fixture(scope="module")
def buffer(collected) -> Path:
    cfg, journal, _ = collected
    return rsft.write_buffer(cfg, list(TASKS), journal, n_tokens=8)


def test_buffer_is_a_lerobot_dataset_with_skill_tokens(buffer, collected):
    cfg, journal, engine = collected
    ds = LeRobotDataset(cfg.repo_id, root=buffer)
    lengths = [20 + int(stem.split("_")[1]) for t in TASKS for stem in EXPECTED_FILES[t]]
    assert ds.num_episodes == 6 and ds.num_frames == sum(lengths) == 127
    table = ds.hf_dataset.with_format("numpy")[:]
    starts = np.flatnonzero(table[SKILL_START_KEY].reshape(-1) == 1)
    assert len(starts) == 6 * 3  # decisions at steps 0, 8, 16 of every episode
    # The tokens stored at each decision frame are the ones the engine sampled there.
    first = engine.episode("reach-v3", S + 1, 1, 1)
    episode0 = table["episode_index"] == 0
    np.testing.assert_array_equal(table[SKILL_TOKENS_KEY][episode0][[0, 8, 16]], first.tokens.numpy())
    np.testing.assert_array_equal(table[SKILL_STEP_KEY][episode0].reshape(-1)[[0, 7, 8, 20]], [0, 0, 1, 2])
    np.testing.assert_allclose(table["observation.state"][episode0], first.states.numpy())
    item = ds[0]
    assert item["task"] == task_description("reach-v3")
    assert item[SKILL_TOKENS_KEY].dtype == torch.int64 and item[SKILL_TOKENS_KEY].shape == (8,)


def test_finetune_learns_the_stored_tokens_then_freezes_encoders(buffer, collected, il_policy, capsys):
    cfg, _, _ = collected
    before, pre, _ = load_policy(il_policy)
    out = rsft.finetune(cfg, buffer)
    epochs = [line for line in capsys.readouterr().out.splitlines() if line.startswith("R-SFT epoch")]
    nll = [float(line.split(" nll:")[1].split()[0]) for line in epochs]
    assert len(nll) == 10 and nll[-1] < nll[0] and min(nll) > 0  # every epoch logs its own NLL
    after, _, _ = load_policy(out)
    assert after.config.freeze_encoders and not any(p.requires_grad for p in after.encoders.parameters())
    ds = LeRobotDataset(cfg.repo_id, root=buffer)
    table = ds.hf_dataset.with_format("torch")[:]
    rows = torch.flatten(torch.nonzero(table[SKILL_START_KEY].reshape(-1) == 1))
    batch = pre({"observation.state": table["observation.state"][rows], "task": [ds[int(i)]["task"] for i in rows]})
    tokens = table[SKILL_TOKENS_KEY][rows]

    def nll(policy):
        with torch.no_grad():
            return -policy.eval().token_logprobs(policy.encode_context(batch), tokens).mean().item()

    assert nll(after) < nll(before) - 0.5  # Eq. 6 on 18 stored skills, 10 epochs at lr 1e-3
    changed = [
        not torch.equal(a, b) for a, b in zip(before.encoders.parameters(), after.encoders.parameters(), strict=True)
    ]
    assert any(changed)  # the whole policy was fine-tuned before the freeze


def test_finetune_runs_where_cuda_is_available(buffer, collected, tmp_path, monkeypatch, capsys):
    """LeRobot's update_policy records the peak GPU memory whenever CUDA is available, whatever the policy's
    device; the fine-tune's tracker must have that meter, as lerobot-train's has (it raised on an H200)."""
    monkeypatch.setattr(lerobot_train, "torch", TorchWhereCudaIsAvailable())
    monkeypatch.setattr(distributed, "torch", TorchWhereCudaIsAvailable())
    cfg = dataclasses.replace(collected[0], output_dir=tmp_path / "out", epochs=1)
    rsft.finetune(cfg, buffer)
    epochs = [line for line in capsys.readouterr().out.splitlines() if line.startswith("R-SFT epoch")]
    assert len(epochs) == 1 and "mem_gb:3.00" in epochs[0]


def test_advantage_weighted_finetune_draws_successes_by_their_states_eq8_advantage(
    buffer, collected, il_policy, tmp_path, capsys
):
    """Eq. 8 of a kept success in its 4-attempt group, by hand: reach S+1 (2 of 4 succeed) 0.5, S+2 (4 of 4) 0;
    button S (1 of 4) 0.75, S+2 (4 of 4) 0. The weighted fine-tune never draws the always-solved states'
    decisions, so it learns their tokens less than the uniform one does, and the others' at least as well."""
    cfg, journal, _ = collected
    states = {t: journal.states(t) for t in TASKS}
    tasks, seeds = ["reach-v3", "reach-v3", "button-press-v3", "button-press-v3"], [S + 1, S + 2, S, S + 2]
    weights = rsft.success_advantages(tasks, seeds, states)
    torch.testing.assert_close(weights, torch.tensor([0.5, 0.0, 0.75, 0.0], dtype=torch.float64))

    ds = LeRobotDataset(cfg.repo_id, root=buffer)
    table = ds.hf_dataset.with_format("torch")[:]
    rows = torch.flatten(torch.nonzero(table[SKILL_START_KEY].reshape(-1) == 1))
    solved = table[rsft.SEED_KEY].reshape(-1)[rows] == S + 2  # the states solved on all 4 attempts, both tasks
    assert int(solved.sum()) == 9  # 3 of the 6 kept episodes, 3 decisions each
    before, pre, _ = load_policy(il_policy)
    batch = pre({"observation.state": table["observation.state"][rows], "task": [ds[int(i)]["task"] for i in rows]})
    tokens = table[SKILL_TOKENS_KEY][rows]

    def nll_drop(**kw) -> torch.Tensor:
        """How much the fine-tune lowers each decision's NLL (a fine-tune from the collection's journal)."""
        out = tmp_path / ("_".join(kw) or "uniform")
        shutil.copytree(cfg.output_dir / "journal", out / "journal")
        after = load_policy(rsft.finetune(dataclasses.replace(cfg, output_dir=out, **kw), buffer))[0]
        with torch.no_grad():
            nll = [-p.eval().token_logprobs(p.encode_context(batch), tokens).mean(-1) for p in (before, after)]
        return nll[0] - nll[1]

    uniform = nll_drop()
    capsys.readouterr()
    weighted = nll_drop(advantage_weighted=True)
    assert "R-SFT fine-tune: 9 of 18 decisions have weight > 0" in capsys.readouterr().out
    # Measured: solved states' NLL drop 1.12 (uniform) vs 0.05 (weighted); the others' 1.12 vs 1.46.
    assert weighted[solved].mean() < uniform[solved].mean() - 0.5
    assert weighted[~solved].mean() > uniform[~solved].mean()

    always = tmp_path / "always"
    every = make_cfg(il_policy, always, advantage_weighted=True)
    rsft.collect(every, list(TASKS), ScriptedEngine(lambda *_: True), rsft.Journal(always / "journal", every.spec()))
    solved_buffer = rsft.write_buffer(every, list(TASKS), rsft.Journal(always / "journal", every.spec()), n_tokens=8)
    with pytest.raises(UsageError, match="every kept success is from a state solved on all its attempts"):
        rsft.finetune(every, solved_buffer)


def test_finetune_mixes_in_demonstration_frames_with_their_autoencoder_tokens(
    buffer, collected, il_policy, tmp_path, capsys
):
    cfg, _, _ = collected
    demos = tmp_path / "demos"
    make_synthetic_dataset(demos, state_dim=39, action_dim=4, tasks=tuple(task_description(t) for t in TASKS))
    only_buffer = dataclasses.replace(cfg, output_dir=tmp_path / "buffer_only")
    mixed = dataclasses.replace(
        cfg, output_dir=tmp_path / "mixed", demo_fraction=0.5, demos_root=demos, demos_repo_id="local/synthetic"
    )
    before, pre, _ = load_policy(il_policy)
    # Every demonstration frame with the IL targets: the frozen autoencoder's tokens of its 32-action chunk.
    everything = rsft.demo_decisions(mixed, before, pre, ["observation.state", "task"], count=10_000)
    assert len(everything) == 185  # all frames of the 4 episodes (60 + 20 + 45 + 60)
    batch = pre(torch.utils.data.default_collate([everything[i] for i in range(len(everything))]))
    tokens = batch[SKILL_TOKENS_KEY]
    assert tokens.shape == (185, 8) and torch.equal(batch[SKILL_START_KEY], torch.ones(185, 1, dtype=torch.int64))

    def demo_nll(policy_dir: Path) -> float:
        policy = load_policy(policy_dir)[0].eval()
        with torch.no_grad():
            return -policy.token_logprobs(policy.encode_context(batch), tokens).mean().item()

    demo_nll_buffer_only = demo_nll(rsft.finetune(only_buffer, buffer))
    capsys.readouterr()
    demo_nll_mixed = demo_nll(rsft.finetune(mixed, buffer))
    assert "18 buffer decisions + 18 demonstration frames" in capsys.readouterr().out  # 18 × 0.5 / (1 − 0.5)
    assert demo_nll_mixed < demo_nll_buffer_only - 1.0  # measured: 7.24 → 4.84 (weighted below: 4.85)
    # With the advantage weighting, each demonstration frame is drawn at the buffer's mean weight: the demos keep
    # their half of the draws, and are learned about as in the uniform mix.
    weighted = dataclasses.replace(mixed, output_dir=tmp_path / "mixed_weighted", advantage_weighted=True)
    shutil.copytree(cfg.output_dir / "journal", weighted.output_dir / "journal")
    demo_nll_weighted = demo_nll(rsft.finetune(weighted, buffer))
    out = capsys.readouterr().out
    assert "18 buffer decisions + 18 demonstration frames" in out and "9 of 18 decisions have weight > 0" in out
    assert demo_nll_weighted < demo_nll_buffer_only - 1.0 and abs(demo_nll_weighted - demo_nll_mixed) < 0.5
    with pytest.raises(UsageError, match="is not a LeRobotDataset"):
        rsft.finetune(dataclasses.replace(mixed, output_dir=tmp_path / "bad", demos_root=tmp_path / "nowhere"), buffer)
    with pytest.raises(UsageError, match="--demo_fraction needs --demos_root"):
        dataclasses.replace(mixed, demos_root=None).validate()


class StandInHub:
    """Records what LeRobot's push_to_hub would send; never touches the network."""

    uploads: list[tuple[str, list[str]]] = []

    def create_repo(self, repo_id, **kw):
        return repo_id

    def create_branch(self, *a, **kw):
        pass

    def upload_folder(self, repo_id, folder_path, ignore_patterns=(), **kw):
        files = sorted(str(p.relative_to(folder_path)) for p in Path(folder_path).rglob("*") if p.is_file())
        StandInHub.uploads.append((repo_id, files))

    def delete_tag(self, *a, **kw):
        pass

    def create_tag(self, repo_id, tag, **kw):
        StandInHub.uploads.append((repo_id, [f"tag:{tag}"]))


def test_push_uploads_the_buffer_to_a_stand_in_hub(buffer, collected, monkeypatch):
    import huggingface_hub
    import lerobot.datasets.lerobot_dataset as lerobot_dataset

    cfg, _, _ = collected
    monkeypatch.setattr(lerobot_dataset, "HfApi", StandInHub)
    monkeypatch.setattr(huggingface_hub.RepoCard, "push_to_hub", lambda self, **kw: None)
    StandInHub.uploads.clear()
    ds = LeRobotDataset(cfg.repo_id, root=buffer)
    ds.repo_id = "lab/cso_buffer"
    ds.push_to_hub()
    (repo, files), (_, tag) = StandInHub.uploads
    assert repo == "lab/cso_buffer"
    assert {"meta/info.json", "meta/stats.json", "meta/tasks.parquet"} <= set(files)
    assert any(f.startswith("data/") and f.endswith(".parquet") for f in files)
    assert tag == ["tag:v3.0"]
