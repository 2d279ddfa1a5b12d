"""Bad user input: ``UsageError``, whose message ``lerobot-cso`` prints as one line before exiting non-zero, and
draccus's parse errors turned into it."""

from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

from draccus.wrappers.suppressing_argparse import SuppressingArgumentParser


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
