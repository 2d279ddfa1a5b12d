"""SPO with the scripted engine, on as many processes as it is launched with (used by tests/test_distributed.py).

    [accelerate launch --multi_gpu --num_processes N] python tests/distributed_spo.py POLICY OUT ITERATIONS DIGESTS

Each process writes ``DIGESTS/rank<r>.pt``, the prior it ends with (the library itself writes on rank 0 only).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from cso_fakes import TASKS, ScriptedEngine, mixed

from lerobot_cso import distributed
from lerobot_cso.checkpoints import load_policy
from lerobot_cso.cso import spo


def main(policy_path: Path, out: Path, iterations: int, digests: Path) -> None:
    torch.set_num_threads(1)
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
    digests.mkdir(parents=True, exist_ok=True)
    prior = trained[0].prior.state_dict() if trained else {}
    torch.save(prior, digests / f"rank{distributed.state().process_index}.pt")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4]))
