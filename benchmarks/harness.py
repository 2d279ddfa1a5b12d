"""What the benchmarks here share: the 95 % interval of a paired difference, the record of how a results file
was made (the commit, the machine and the date of its latest run; the benchmark keeps its own commands), and a
checkpoint's skill autoencoder as an action filter (the skill-replay benchmarks of the twin and of LIBERO).

A benchmark run as ``python benchmarks/<script>.py`` imports this module by name (its folder is on ``sys.path``).
"""

import datetime
import math
import os
import platform
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.lerobot_types import TransitionKey
from lerobot.processor import NormalizerProcessorStep
from lerobot.processor.converters import create_transition

from lerobot_cso.checkpoints import load_policy

ROOT = Path(__file__).resolve().parents[1]
# Student t quantiles for a two-sided 95 % interval, by degrees of freedom (a paired difference over a few seeds)
T_975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228}
Z_975 = 1.96  # the normal quantile (a paired difference over many trials)


def mean_ci(diffs: Sequence[float], student: bool) -> dict[str, Any]:
    """The mean of paired differences and its 95 % interval, mean ± q · s / √n (s the sample standard deviation):
    q from Student's t with n − 1 degrees of freedom (``student``: few pairs, e.g. training seeds) or 1.96 (many
    pairs, e.g. trials). ``ci95`` is None for one difference."""
    n = len(diffs)
    if n == 0:
        raise ValueError("mean_ci: no differences")
    mean = sum(diffs) / n
    if n < 2:
        return {"mean": mean, "ci95": None}
    if student and n - 1 not in T_975:
        raise ValueError(f"mean_ci: no t quantile for {n - 1} degrees of freedom (at most {max(T_975)})")
    sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1))
    half = (T_975[n - 1] if student else Z_975) * sd / math.sqrt(n)
    return {"mean": mean, "ci95": [mean - half, mean + half]}


def provenance() -> dict[str, str | None]:
    """Where and when this run is: the commit checked out (None outside a git checkout), the machine, the date."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    machine = f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}"
    return {"commit": commit, "machine": machine, "date": datetime.date.today().isoformat()}


class Reconstruction:
    """A checkpoint's autoencoder as an action filter: raw actions (T, A) → the decoded executed prefixes (T, A)."""

    def __init__(self, path: str) -> None:
        self.policy, pre, self.post = load_policy(path)
        self.policy.eval()
        self.normalize = next(s for s in pre.steps if isinstance(s, NormalizerProcessorStep))

    @torch.no_grad()
    def __call__(self, actions: np.ndarray) -> np.ndarray:
        cfg = self.policy.config
        raw = torch.as_tensor(actions, dtype=torch.float32)
        normalized = self.normalize(create_transition(action=raw))[TransitionKey.ACTION]
        out = []
        for start in range(0, len(raw), cfg.n_action_steps):
            chunk = normalized[start : start + cfg.chunk_size]  # padded with its last action, as the dataset pads
            chunk = torch.cat([chunk, chunk[-1:].expand(cfg.chunk_size - len(chunk), -1)])
            decoded, _ = self.policy.autoencoder(chunk[None])
            out.append(self.post(decoded[0, : cfg.n_action_steps]))
        return torch.cat(out)[: len(raw)].numpy()
