"""SPO: dynamic rejection, prior-only updates with frozen encoders, every granularity on one engine, resume."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from cso_fakes import TASKS, ScriptedEngine, TorchWhereCudaIsAvailable, mixed, save_tiny_metaworld_policy
from lerobot.scripts import lerobot_train

from lerobot_cso import distributed
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso import spo

S = 1_500_000  # first SPO initial-state seed


@pytest.fixture(scope="module")
def rsft_policy(tmp_path_factory) -> Path:
    path = save_tiny_metaworld_policy(tmp_path_factory.mktemp("rsft") / "pretrained_model", seed=1)
    policy, pre, post = load_policy(path)
    policy.set_encoders_frozen(True)
    policy.save_pretrained(path)
    return path


def make_cfg(policy_path: Path, out: Path, **kw) -> spo.SPOConfig:
    defaults = dict(
        tasks=",".join(TASKS),
        output_dir=out,
        iterations=2,
        groups_per_iteration=2,
        group_size=4,
        epochs=2,
        minibatch_trajectories=4,
        lr=1e-3,
    )
    cfg = spo.SPOConfig(**(defaults | kw))
    cfg.policy = load_policy(policy_path)[0].config
    cfg.policy.pretrained_path = policy_path
    return cfg


def engine_factory(engines: list[ScriptedEngine], outcome=mixed):
    def make(policy, pre, post, cfg):
        engine = ScriptedEngine(outcome, policy=policy)
        engines.append(engine)
        return engine

    return make


def test_dynamic_rejection_draws_new_states_until_b_groups(rsft_policy, tmp_path):
    cfg = make_cfg(rsft_policy, tmp_path)
    engine = ScriptedEngine(mixed)
    groups, stats, cursor = spo.collect_groups(cfg, list(TASKS), engine, cursor=0, round_seed=0)
    # Draw 1: seeds S (all fail, rejected) and S+1 (2/4, kept); draw 2: S+2 (all succeed, rejected);
    # draw 3: S+3 (2/4, kept). 4 groups drawn, 2 rejected; 2+4+2 successes of 16 episodes.
    assert [[s.seed for s in call] for call in engine.calls] == [[S, S + 1], [S + 2], [S + 3]]
    assert [g[0].init_seed for g in groups] == [S + 1, S + 3]
    # ScriptedEngine episodes last 20 + sample steps: 4 groups of samples 0..3 -> 4 * (20 + 21 + 22 + 23) steps.
    assert stats == {"success_rate": 8 / 16, "rejection_rate": 0.5, "episodes": 16, "env_steps": 4 * 86}
    assert cursor == 4
    assert [g[0].task for g in groups] == ["button-press-v3", "button-press-v3"]  # tasks alternate per state


def test_batch_pads_decisions_and_broadcasts_group_advantages(rsft_policy, tmp_path):
    engine = ScriptedEngine(mixed)
    groups = [engine.rollout([("reach-v3", S + 1)], k=4).groups()[0]]
    batch = spo.Batch.from_groups(groups, "group_mean")
    # Lengths 20..23 steps -> 3 decisions each (steps 0, 8, 16); rewards 1,1,0,0 -> A = R - 0.5.
    assert batch.tokens.shape == (4, 3, 8) and batch.mask.all()
    torch.testing.assert_close(batch.advantages, torch.tensor([0.5, 0.5, -0.5, -0.5]))
    loo = spo.Batch.from_groups(groups, "leave_one_out").advantages  # leave-one-out: 1 - 1/3, 0 - 2/3
    torch.testing.assert_close(loo, torch.tensor([2 / 3, 2 / 3, -2 / 3, -2 / 3]))
    # The rollouts keep contexts on the CPU; the batch goes to the policy's device ("meta" stands in for cuda).
    on_device = spo.Batch.from_groups(groups, "group_mean", device="meta")
    tensors = (on_device.contexts, on_device.tokens, on_device.mask, on_device.advantages)
    assert {t.device.type for t in tensors} == {"meta"}
    assert on_device.inputs == {} and on_device.tasks == []  # frozen encoders: only the cached contexts
    assert on_device.contexts.shape == batch.contexts.shape and on_device.mask.dtype == torch.bool


@pytest.mark.parametrize("objective", ["skill", "token", "trajectory", "ript"])
def test_spo_updates_the_prior_only(rsft_policy, tmp_path, objective):
    engines: list[ScriptedEngine] = []
    cfg = make_cfg(rsft_policy, tmp_path / objective, objective=objective)
    history = spo.run_spo(cfg, make_engine=engine_factory(engines))
    before, _, _ = load_policy(rsft_policy)
    after, _, _ = load_policy(cfg.output_dir / "pretrained_model")
    for name in ("encoders", "autoencoder"):
        a, b = getattr(before, name).state_dict(), getattr(after, name).state_dict()
        assert all(torch.equal(a[k], b[k]) for k in a), f"{name} changed"
    assert any(not torch.equal(p, q) for p, q in zip(before.prior.parameters(), after.prior.parameters(), strict=True))
    assert after.config.freeze_encoders
    assert [h["iteration"] for h in history] == [1, 2]
    drawn = [s for call in engines[0].calls for s in call]
    assert len(drawn) == len(set(drawn))  # every iteration draws fresh initial states
    assert all(h["rejection_rate"] == 0.5 and h["success_rate"] == 0.5 for h in history)
    assert all(0.0 <= h["clip_fraction"] <= 1.0 and h["grad_norm"] > 0 for h in history)
    logged = [json.loads(line) for line in (cfg.output_dir / "log.jsonl").read_text().splitlines()]
    assert logged == history
    assert (cfg.output_dir / "spo.png").stat().st_size > 1000


def test_without_the_freeze_spo_updates_the_encoders_too_from_the_kept_inputs(rsft_policy, tmp_path):
    """The ablation: contexts recomputed from each decision's kept encoder inputs, so the encoders learn too; with
    a vanishing lr the recomputed contexts are the rollout's (every ratio 1)."""
    engines: list[ScriptedEngine] = []
    cfg = make_cfg(rsft_policy, tmp_path / "unfrozen", encoder_freeze=False)
    spo.run_spo(cfg, make_engine=engine_factory(engines))
    assert engines[0].policy is not None and not engines[0].policy.config.freeze_encoders
    before, _, _ = load_policy(rsft_policy)
    after, _, _ = load_policy(cfg.output_dir / "pretrained_model")
    a, b = before.encoders.state_dict(), after.encoders.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)
    a, b = before.autoencoder.state_dict(), after.autoencoder.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not after.config.freeze_encoders
    tiny = make_cfg(rsft_policy, tmp_path / "tiny_lr", encoder_freeze=False, epochs=1, minibatch_trajectories=64)
    still = spo.run_spo(dataclasses.replace(tiny, lr=1e-12), make_engine=engine_factory(engines))
    assert all(h["clip_fraction"] == 0.0 and h["ratio_mean"] == pytest.approx(1.0, abs=1e-6) for h in still)


def test_first_minibatch_ratio_is_one_and_clip_starts_at_zero(rsft_policy, tmp_path):
    cfg = make_cfg(rsft_policy, tmp_path, epochs=1, minibatch_trajectories=64)
    engines: list[ScriptedEngine] = []
    history = spo.run_spo(cfg, make_engine=engine_factory(engines))
    # One epoch of one minibatch: its ratios are taken before its step, at π = π_old (recomputed after each
    # iteration's collection): every ratio is exactly 1, nothing is clipped and the KL is 0.
    assert all(h["clip_fraction"] == 0.0 and abs(h["approx_kl"]) < 1e-6 for h in history)
    assert all(h["ratio_mean"] == pytest.approx(1.0) and h["updates"] == 1 for h in history)  # 1 epoch, 1 minibatch
    codes = load_policy(rsft_policy)[0].config.vocab_size
    assert all(0 < h["entropy"] < math.log(codes) for h in history)  # the prior's spread, logged


def test_trajectory_mean_reaches_the_loss_which_then_counts_trajectories(rsft_policy, tmp_path, monkeypatch):
    seen, real = [], spo.clipped_surrogate_loss

    def spy(new, old, mask, adv, granularity, clip, n_units, trajectory_mean):
        seen.append((int(n_units), int((mask.sum(dim=1) > 0).sum()), trajectory_mean))
        return real(new, old, mask, adv, granularity, clip, n_units, trajectory_mean)

    monkeypatch.setattr(spo, "clipped_surrogate_loss", spy)
    cfg = make_cfg(rsft_policy, tmp_path, iterations=1, minibatch_trajectories=64, trajectory_mean=True)
    spo.run_spo(cfg, make_engine=engine_factory([]))
    assert seen and all(mean and units == trajectories for units, trajectories, mean in seen)


def test_target_kl_stops_an_iterations_updates_early(rsft_policy, tmp_path):
    engines: list[ScriptedEngine] = []
    full = spo.run_spo(make_cfg(rsft_policy, tmp_path / "full", lr=1e-2), make_engine=engine_factory(engines))
    assert all(h["updates"] == 4 for h in full)  # 2 epochs x 2 minibatches
    stopped = spo.run_spo(
        make_cfg(rsft_policy, tmp_path / "stopped", lr=1e-2, target_kl=1e-9), make_engine=engine_factory(engines)
    )
    # The first minibatch has ratio 1 (KL 0); the second one, after a step at lr 1e-2, exceeds any tiny target.
    assert all(h["updates"] == 2 for h in stopped)
    assert all(h["clip_low_fraction"] + h["clip_high_fraction"] == pytest.approx(h["clip_fraction"]) for h in full)


def test_resume_continues_after_the_last_finished_iteration(rsft_policy, tmp_path):
    engines: list[ScriptedEngine] = []
    first = spo.run_spo(make_cfg(rsft_policy, tmp_path, iterations=1), make_engine=engine_factory(engines))
    resumed = spo.run_spo(make_cfg(rsft_policy, tmp_path, iterations=2), make_engine=engine_factory(engines))
    assert resumed[0] == first[0] and [h["iteration"] for h in resumed] == [1, 2]
    seeds_run = [s.seed for e in engines for call in e.calls for s in call]
    assert len(seeds_run) == len(set(seeds_run))  # the second run drew new initial states only
    shutil.rmtree(tmp_path / "pretrained_model")  # as if killed between the last iteration and the final copy
    again = spo.run_spo(make_cfg(rsft_policy, tmp_path, iterations=2), make_engine=engine_factory(engines))
    assert again == resumed and len(engines) == 2  # complete: nothing rolled out
    assert (tmp_path / "pretrained_model" / "model.safetensors").is_file()


def calls(engine: ScriptedEngine) -> list[list[tuple[str, int]]]:
    return [[(s.task, s.seed) for s in call] for call in engine.calls]


def test_a_state_pool_cycles_and_skips_states_whose_group_was_uniform(rsft_policy, tmp_path):
    """Pool of 2 states per task: positions 0..3 = (reach, S), (button, S), (reach, S+1), (button, S+1).
    Seed S fails in every sample (uniform), S+1 is mixed; skip_uniform_for=1 keeps S out of iteration 1."""
    cfg = make_cfg(rsft_policy, tmp_path, state_pool=2, skip_uniform_for=1, max_draw_factor=2)
    r, b = TASKS
    engine, skip = ScriptedEngine(mixed), {}
    groups, stats, cursor = spo.collect_groups(cfg, list(TASKS), engine, 0, 0, iteration=0, skip_until=skip)
    assert calls(engine) == [[(r, S), (b, S)], [(r, S + 1), (b, S + 1)]]
    assert [(g[0].task, g[0].init_seed) for g in groups] == [(r, S + 1), (b, S + 1)]
    assert skip == {"0": 2, "1": 2} and cursor == 4 and stats["rejection_rate"] == 0.5
    engine.calls.clear()
    groups, stats, cursor = spo.collect_groups(cfg, list(TASKS), engine, cursor, 0, iteration=1, skip_until=skip)
    assert calls(engine) == [[(r, S + 1), (b, S + 1)]] and stats["rejection_rate"] == 0.0  # S skipped
    assert cursor == 8
    engine.calls.clear()
    spo.collect_groups(cfg, list(TASKS), engine, cursor, 0, iteration=2, skip_until=skip)
    assert calls(engine) == [[(r, S), (b, S)], [(r, S + 1), (b, S + 1)]]  # S is back, and skipped again
    assert skip == {"0": 4, "1": 4}


def test_an_exhausted_pool_ends_the_collection(rsft_policy, tmp_path):
    cfg = make_cfg(rsft_policy, tmp_path, state_pool=1, skip_uniform_for=3)  # only seed S: uniform
    engine = ScriptedEngine(mixed)
    groups, stats, _ = spo.collect_groups(cfg, list(TASKS), engine, 0, 0, iteration=0, skip_until={})
    assert groups == [] and len(engine.calls) == 1 and stats["rejection_rate"] == 1.0


def test_resume_keeps_the_pools_skip_memory(rsft_policy, tmp_path):
    pool = dict(state_pool=2, skip_uniform_for=1, iterations=2)
    whole: list[ScriptedEngine] = []
    history = spo.run_spo(make_cfg(rsft_policy, tmp_path / "whole", **pool), make_engine=engine_factory(whole))
    parts: list[ScriptedEngine] = []
    first = make_cfg(rsft_policy, tmp_path / "parts", **pool | {"iterations": 1})
    spo.run_spo(first, make_engine=engine_factory(parts))
    continued = spo.run_spo(make_cfg(rsft_policy, tmp_path / "parts", **pool), make_engine=engine_factory(parts))
    assert [c for e in parts for c in calls(e)] == calls(whole[0])
    # A 1-iteration run continued to 2 is the 2-iteration run: same updates, same weights.
    assert [{k: v for k, v in h.items() if k != "seconds"} for h in continued] == [
        {k: v for k, v in h.items() if k != "seconds"} for h in history
    ]
    weights = [load_policy(tmp_path / run / "pretrained_model")[0].state_dict() for run in ("whole", "parts")]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert calls(whole[0])[-1] == [(TASKS[0], S + 1), (TASKS[1], S + 1)]  # iteration 2 skipped seed S


def test_bad_objective_is_a_clear_error(rsft_policy, tmp_path):
    from lerobot_cso.errors import UsageError

    with pytest.raises(UsageError, match="objective must be one of skill, token, trajectory, ript"):
        make_cfg(rsft_policy, tmp_path, objective="sequence").validate()
    with pytest.raises(UsageError, match="ratio must be one of token, skill, trajectory or null, got 'ript'"):
        make_cfg(rsft_policy, tmp_path, ratio="ript").validate()
    with pytest.raises(UsageError, match="advantage must be one of group_mean, leave_one_out or null"):
        make_cfg(rsft_policy, tmp_path, advantage="std").validate()


def test_an_objectives_axes_override_its_preset_one_by_one(rsft_policy, tmp_path):
    """``--objective`` names a preset; ``--ratio``, ``--advantage`` and ``--clip_low/high`` each replace one of its
    choices. Left unset they are not part of the spec (outputs made before they existed still resume)."""
    from lerobot_cso.cso.objectives import Advantage, Granularity, Objective
    from lerobot_cso.stage import without_added_settings

    cfg = make_cfg(rsft_policy, tmp_path, objective="ript")
    assert cfg.loss_objective() == Objective(Granularity.TOKEN, Advantage.LEAVE_ONE_OUT, (0.8, 1.2))
    mixed = make_cfg(rsft_policy, tmp_path, objective="ript", ratio="skill", clip_high=1.3)
    assert mixed.loss_objective() == Objective(Granularity.SKILL, Advantage.LEAVE_ONE_OUT, (0.8, 1.3))
    group = make_cfg(rsft_policy, tmp_path, advantage="group_mean")
    assert group.loss_objective() == Objective(Granularity.SKILL, Advantage.GROUP_MEAN, (0.93, 1.15))
    assert not {"ratio", "advantage"} & set(without_added_settings(cfg.stage_spec()))
    assert without_added_settings(mixed.stage_spec())["ratio"] == "skill"


def test_spo_steps_where_cuda_is_available(rsft_policy, tmp_path, monkeypatch):
    """LeRobot's update_policy records the peak GPU memory whenever CUDA is available, whatever the policy's device:
    SPO's step tracker must have that meter, as R-SFT's and lerobot-train's have (R-SFT's lacked it on an H200)."""
    monkeypatch.setattr(lerobot_train, "torch", TorchWhereCudaIsAvailable())
    monkeypatch.setattr(distributed, "torch", TorchWhereCudaIsAvailable())
    history = spo.run_spo(make_cfg(rsft_policy, tmp_path, iterations=1), make_engine=engine_factory([]))
    assert history[0]["updates"] > 0
