"""``python -m lerobot_cso.train ARGS``: ``lerobot-train ARGS``, with camera-free datasets served from memory.

The same training loop, checkpoints, resume and logs as ``lerobot-train`` (this calls its ``main``); only the
datasets it makes are wrapped by :func:`lerobot_cso.frames.in_memory`, which returns identical items without
LeRobot's per-item Arrow queries. The pipeline's IL stage runs this.
"""

import logging

from lerobot.configs.train import TrainPipelineConfig
from lerobot.scripts import lerobot_train

from lerobot_cso.frames import InMemoryFrames, in_memory


def main() -> None:
    make_datasets = lerobot_train.make_train_eval_datasets

    def make_in_memory(cfg: TrainPipelineConfig) -> tuple:
        train, evaluation = make_datasets(cfg)
        if cfg.dataset.streaming:
            return train, evaluation
        train, evaluation = in_memory(train), None if evaluation is None else in_memory(evaluation)
        if isinstance(train, InMemoryFrames):
            logging.info(f"lerobot_cso.train: {len(train)} frames served from memory")
        return train, evaluation

    lerobot_train.make_train_eval_datasets = make_in_memory
    lerobot_train.main()


if __name__ == "__main__":
    main()
