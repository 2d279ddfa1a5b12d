"""Bad user input: ``UsageError``, whose message ``lerobot-cso`` prints as one line before exiting non-zero,
draccus's parse errors turned into it, and :func:`check_number`, the one check of a numeric setting."""

import math
import operator
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

from draccus.wrappers.suppressing_argparse import SuppressingArgumentParser

COMPARISONS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}


class UsageError(Exception):
    """Bad user input (unknown task, impossible count, conflicting output dir, ...)."""


@contextmanager
def parse_errors_as_usage_errors() -> Iterator[None]:
    """Make draccus's parser raise its error as a ``UsageError`` instead of printing every option first."""

    def error(parser: SuppressingArgumentParser, message: str) -> NoReturn:
        raise UsageError(message)

    original = SuppressingArgumentParser.error
    SuppressingArgumentParser.error = error  # type: ignore[method-assign]
    try:
        yield
    finally:
        SuppressingArgumentParser.error = original  # type: ignore[method-assign]


def check_number(
    name: str,
    value: float | None,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    optional: bool = False,
    error: type[Exception] = UsageError,
) -> None:
    """Raise ``error`` unless ``value`` is a finite number within the bounds given (> ``gt``, >= ``ge``, < ``lt``,
    <= ``le``), or None when ``optional``. NaN fails every bound, unlike a check written ``value <= 0``."""
    if value is None and optional:
        return
    bounds = {symbol: bound for symbol, bound in zip(COMPARISONS, (gt, ge, lt, le), strict=True) if bound is not None}
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and all(COMPARISONS[s](value, b) for s, b in bounds.items())):
        wanted = " ".join(["a finite number", " and ".join(f"{symbol} {bound:g}" for symbol, bound in bounds.items())])
        raise error(f"{name} must be {wanted.strip()}{' (or null)' if optional else ''}, got {value}")
