"""The rollout engine with a real (tiny, briefly trained) cso policy: determinism, groups of K, recorded
log-probs and actions against recomputation, throughput, cameras; and the env pool with async workers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium.vector import AsyncVectorEnv
from metaworld_fixtures import load_policy, shared_policy

from lerobot_cso.rollout.engine import Episode, RolloutEngine
from lerobot_cso.rollout.pool import EnvPool, Job, kept_pools
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.expert import ExpertController
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.metaworld.world import pool as metaworld_pool

STATES = [("reach-v3", 11), ("button-press-v3", 12)]
MAX_STEPS = 48


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Envs, env workers and the policy share two cores: spinning OpenMP threads would slow inference 10x+."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def loaded(tmp_path_factory):
    return load_policy(shared_policy(tmp_path_factory))


@pytest.fixture(scope="module")
def engine(loaded):
    with RolloutEngine(*loaded, metaworld_pool(3, max_steps=MAX_STEPS), task_description) as eng:
        yield eng


def assert_same_episodes(a: list[Episode], b: list[Episode]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert (x.task, x.init_seed, x.group, x.sample, x.success, x.length) == (
            y.task,
            y.init_seed,
            y.group,
            y.sample,
            y.success,
            y.length,
        )
        for field in ("states", "actions", "tokens", "logprobs", "contexts", "decision_steps"):
            torch.testing.assert_close(getattr(x, field), getattr(y, field), rtol=0, atol=0, msg=field)


def test_greedy_rollouts_are_deterministic(loaded, engine):
    first = engine.rollout(STATES, k=2, sampling=Sampling(greedy=True), seed=0).episodes
    again = engine.rollout(STATES, k=2, sampling=Sampling(greedy=True), seed=5).episodes  # seed only drives sampling
    with RolloutEngine(*loaded, metaworld_pool(3, max_steps=MAX_STEPS), task_description) as fresh:
        other = fresh.rollout(STATES, k=2, sampling=Sampling(greedy=True), seed=0).episodes
    assert_same_episodes(first, again)
    assert_same_episodes(first, other)
    torch.testing.assert_close(first[0].actions, first[1].actions)  # greedy: the K samples coincide


def test_groups_of_k_start_from_their_initial_state(engine):
    result = engine.rollout(STATES, k=3, sampling=Sampling(temperature=1.0, top_k=5), seed=0)
    groups = result.groups()
    assert [(e.group, e.sample) for e in result.episodes] == [(g, i) for g in range(2) for i in range(3)]
    for (task, seed), group in zip(STATES, groups, strict=True):
        assert all((e.task, e.init_seed) == (task, seed) for e in group)
        for e in group[1:]:
            torch.testing.assert_close(e.states[0], group[0].states[0], rtol=0, atol=0)
    assert not torch.equal(groups[0][0].states[0], groups[1][0].states[0])
    assert any(not torch.equal(groups[0][0].tokens, e.tokens) for e in groups[0][1:])  # sampled, not greedy
    other_seed = engine.rollout(STATES, k=3, sampling=Sampling(temperature=1.0, top_k=5), seed=1)
    assert any(not torch.equal(a.tokens, b.tokens) for a, b in zip(result.episodes, other_seed.episodes, strict=True))


@pytest.mark.parametrize("sampling", [Sampling(temperature=1.0, top_k=5), Sampling(temperature=0.7, top_k=None)])
def test_recorded_tokens_logprobs_and_actions_match_recomputation(loaded, engine, sampling):
    policy, _, post = loaded
    n_act = policy.config.n_action_steps
    for e in engine.rollout(STATES, k=2, sampling=sampling, seed=3).episodes:
        decisions = math.ceil(e.length / n_act)
        assert e.decision_steps.tolist() == [n_act * d for d in range(decisions)]
        assert e.tokens.shape == (decisions, policy.config.n_tokens) and e.tokens.dtype == torch.int64
        assert e.states.shape == (e.length, 39) and e.actions.shape == (e.length, 4)
        recomputed = policy.token_logprobs(e.contexts, e.tokens, sampling)
        assert recomputed.requires_grad
        torch.testing.assert_close(recomputed.detach(), e.logprobs, rtol=0, atol=1e-5)
        with torch.no_grad():
            chunks = policy.decode_skills(e.tokens)[:, :n_act]
            executed = post(chunks.reshape(-1, 4)).reshape(decisions * n_act, 4).clamp(-1, 1)
        torch.testing.assert_close(executed[: e.length], e.actions, rtol=0, atol=1e-6)


def test_throughput_and_on_episode(engine):
    seen: list[tuple[str, int]] = []
    result = engine.rollout(STATES, k=2, sampling=Sampling(), on_episode=lambda e: seen.append((e.task, e.sample)))
    assert sorted(seen) == sorted((e.task, e.sample) for e in result.episodes)
    assert result.env_steps == sum(e.length for e in result.episodes) > 0
    assert result.decisions == sum(len(e.tokens) for e in result.episodes)
    assert result.env_steps_per_s > 0 and result.decisions_per_s > 0 and 0 < result.policy_seconds < result.seconds
    assert 0.0 <= result.success_rate <= 1.0


def test_async_env_workers_give_the_same_episodes_as_sync():
    jobs = [Job("reach-v3", 0), Job("reach-v3", 1), Job("button-press-v3", 0)]
    traces = {}
    for vectorization in ("sync", "async"):
        with metaworld_pool(2, max_steps=30, vectorization=vectorization) as pool:
            assert isinstance(pool.vec, AsyncVectorEnv) == (vectorization == "async")
            traces[vectorization] = dict(pool.run(jobs, ExpertController(2, noise_std=0.2, seed=0)))
    for i in range(len(jobs)):
        np.testing.assert_array_equal(traces["sync"][i].states, traces["async"][i].states)
        np.testing.assert_array_equal(traces["sync"][i].actions, traces["async"][i].actions)


def test_kept_pools_serve_later_stages_from_the_same_open_pool(loaded):
    """Inside kept_pools, a stage's close leaves its pool (and its worker processes) running for the next stage
    with the same arguments, which gets the same episodes; other arguments get another pool; all close at the end."""
    greedy = Sampling(greedy=True)
    with kept_pools():
        first = metaworld_pool(3, max_steps=MAX_STEPS, workers=2)
        with RolloutEngine(*loaded, first, task_description) as stage:
            episodes = stage.rollout(STATES, k=2, sampling=greedy).episodes
        second = metaworld_pool(3, max_steps=MAX_STEPS, workers=2)
        other = metaworld_pool(3, max_steps=MAX_STEPS - 1, workers=2)
        assert second.pool is first.pool and other.pool is not first.pool
        with metaworld_pool(3, max_steps=MAX_STEPS, workers=2) as entered:  # a stage that opens it in a `with`
            assert entered.pool is first.pool
        workers = first.pool.vec._processes
        assert all(p.is_alive() for p in workers)
        with RolloutEngine(*loaded, second, task_description) as stage:
            assert_same_episodes(episodes, stage.rollout(STATES, k=2, sampling=greedy).episodes)
    for p in workers:
        p.join(timeout=10)
    assert not any(p.is_alive() for p in [*workers, *other.pool.vec._processes])
    with metaworld_pool(2, max_steps=MAX_STEPS, vectorization="sync") as outside:  # outside the block: a new pool
        assert isinstance(outside, EnvPool)


def test_the_pool_asks_skip_when_a_jobs_turn_comes_and_runs_no_skipped_job():
    """Two slots, four jobs: job 2 is asked about only once a slot is free (a job has ended) and is skipped
    then; job 3, the last, is skipped too, and the run still ends."""
    jobs = [Job("reach-v3", s, s) for s in range(4)]
    ended: list[int] = []
    asked: dict[int, list[int]] = {}

    def skip(job: Job) -> bool:
        asked[job.key] = list(ended)
        return job.key == 3 or (job.key == 2 and bool(ended))

    with metaworld_pool(2, max_steps=24, vectorization="sync") as pool:
        for index, _ in pool.run(jobs, ExpertController(2, noise_std=0.2, seed=0), skip=skip):
            ended.append(index)
    assert sorted(ended) == [0, 1]
    assert list(asked) == [0, 1, 2, 3] and asked[0] == asked[1] == [] and asked[2]


def test_camera_frames_are_recorded_per_step(loaded):
    with RolloutEngine(*loaded, metaworld_pool(2, ("corner2",), max_steps=10), task_description) as eng:
        episodes = eng.rollout([("reach-v3", 0)], k=2, sampling=Sampling(greedy=True)).episodes
    for e in episodes:
        frames = e.images["corner2"]
        assert frames.shape == (e.length, 128, 128, 3) and frames.dtype == torch.uint8
        assert not torch.equal(frames[0], frames[-1])


def test_bad_requests_are_clear_errors(engine):
    with pytest.raises(ValueError, match="k must be >= 1"):
        engine.rollout(STATES, k=0)
    with pytest.raises(ValueError, match="stop_after must be >= 1"):
        engine.rollout(STATES, k=2, stop_after=0)
    with pytest.raises(ValueError, match="unknown MetaWorld task 'reach-v2'"):
        engine.rollout([("reach-v2", 0)])
    assert np.all(engine.rollout(STATES[:1], k=1).episodes[0].actions.abs().numpy() <= 1.0)
