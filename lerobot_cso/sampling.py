"""How skills are drawn from the prior: one type from a stage's settings down to the policy's sampler."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot_cso.errors import UsageError, check_number


@dataclass(frozen=True)
class Sampling:
    """Top-k sampling at a temperature (QueST: k=5, T=1), or greedy (argmax); ``top_k`` null: every code.

    It also names the distribution a likelihood is taken under (temperature and top-k; ``greedy`` unused there)."""

    temperature: float = 1.0
    top_k: int | None = 5
    greedy: bool = False

    def check(self, prefix: str = "", error: type[Exception] = UsageError) -> None:
        """Raise ``error`` naming the setting (``<prefix>temperature``, ...) unless the temperature is > 0 and
        top-k >= 1 or null."""
        check_number(f"{prefix}temperature", self.temperature, gt=0, error=error)
        check_number(f"{prefix}top_k", self.top_k, ge=1, optional=True, error=error)


FULL = Sampling(top_k=None)  # the whole softmax at temperature 1
