"""The inference decode path: the streamlined sampler equals the prior's, int8 is measured, async decode is exact."""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest
import torch

from lerobot_cso.policy import CSOPolicy
from lerobot_cso.policy.fast_prior import FastSkillSampler
from lerobot_cso.sampling import Sampling
from lerobot_cso.untrained import untrained_policy

N_CONTEXTS = 1000


def full_size_policy(**overrides) -> CSOPolicy:
    """Default dims (prior 6 × 384), MetaWorld shapes, random init."""
    return untrained_policy(["reach"], state_dim=39, action_dim=4, **overrides).eval()


@pytest.fixture(scope="module")
def policy() -> CSOPolicy:
    return full_size_policy()


@pytest.fixture(scope="module")
def contexts(policy) -> torch.Tensor:
    batch = {"observation.state": torch.randn(N_CONTEXTS, 39), "task": ["reach"] * N_CONTEXTS}
    with torch.inference_mode():
        return policy.encode_context(batch)


def test_float32_sampler_greedy_tokens_equal_the_prior_on_1000_contexts(policy, contexts):
    with torch.inference_mode():
        ref_tokens, ref_logp = policy.sample_skills(contexts, Sampling(top_k=5, greedy=True))
        tokens, logp = FastSkillSampler(policy.prior).sample(contexts, Sampling(top_k=5, greedy=True))
    assert (tokens == ref_tokens).all(dim=1).float().mean() >= 0.99
    torch.testing.assert_close(logp, ref_logp, atol=1e-4, rtol=0)


def test_float32_sampler_draws_the_same_samples_from_the_same_generator(policy, contexts):
    with torch.inference_mode():
        ref_tokens, ref_logp = policy.sample_skills(
            contexts, Sampling(top_k=5), generator=torch.Generator().manual_seed(3)
        )
        sampler = FastSkillSampler(policy.prior)
        tokens, logp = sampler.sample(contexts, Sampling(top_k=5), generator=torch.Generator().manual_seed(3))
    same = (tokens == ref_tokens).all(dim=1)
    assert same.float().mean() >= 0.99
    torch.testing.assert_close(logp[same], ref_logp[same], atol=1e-4, rtol=0)


def test_int8_sampler_stays_near_fp32_but_is_not_equivalent(policy, contexts):
    """int8 weights miss the >= 99 % bar (measured: 85 % of greedy skills, max log-prob error 0.016 nats on the
    agreeing prefix, random init whose logits are flat); this bounds that, so a broken int8 path fails."""
    with torch.inference_mode():
        ref_tokens, ref_logp = policy.sample_skills(contexts, Sampling(top_k=5, greedy=True))
        tokens, logp = FastSkillSampler(policy.prior, "int8").sample(contexts, Sampling(top_k=5, greedy=True))
    agreeing_prefix = (tokens != ref_tokens).float().cumsum(dim=1) == 0
    assert (tokens == ref_tokens).all(dim=1).float().mean() >= 0.8
    assert (logp - ref_logp)[agreeing_prefix].abs().max() <= 0.03


def test_async_decode_gives_the_synchronous_actions_from_a_lowest_priority_process_and_reset_waits():
    """With lead L, skill k > 0 comes from the tick after which L actions remained: replaying that is exact. The
    decode runs in a process of its own at the lowest CPU priority (session 36: a decode thread took the loop's
    GIL); ``reset`` waits for a decode in flight and drops it, keeping the process."""
    sync, lead = full_size_policy(greedy=True), full_size_policy(greedy=True, async_decode_lead=3)
    observations = [{"observation.state": torch.randn(1, 39), "task": ["reach"]} for _ in range(24)]
    with torch.inference_mode():
        got = [lead.select_action(obs) for obs in observations]
        # Synchronous replay: skill k > 0 is decoded from the observation of tick 8k − 3 − 1.
        expected = []
        for t in range(24):
            source = t if t == 0 else t - 4 if t % 8 == 0 else None
            if source is not None:
                sync._action_queue.clear()
            expected.append(sync.select_action(observations[source if source is not None else t]))
    torch.testing.assert_close(torch.stack(got), torch.stack(expected))
    pid = lead._decode_process.pid
    assert pid != os.getpid()
    if sys.platform == "linux":
        assert os.sched_getscheduler(pid) == os.SCHED_IDLE
    assert lead._next_chunk is not None  # tick 20 handed skill 3's decode over
    lead.reset()
    assert lead._next_chunk is None and not lead._action_queue and lead._decode_process.pid == pid
    os.kill(pid, signal.SIGKILL)  # a process that died is a clear error, not a hang or an EOFError
    lead._decode_process._process.join(timeout=10)
    with pytest.raises(RuntimeError, match=rf"decode process \(pid {pid}\) ended, exit code -9"):
        lead._decode_process.decode(observations[0]).result()


def test_async_decode_lead_must_leave_a_queued_action():
    with pytest.raises(ValueError, match="async_decode_lead"):
        full_size_policy(async_decode_lead=8)
    with pytest.raises(ValueError, match="inference_weights"):
        full_size_policy(inference_weights="fp8")


def test_the_caller_goes_on_while_the_process_decodes_errors_reach_it_and_train_ends_the_process():
    """Handing a decode over does not wait for it (a batch of 256 takes the process far longer than the hand-over);
    an error in the process reaches the caller and the process serves on; ``reset()`` in eval mode starts it (before
    a control loop's first tick); ``train()`` ends it (its copy of the weights would go stale)."""
    policy = full_size_policy(async_decode_lead=3)
    obs = {"observation.state": torch.randn(1, 39), "task": ["reach"]}
    many = {"observation.state": torch.randn(256, 39), "task": ["reach"] * 256}
    assert policy._decode_process is None  # made in training mode, then put in eval mode (no reset since)
    policy.reset()  # as LeRobot's rollout does in its set-up: the process starts there, not on the first tick
    process = policy._decode_process
    assert process is not None and process.pid != os.getpid()
    with torch.inference_mode():
        policy.select_action(obs)
        assert policy._decode_process is process
        handed = time.perf_counter()
        pending = process.decode(many)
        returned = time.perf_counter()
        chunks = pending.result()
        done = time.perf_counter()
        with pytest.raises(RuntimeError, match="shapes cannot be multiplied"):
            process.decode({"observation.state": torch.randn(1, 5), "task": ["reach"]}).result()
        assert process.decode(obs).result().shape == (1, policy.config.n_action_steps, 4)
    assert chunks.shape == (256, policy.config.n_action_steps, 4)
    assert returned - handed < 0.25 * (done - handed)
    policy.train()
    assert policy._decode_process is None
    process._process.join(timeout=10)
    assert process._process.exitcode == 0
