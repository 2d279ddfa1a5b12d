"""The multi-process pool (one SyncVectorEnv shard per worker) runs exactly the episodes the in-process one does."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_cso.rollout.expert import ExpertController
from lerobot_cso.rollout.pool import EnvPool, Job

SEEDS = range(1_000_000, 1_000_003)
JOBS = [Job(task, seed, (task, seed)) for task in ("reach-v3", "button-press-v3") for seed in SEEDS]


def traces(vectorization: str) -> dict:
    with EnvPool(4, max_steps=40, vectorization=vectorization, workers=2) as pool:
        return {trace.job.key: trace for _, trace in pool.run(JOBS, ExpertController(4, noise_std=0.2, seed=3))}


@pytest.mark.parametrize("vectorization", ["processes", "async"])
def test_parallel_pools_replay_the_in_process_episodes(vectorization):
    expected, got = traces("sync"), traces(vectorization)
    assert got.keys() == expected.keys() == {job.key for job in JOBS}
    for key, trace in expected.items():
        assert (got[key].success, got[key].length) == (trace.success, trace.length)
        np.testing.assert_array_equal(got[key].states, trace.states)
        np.testing.assert_array_equal(got[key].actions, trace.actions)
    assert any(t.success for t in expected.values()) and any(t.length == 40 for t in expected.values())
