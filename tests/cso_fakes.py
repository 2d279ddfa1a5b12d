"""Test doubles for the CSO stages: a tiny saved MetaWorld-shaped policy and a scripted rollout engine."""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from types import SimpleNamespace

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from safetensors.torch import load_file
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso.policy import CSOConfig, CSOPolicy
from lerobot_cso.rollout.engine import Episode, InitialState, RolloutResult
from lerobot_cso.sampling import Sampling
from lerobot_cso.worlds.metaworld.tasks import task_description

TASKS = ("reach-v3", "button-press-v3")


def save_tiny_metaworld_policy(path: Path, seed: int = 0) -> Path:
    """A tiny untrained cso policy with MetaWorld shapes (state 39, action 4), saved with processors."""
    torch.manual_seed(seed)
    config = CSOConfig(
        **TINY_POLICY_KWARGS,
        device="cpu",
        push_to_hub=False,
        n_autoencoder_steps=0,
        tasks=[task_description(t) for t in TASKS],
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (39,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    stats = {
        "observation.state": {"mean": torch.zeros(39), "std": torch.ones(39)},
        "action": {"min": -torch.ones(4), "max": torch.ones(4)},
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    CSOPolicy(config).save_pretrained(path)
    pre.save_pretrained(path)
    post.save_pretrained(path)
    return path


def mixed(task: str, seed: int, sample: int) -> bool:
    """Odd seeds: samples 0 and 1 of 4 succeed; seeds = 0 mod 4 all fail; seeds = 2 mod 4 all succeed."""
    if seed % 2:
        return sample < 2
    return seed % 4 == 2


class ScriptedEngine:
    """Stands in for RolloutEngine: success of (task, seed, sample) comes from ``outcome``; the episode
    content (states, tokens, contexts) is random but seeded by (task, seed, sample)."""

    def __init__(
        self,
        outcome: Callable[[str, int, int], bool],
        length: int = 20,
        crash_after: int | None = None,
        policy: CSOPolicy | None = None,
    ) -> None:
        self.outcome = outcome
        self.length = length
        self.crash_after = crash_after
        self.policy = policy
        self.calls: list[list[InitialState]] = []
        self.delivered = 0

    def episode(self, task: str, seed: int, group: int, sample: int, n_action_steps: int = 8) -> Episode:
        g = torch.Generator().manual_seed(hash((task, seed, sample)) % 2**31)
        length = self.length + sample
        steps = torch.arange(0, length, n_action_steps)
        d = len(steps)
        context = torch.randn(d, 2, 48, generator=g)
        tokens = torch.randint(0, 1000, (d, 8), generator=g)
        logprobs = -torch.rand(d, 8, generator=g)
        inputs: dict[str, torch.Tensor] = {}
        if self.policy is not None:
            with torch.no_grad():
                if not self.policy.config.freeze_encoders:  # as the engine: keep the inputs, encode them
                    inputs = {"observation.state": torch.randn(d, 39, generator=g)}
                    context = self.policy.encode_context(inputs | {"task": [task_description(task)] * d})
                tokens, logprobs = self.policy.sample_skills(context, generator=g)
        return Episode(
            task=task,
            task_description=task_description(task),
            init_seed=seed,
            group=group,
            sample=sample,
            success=self.outcome(task, seed, sample),
            length=length,
            states=torch.randn(length, 39, generator=g),
            actions=torch.rand(length, 4, generator=g) * 2 - 1,
            images={},
            decision_steps=steps,
            contexts=context,
            tokens=tokens,
            logprobs=logprobs,
            inputs=inputs,
        )

    def rollout(
        self,
        initial_states: Sequence[InitialState],
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
        self.calls.append(states)
        episodes = []
        for g, s in enumerate(states):
            for i in range(k):
                if stop_after is not None and sum(e.success for e in episodes if e.group == g) >= stop_after:
                    break
                if self.crash_after is not None and self.delivered >= self.crash_after:
                    raise KeyboardInterrupt("simulated crash")
                episode = self.episode(s.task, s.seed, g, i)
                episodes.append(episode)
                self.delivered += 1
                if on_episode is not None:
                    on_episode(episode)
        return RolloutResult(episodes, k, sampling, seconds=1.0, policy_seconds=0.5)

    def __enter__(self) -> ScriptedEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


class TorchWhereCudaIsAvailable:
    """``torch`` as a module sees it on a GPU machine: ``torch.cuda`` reports a GPU and a 3 GiB peak."""

    cuda = SimpleNamespace(
        is_available=lambda: True,
        reset_peak_memory_stats=lambda *args, **kwargs: None,
        max_memory_allocated=lambda *args, **kwargs: 3 * 1024**3,
    )

    def __getattr__(self, name: str):
        return getattr(torch, name)


def saved_weights(checkpoint: Path, prefix: str) -> dict[str, torch.Tensor]:
    """The tensors of a saved policy's ``model.safetensors`` whose names start with ``prefix``."""
    return {k: v for k, v in load_file(checkpoint / "model.safetensors").items() if k.startswith(prefix)}
