"""A contextual bandit behind the rollout-engine interface, with a known answer, driven by the real policy.

An initial state ``(task, seed)`` has the context class ``c = seed % 3``; its observation is the 39-d state
``3 · onehot(c)``. Every decision goes through the real policy hooks, batched over all episodes
(``encode_context`` on the preprocessed observation, ``sample_skills``, ``decode_skills`` and the
postprocessor), exactly what :class:`~lerobot_cso.rollout.engine.RolloutEngine` records.

The answer: for each (task, class) two "good" first tokens, the 4th and 5th most likely first tokens of
the initial policy there. An episode succeeds iff the first token of its first skill is a good one, so with
QueST's top-5 sampling the initial policy succeeds about 1/3 of the time, and one that moved its mass onto
its own least favoured top-5 tokens always. A success ends the episode after its first skill
(``n_action_steps`` steps); a failure runs ``failure_decisions`` skills, so failures are much longer than
successes, and their later skills do not matter (noise for the objectives).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence

import torch
from lerobot.envs.utils import preprocess_observation

from lerobot_cso.rollout.engine import Episode, InitialState, RolloutResult
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.constants import STATE_DIM
from lerobot_cso.worlds.metaworld.tasks import task_description

N_CLASSES = 3


def context_class(seed: int) -> int:
    return seed % N_CLASSES


def observation(seed: int) -> torch.Tensor:
    state = torch.zeros(STATE_DIM)
    state[context_class(seed)] = 3.0
    return state


@torch.no_grad()
def good_tokens(policy, preprocessor, tasks: Sequence[str]) -> dict[tuple[str, int], set[int]]:
    """The answer: per (task, class), the initial policy's 4th and 5th most likely first tokens."""
    answer = {}
    for task in tasks:
        for c in range(N_CLASSES):
            batch = preprocess_observation({"agent_pos": observation(c)[None].numpy()})
            batch["task"] = [task_description(task)]
            context = policy.encode_context(preprocessor(batch))
            logits = policy.prior.logits(context, torch.zeros(1, policy.config.n_tokens, dtype=torch.long))
            answer[(task, c)] = {int(t) for t in logits[0, 0].topk(5).indices[3:]}
    return answer


class BanditEngine:
    """Stands in for ``RolloutEngine``; ``make_engine``-compatible through :func:`bandit_factory`."""

    def __init__(self, answer, policy, preprocessor, postprocessor, failure_decisions: int = 6) -> None:
        self.answer = answer
        self.policy, self.preprocessor, self.postprocessor = policy, preprocessor, postprocessor
        self.failure_decisions = failure_decisions
        self.episodes_run = 0

    @torch.no_grad()
    def _decide(self, seeds: list[int], tasks: list[str], sampling: Sampling, generator: torch.Generator):
        obs = {"agent_pos": torch.stack([observation(s) for s in seeds]).numpy()}
        batch = preprocess_observation(obs)
        batch["task"] = [task_description(t) for t in tasks]
        context = self.policy.encode_context(self.preprocessor(batch))
        tokens, logprobs = self.policy.sample_skills(context, sampling, generator)
        n = self.policy.config.n_action_steps
        chunk = self.policy.decode_skills(tokens, n)
        actions = self.postprocessor(chunk.reshape(-1, chunk.shape[-1])).reshape(chunk.shape).float()
        return context.float(), tokens, logprobs.float(), actions

    def rollout(
        self,
        initial_states: Sequence[InitialState | tuple[str, int]],
        k: int = 1,
        sampling: Sampling = Sampling(),  # noqa: B008  (frozen dataclass, as in RolloutEngine.rollout)
        seed: int = 0,
        progress: str | None = None,
        on_episode: Callable[[Episode], None] | None = None,
        stop_after: int | None = None,
        keep_frames: Collection[int] = (),  # no camera here: nothing to keep
        round_id: int | None = None,  # no journal here: nothing to name
    ) -> RolloutResult:
        states = [InitialState(*s) for s in initial_states]
        jobs = [(g, i, s) for g, s in enumerate(states) for i in range(k)]
        generator = torch.Generator().manual_seed(seed)
        was_training = self.policy.training
        self.policy.eval()
        decisions = [
            self._decide([s.seed for _, _, s in jobs], [s.task for _, _, s in jobs], sampling, generator)
            for _ in range(self.failure_decisions)
        ]
        self.policy.train(was_training)
        n = self.policy.config.n_action_steps
        episodes = []
        for row, (g, i, s) in enumerate(jobs):
            if stop_after is not None and sum(e.success for e in episodes if e.group == g) >= stop_after:
                continue
            success = int(decisions[0][1][row, 0]) in self.answer[(s.task, context_class(s.seed))]
            d = 1 if success else self.failure_decisions
            length = d * n
            episode = Episode(
                task=s.task,
                task_description=task_description(s.task),
                init_seed=s.seed,
                group=g,
                sample=i,
                success=success,
                length=length,
                states=observation(s.seed).expand(length, -1).clone(),
                actions=torch.cat([decisions[j][3][row] for j in range(d)]).clamp(-1, 1),
                images={},
                decision_steps=torch.arange(0, length, n),
                contexts=torch.stack([decisions[j][0][row] for j in range(d)]),
                tokens=torch.stack([decisions[j][1][row] for j in range(d)]),
                logprobs=torch.stack([decisions[j][2][row] for j in range(d)]),
            )
            episodes.append(episode)
            if on_episode is not None:
                on_episode(episode)
        self.episodes_run += len(episodes)
        return RolloutResult(episodes, k, sampling, seconds=1.0, policy_seconds=1.0)

    def __enter__(self) -> BanditEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def bandit_factory(answer, engines: list[BanditEngine] | None = None, failure_decisions: int = 6):
    """A ``make_engine`` for ``run_spo`` / ``run_rsft`` that builds bandit engines with this answer."""

    def make(policy, preprocessor, postprocessor, cfg: object) -> BanditEngine:
        engine = BanditEngine(answer, policy, preprocessor, postprocessor, failure_decisions)
        if engines is not None:
            engines.append(engine)
        return engine

    return make


def success_rate(answer, policy, preprocessor, postprocessor, n_states: int = 60, k: int = 4) -> float:
    """Mean success with QueST's sampling over ``n_states`` held-out states per task."""
    engine = BanditEngine(answer, policy, preprocessor, postprocessor, failure_decisions=1)  # decision 0 decides
    tasks = sorted({task for task, _ in answer})
    states = [(t, 9_000_000 + i) for t in tasks for i in range(n_states)]
    return engine.rollout(states, k=k, seed=12345).success_rate
