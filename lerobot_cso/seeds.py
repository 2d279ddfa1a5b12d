"""Initial-state seeds: one disjoint integer range per purpose.

A MetaWorld initial state (object and goal positions) is named by ``(task, init_seed)``: resetting a task
with the same seed gives the same state, bit for bit. The integer line is split so that the states used
for demonstrations, online-training rollouts and evaluation can never coincide:

=========  ===========================  ==============================================================
purpose    range                        use
=========  ===========================  ==============================================================
demo       [0, 1_000_000)               episode ``i`` of a task's demos starts from ``DEMO.start + i``
train      [1_000_000, 2_000_000)       online rollouts: R-SFT draws from the first half, SPO from the second
eval       [2_000_000, 3_000_000)       evaluation: seed ``s`` owns the block of ``EVAL_BLOCK`` states
                                        starting at ``EVAL.start + s * EVAL_BLOCK``
demo       [3_000_000, 4_000_000)       demonstrations in a world whose small integers are its fixed
(placed)                                evaluation states (LIBERO): episode ``i`` starts from
                                        ``DEMO_PLACEMENTS.start + i``, a placement drawn from that seed
=========  ===========================  ==============================================================

LeRobot's own tools (``lerobot-eval``, ``lerobot-train --env_eval_freq``) pass small seeds
(``--seed`` + episode index); the ``cso_metaworld`` env config adds ``EVAL.start`` to them, so they land in
the evaluation range as well.
"""

from __future__ import annotations

DEMO = range(0, 1_000_000)
TRAIN = range(1_000_000, 2_000_000)
EVAL = range(2_000_000, 3_000_000)
DEMO_PLACEMENTS = range(3_000_000, 4_000_000)
EVAL_BLOCK = 10_000
TRAINING_OFFSETS = {"rsft": 0, "spo": len(TRAIN) // 2}  # each purpose's half of the training range


def _block(span: range, start: int, count: int) -> list[int]:
    """``count`` consecutive seeds of ``span`` from offset ``start``; raises if they leave the range."""
    if start < 0 or count < 0 or start + count > len(span):
        raise ValueError(f"seeds [{start}, {start + count}) exceed the {len(span)} seeds of range {span}")
    return list(span[start : start + count])


def demo_seeds(count: int, start: int = 0) -> list[int]:
    """Initial-state seeds for demonstration episodes ``start .. start + count - 1``."""
    return _block(DEMO, start, count)


def train_seeds(count: int, start: int = 0) -> list[int]:
    """Initial-state seeds for online-training rollouts ``start .. start + count - 1``."""
    return _block(TRAIN, start, count)


def training_seeds(purpose: str, start: int, count: int) -> list[int]:
    """Initial-state seeds ``start .. start + count - 1`` of one online-training purpose (``rsft`` or ``spo``)."""
    if start + count > len(TRAIN) // 2:
        raise ValueError(f"{purpose} seeds [{start}, {start + count}) exceed its {len(TRAIN) // 2} training states")
    return train_seeds(count, TRAINING_OFFSETS[purpose] + start)


def round_seed(seed: int, index: int) -> int:
    """The sampling seed of one rollout round: the run's ``seed`` mixed with the round's ``index``."""
    return seed * 1_000_003 + index


def eval_seeds(count: int, eval_seed: int = 0) -> list[int]:
    """The first ``count`` evaluation initial states of evaluation seed ``eval_seed``."""
    if count > EVAL_BLOCK:
        raise ValueError(f"at most {EVAL_BLOCK} evaluation episodes per task and seed, got {count}")
    return _block(EVAL, eval_seed * EVAL_BLOCK, count)
