"""Policy-driven rollouts: "roll out this policy from these initial states, K times each".

Every later stage (R-SFT, SPO, evaluation) goes through :meth:`RolloutEngine.rollout`, whatever the world: the
engine drives a :class:`~lerobot_cso.rollout.backend.RolloutBackend` (a simulated world's env pool, a robot) that
it is given: it knows no world and no stage. The K episodes of a group all start from the
same initial state ``(task, seed)``; per episode the engine returns the
observations and executed actions of every step, and per decision (every ``n_action_steps`` steps) the
encoder context the skill was sampled from, the sampled tokens and their sampling log-probs, so that
``policy.token_logprobs(context, tokens, sampling)`` recomputes them with gradients.

Inference is batched across all envs: episodes start on multiples of ``n_action_steps``, so each decision round
is one call of the policy hooks (the :class:`SkillPolicy` contract)::

    ctx = policy.encode_context(preprocessor(obs))          # (B, P, d)
    tokens, logp = policy.sample_skills(ctx, sampling, generator)
    actions = postprocessor(policy.decode_skills(tokens, n_action_steps))

Sampling draws from one ``torch.Generator`` seeded per call: a call is reproducible given the same
initial states, K, sampling settings, seed and number of envs.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.utils.constants import OBS_IMAGE
from torch import Tensor

from lerobot_cso.rollout.backend import ActiveSkill, Job, RolloutBackend, Trace
from lerobot_cso.sampling import Sampling


class InitialState(NamedTuple):
    """An initial state: a task and its world's id for the state (MetaWorld: the seed placing objects and goal)."""

    task: str
    seed: int


@dataclass
class Episode:
    """One rolled-out episode; ``states[t]`` (and ``images[cam][t]``) is what ``actions[t]`` was chosen from."""

    task: str
    task_description: str
    init_seed: int
    group: int  # index of the initial state in the request
    sample: int  # 0 .. K-1 within the group
    success: bool
    length: int  # env steps executed
    states: Tensor  # (length, S) float32, raw (unnormalised) state observations
    actions: Tensor  # (length, A) float32, executed actions (unnormalised, as the backend executed them)
    images: dict[str, Tensor]  # camera -> (length, H, W, 3) uint8; empty without cameras
    decision_steps: Tensor  # (D,) int64, the step at which each skill was sampled
    contexts: Tensor  # (D, P, d) float32, encoder output the skill was sampled from
    tokens: Tensor  # (D, n_tokens) int64
    logprobs: Tensor  # (D, n_tokens) float32, log-probs under the distribution sampled from
    # The encoders' preprocessed inputs of each decision, {key: (D, ...)}: kept only by an engine asked to keep them
    # (SPO without the encoder freeze recomputes the contexts from them, with gradients); empty otherwise.
    inputs: dict[str, Tensor] = field(default_factory=dict)


@dataclass
class RolloutResult:
    """All episodes of one call, ordered by (group, sample), with throughput figures."""

    episodes: list[Episode]
    k: int  # samples asked per group
    sampling: Sampling
    seconds: float
    policy_seconds: float

    @property
    def env_steps(self) -> int:
        return sum(e.length for e in self.episodes)

    @property
    def decisions(self) -> int:
        return sum(len(e.decision_steps) for e in self.episodes)

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.seconds

    @property
    def decisions_per_s(self) -> float:
        return self.decisions / self.seconds

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes]))

    def groups(self) -> list[list[Episode]]:
        """The episodes grouped by initial state: ``groups()[g]`` holds the samples of state ``g`` (K of them,
        fewer when the call stopped groups early)."""
        return [list(group) for _, group in itertools.groupby(self.episodes, key=lambda e: e.group)]


class SkillPolicy(Protocol):
    """What the engine and the CSO stages need of a policy (``CSOPolicy`` implements it)."""

    config: Any  # n_action_steps, n_tokens, device, input_features
    training: bool

    def encode_context(self, batch: dict[str, Any]) -> Tensor:
        """Encoder context ``(B, P, d)`` of a preprocessed observation batch."""

    def sample_skills(
        self, context: Tensor, sampling: Sampling, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """Sampled tokens ``(B, n)`` and their log-probs under the distribution sampled from."""

    def token_logprobs(self, context: Tensor, tokens: Tensor, sampling: Sampling) -> Tensor:
        """Teacher-forced per-token log-probs ``(B, n)`` under ``sampling``'s distribution, with gradients."""

    def decode_skills(self, tokens: Tensor, n_actions: int | None = None) -> Tensor:
        """Normalised actions ``(B, n_actions, A)`` of the skills."""

    def train(self, mode: bool = True) -> Any: ...

    def eval(self) -> Any: ...


class SkillSampler:
    """A policy and its processors: one batched skill decision from raw observations."""

    def __init__(self, policy: SkillPolicy, preprocessor: Any, postprocessor: Any, keep_inputs: bool = False) -> None:
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.keep_inputs = keep_inputs

    @torch.no_grad()
    def decide(
        self,
        obs: dict[str, Any],
        rows: list[int],
        descriptions: list[str],
        sampling: Sampling,
        generator: torch.Generator,
    ) -> tuple[Tensor, Tensor, Tensor, np.ndarray, dict[str, Tensor]]:
        """One batched decision for env ``rows``: contexts, tokens, log-probs (CPU), action chunks, and the
        encoders' preprocessed inputs (CPU; only when ``keep_inputs``)."""
        raw: dict[str, Any] = {"agent_pos": obs["agent_pos"][rows]}
        if "pixels" in obs:
            pixels = {cam: image[rows] for cam, image in obs["pixels"].items()}
            raw["pixels"] = single_camera(pixels) if OBS_IMAGE in self.policy.config.input_features else pixels
        batch = preprocess_observation(raw)
        batch["task"] = [descriptions[r] for r in rows]
        batch = self.preprocessor(batch)
        context = self.policy.encode_context(batch)
        tokens, logprobs = self.policy.sample_skills(context, sampling, generator)
        chunk = self.policy.decode_skills(tokens, self.policy.config.n_action_steps)  # executed prefix only
        flat = self.postprocessor(chunk.reshape(-1, chunk.shape[-1]))
        chunks = flat.reshape(chunk.shape).float().cpu().numpy()
        features = self.policy.config.input_features
        inputs = {k: v.cpu() for k, v in batch.items() if k in features} if self.keep_inputs else {}
        return context.float().cpu(), tokens.cpu(), logprobs.float().cpu(), chunks, inputs


def single_camera(pixels: dict[str, np.ndarray]) -> np.ndarray:
    """The frames of the one camera in ``pixels``, for a policy reading LeRobot's single-camera key
    ``observation.image``: LeRobot's envs with one camera give it as a bare ``pixels`` array, which
    ``preprocess_observation`` maps to that key (the world chose the camera: the one its LeRobot env renders)."""
    if len(pixels) != 1:
        raise ValueError(
            f"a policy reading {OBS_IMAGE} reads one camera; the backend gives {', '.join(pixels) or 'none'}"
        )
    return next(iter(pixels.values()))


class _PolicyController:
    """Backend controller: one batched skill decision for every active slot, executed as an action chunk.

    Backends start episodes only on multiples of ``n_action_steps``, so every call is a decision step of
    every running episode.
    """

    def __init__(
        self,
        sampler: SkillSampler,
        num_envs: int,
        describe: Callable[[str], str],
        sampling: Sampling,
        generator: torch.Generator,
    ) -> None:
        self.sampler = sampler
        self.describe = describe
        self.sampling = sampling
        self.generator = generator
        self.steps = np.zeros(num_envs, dtype=np.int64)
        self.descriptions: list[str] = [""] * num_envs
        self.decisions: list[list[tuple[int, Tensor, Tensor, Tensor, dict[str, Tensor]]]] = [
            [] for _ in range(num_envs)
        ]
        self.policy_seconds = 0.0

    def start(self, slot: int, job: Job) -> None:
        self.steps[slot] = 0
        self.descriptions[slot] = self.describe(job.task)
        self.decisions[slot] = []

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        started = time.perf_counter()
        rows = np.flatnonzero(active).tolist()
        contexts, tokens, logprobs, chunks, inputs = self.sampler.decide(
            obs, rows, self.descriptions, self.sampling, self.generator
        )
        actions = np.zeros((len(active), *chunks.shape[1:]), dtype=np.float32)
        for i, slot in enumerate(rows):
            mine = {key: value[i] for key, value in inputs.items()}
            self.decisions[slot].append((int(self.steps[slot]), contexts[i], tokens[i], logprobs[i], mine))
            actions[slot] = chunks[i]
            self.steps[slot] += chunks.shape[1]
        self.policy_seconds += time.perf_counter() - started
        return actions

    def current_skill(self, slot: int) -> ActiveSkill | None:
        if not self.decisions[slot]:
            return None
        step, _, tokens, _, _ = self.decisions[slot][-1]
        return ActiveSkill(len(self.decisions[slot]) - 1, step, tuple(tokens.tolist()))

    def finish(self, slot: int) -> dict[str, Tensor]:
        steps, contexts, tokens, logprobs, inputs = zip(*self.decisions[slot], strict=True)
        return {
            "decision_steps": torch.tensor(steps, dtype=torch.int64),
            "contexts": torch.stack(contexts),
            "tokens": torch.stack(tokens),
            "logprobs": torch.stack(logprobs),
        } | ({"inputs": {key: torch.stack([d[key] for d in inputs]) for key in inputs[0]}} if inputs[0] else {})


def _episode(trace: Trace, describe: Callable[[str], str]) -> Episode:
    group, sample = trace.job.key
    return Episode(
        task=trace.job.task,
        task_description=describe(trace.job.task),
        init_seed=trace.job.init_seed,
        group=group,
        sample=sample,
        success=trace.success,
        length=trace.length,
        states=torch.from_numpy(trace.states),
        actions=torch.from_numpy(trace.actions),
        images={cam: torch.from_numpy(frames) for cam, frames in trace.images.items()},
        **trace.record,
    )


class RolloutEngine:
    """A policy, its processors and a rollout backend; reused across calls (models stay built).

    ``describe`` maps a task name to the language instruction the policy is conditioned on.
    """

    def __init__(
        self,
        policy: SkillPolicy,
        preprocessor: Any,
        postprocessor: Any,
        backend: RolloutBackend,
        describe: Callable[[str], str],
        keep_inputs: bool = False,
    ) -> None:
        self.policy = policy
        self.sampler = SkillSampler(policy, preprocessor, postprocessor, keep_inputs)
        self.backend = backend
        self.describe = describe

    def rollout(
        self,
        initial_states: Sequence[InitialState | tuple[str, int]],
        k: int = 1,
        sampling: Sampling = Sampling(),  # noqa: B008  (a frozen dataclass)
        seed: int = 0,
        progress: str | None = None,
        on_episode: Callable[[Episode], None] | None = None,
        stop_after: int | None = None,
        keep_frames: Collection[int] = (),
        round_id: int | None = None,
    ) -> RolloutResult:
        """Roll the policy out ``k`` times from each initial state; episodes come back ordered by (group, sample).

        The episodes of the initial states at the indices ``keep_frames`` keep their camera frames even when the
        backend records none (frames between decisions then repeat the decision's).

        ``on_episode`` is called with each episode as soon as it finishes (in finishing order). With
        ``stop_after``, a group whose finished samples hold that many successes starts no more samples: the
        ones not started are absent from the result. ``round_id`` names this call's round in a backend's journal
        (:class:`~lerobot_cso.rollout.backend.Job`), for callers that draw an initial state again in later calls.
        """
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        if stop_after is not None and stop_after < 1:
            raise ValueError(f"stop_after must be >= 1, got {stop_after}")
        states = [InitialState(*s) for s in initial_states]
        jobs = [Job(s.task, s.seed, (g, i), g in keep_frames, round_id) for g, s in enumerate(states) for i in range(k)]
        successes = [0] * len(states)
        skipped: set[int] = set()

        def skip(job: Job) -> bool:
            group, sample = job.key
            if stop_after is None or successes[group] < stop_after:
                return False
            skipped.add(group * k + sample)
            return True

        device = torch.device(self.policy.config.device or "cpu")
        generator = torch.Generator(device=device).manual_seed(seed)
        controller = _PolicyController(self.sampler, self.backend.num_envs, self.describe, sampling, generator)
        was_training = self.policy.training
        self.policy.eval()
        started = time.perf_counter()
        episodes: list[Episode] = [None] * len(jobs)  # type: ignore[list-item]
        try:
            for index, trace in self.backend.run(jobs, controller, self.policy.config.n_action_steps, progress, skip):
                episodes[index] = _episode(trace, self.describe)
                successes[index // k] += trace.success
                if on_episode is not None:
                    on_episode(episodes[index])
        finally:
            self.policy.train(was_training)
        missing = {i for i, e in enumerate(episodes) if e is None} - skipped
        if missing:
            raise RuntimeError(f"the backend returned no episode for {len(missing)} jobs it did not skip")
        run = [e for e in episodes if e is not None]
        return RolloutResult(run, k, sampling, time.perf_counter() - started, controller.policy_seconds)

    def close(self) -> None:
        self.backend.close()

    def __enter__(self) -> RolloutEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
