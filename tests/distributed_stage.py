"""SPO or R-SFT with the scripted engine, on as many processes as it is launched with (tests/test_distributed.py).

    [accelerate launch --multi_gpu --num_processes N] tests/distributed_stage.py STAGE POLICY OUT LENGTH DIGESTS

STAGE is spo, rsft or rsft_adv (R-SFT with ``advantage_weighted``); LENGTH is SPO's iterations or R-SFT's epochs.

Each process writes ``DIGESTS/rank<r>.pt``, the weights its replica ends with (the library itself writes on
rank 0 only): the prior after SPO, the whole policy after R-SFT; after R-SFT also ``DIGESTS/drawn_rank<r>.pt``,
the skill tokens of every decision its fine-tune trained on, in order.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from cso_fakes import TASKS, ScriptedEngine, mixed

from lerobot_cso import distributed
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso import rsft, spo
from lerobot_cso.policy import CSOPolicy
from lerobot_cso.policy.configuration_cso import SKILL_TOKENS_KEY


def run_spo(policy_path: Path, out: Path, iterations: int) -> dict[str, torch.Tensor]:
    cfg = spo.SPOConfig(
        tasks=",".join(TASKS),
        output_dir=out,
        iterations=iterations,
        groups_per_iteration=3,
        group_size=4,
        epochs=2,
        minibatch_trajectories=5,
        lr=1e-3,
        max_draw_factor=4,
    )
    cfg.policy = load_policy(policy_path)[0].config
    cfg.policy.pretrained_path = policy_path
    trained = []

    def make_engine(policy, pre, post, settings) -> ScriptedEngine:
        trained.append(policy)
        return ScriptedEngine(mixed, policy=policy)

    spo.run_spo(cfg, make_engine=make_engine)
    return trained[0].prior.state_dict() if trained else {}


def run_rsft(
    policy_path: Path, out: Path, epochs: int, digests: Path, advantage_weighted: bool = False
) -> dict[str, torch.Tensor]:
    cfg = rsft.RSFTConfig(
        tasks=",".join(TASKS),
        output_dir=out,
        successes_per_task=3,
        n_strikes=4,
        states_per_round=1,
        epochs=epochs,
        batch_size=4,
        lr=1e-3,
        min_lr=1e-4,
        advantage_weighted=advantage_weighted,
    )
    cfg.policy = load_policy(policy_path)[0].config
    cfg.policy.pretrained_path = policy_path
    frozen: list[CSOPolicy] = []
    freeze = CSOPolicy.set_encoders_frozen

    def record_frozen(self: CSOPolicy, value: bool) -> None:  # the replica R-SFT ends with, on every process
        freeze(self, value)
        if value:
            frozen.append(self)

    drawn: list[torch.Tensor] = []
    update = rsft.update_policy

    def record_drawn(tracker, policy, batch, *args, **kwargs):  # the decisions this process trains on
        drawn.append(batch[SKILL_TOKENS_KEY].clone())
        return update(tracker, policy, batch, *args, **kwargs)

    CSOPolicy.set_encoders_frozen = record_frozen
    rsft.update_policy = record_drawn
    rsft.run_rsft(cfg, make_engine=lambda policy, pre, post, settings: ScriptedEngine(mixed))
    digests.mkdir(parents=True, exist_ok=True)
    torch.save(torch.cat(drawn), digests / f"drawn_rank{distributed.state().process_index}.pt")
    return frozen[-1].state_dict()


def main(stage: str, policy_path: Path, out: Path, length: int, digests: Path) -> None:
    torch.set_num_threads(1)
    if stage == "spo":
        weights = run_spo(policy_path, out, length)
    else:
        weights = run_rsft(policy_path, out, length, digests, advantage_weighted=stage == "rsft_adv")
    digests.mkdir(parents=True, exist_ok=True)
    torch.save(weights, digests / f"rank{distributed.state().process_index}.pt")


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), Path(sys.argv[5]))
