"""The multi-process pool (one SyncVectorEnv shard per worker, two lanes) runs exactly the episodes the in-process
one does, and decides each lane's actions on its own while the other lane's chunk runs."""

from __future__ import annotations

import functools
import os

import gymnasium as gym
import numpy as np
import pytest

from lerobot_cso.errors import EnvWorkerError
from lerobot_cso.rollout.pool import Job
from lerobot_cso.rollout.sharded import ShardedVectorEnv
from lerobot_cso.worlds.metaworld.expert import ExpertController
from lerobot_cso.worlds.metaworld.world import pool as metaworld_pool

SEEDS = range(1_000_000, 1_000_003)
JOBS = [Job(task, seed, (task, seed)) for task in ("reach-v3", "button-press-v3") for seed in SEEDS]


class RecordingExpert(ExpertController):
    """The scripted experts, noting which slots each ``act`` call decided for."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.calls: list[set[int]] = []

    def act(self, obs, active):
        self.calls.append(set(np.flatnonzero(active).tolist()))
        return super().act(obs, active)


def traces(vectorization: str, controller: ExpertController | None = None) -> dict:
    controller = controller or ExpertController(4, noise_std=0.2, seed=3)
    with metaworld_pool(4, max_steps=40, vectorization=vectorization, workers=2) as pool:
        return {trace.job.key: trace for _, trace in pool.run(JOBS, controller)}


@pytest.mark.parametrize("vectorization", ["processes", "async"])
def test_parallel_pools_replay_the_in_process_episodes(vectorization):
    expected, got = traces("sync"), traces(vectorization)
    assert got.keys() == expected.keys() == {job.key for job in JOBS}
    for key, trace in expected.items():
        assert (got[key].success, got[key].length) == (trace.success, trace.length)
        np.testing.assert_array_equal(got[key].states, trace.states)
        np.testing.assert_array_equal(got[key].actions, trace.actions)
    assert any(t.success for t in expected.values()) and any(t.length == 40 for t in expected.values())


def test_the_two_lanes_of_a_sharded_pool_are_decided_in_turn():
    controller = RecordingExpert(4, noise_std=0.2, seed=3)
    expected, got = traces("sync"), traces("processes", controller)
    assert {key: (t.success, t.length) for key, t in got.items()} == {
        key: (t.success, t.length) for key, t in expected.items()
    }
    lanes = [{0, 1}, {2, 3}]
    assert all(any(call <= lane for lane in lanes) for call in controller.calls)  # one lane per decision
    firsts = [next(i for i, call in enumerate(controller.calls) if call <= lane) for lane in lanes]
    assert firsts == [0, 1]  # lane 0 decides, then lane 1 while lane 0's step runs
    assert sum(call <= lanes[1] for call in controller.calls) >= 40  # lane 1 stepped its own episodes


def test_a_run_left_early_leaves_the_pool_as_good_as_new():
    expected = traces("sync")
    with metaworld_pool(4, max_steps=40, vectorization="processes", workers=2) as pool:
        run = pool.run(JOBS, ExpertController(4, noise_std=0.2, seed=3))
        next(run)  # the other lane's chunk is in flight now
        run.close()
        got = {trace.job.key: trace for _, trace in pool.run(JOBS, ExpertController(4, noise_std=0.2, seed=3))}
    assert got.keys() == expected.keys()
    for key, trace in expected.items():
        np.testing.assert_array_equal(got[key].states, trace.states)
        np.testing.assert_array_equal(got[key].actions, trace.actions)


class FailingEnv(gym.Env):
    """Raises on its ``fail_at``-th step; with ``die`` its process exits instead (a native crash's way)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def __init__(self, fail_at: int, die: bool = False) -> None:
        self.fail_at, self.die, self.steps = fail_at, die, 0

    def reset(self, *, seed=None, options=None):
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.steps += 1
        if self.steps == self.fail_at:
            if self.die:
                os._exit(3)
            raise FileNotFoundError(2, "No such file or directory", "/gone/init_file")
        return np.zeros(2, np.float32), 0.0, False, False, {}


@pytest.mark.parametrize(
    ("die", "message"),
    [
        (False, "env worker 1 failed: FileNotFoundError: [Errno 2] No such file or directory: '/gone/init_file'"),
        (True, "env worker 1 exited (exit code 3)"),
    ],
)
def test_an_env_worker_that_fails_is_one_error_naming_it(die, message):
    """A worker whose env raised (seen: LIBERO's init file gone) or whose process died surfaced as an EOFError
    traceback of the pipe; it is now an ``EnvWorkerError`` naming the worker and its error (the CLI prints it as
    one line, exit 1)."""
    fns = [functools.partial(FailingEnv, 99), functools.partial(FailingEnv, 2, die)]
    vec = ShardedVectorEnv(fns, workers=2)
    try:
        vec.reset(seed=[0, 1])
        vec.step(np.zeros((2, 1), np.float32))
        with pytest.raises(EnvWorkerError) as info:
            vec.step(np.zeros((2, 1), np.float32))
        assert str(info.value) == message
    finally:
        vec.close()
