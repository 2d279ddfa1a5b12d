"""Bad user input: ``UsageError``, whose message ``lerobot-cso`` prints as one line before exiting non-zero,
draccus's parse errors turned into it (and a cso policy config's refusal made one line in LeRobot's own commands,
:func:`one_line_policy_refusals`), and :func:`check_number`, the one check of a numeric setting; and
:func:`check_output_dir` and :func:`check_config_path`; and :func:`interruptible`, which names the work a Ctrl-C
stopped for that line."""

import functools
import math
import operator
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import draccus
from draccus.cfgparsing import load_config
from draccus.utils import ParsingError
from draccus.wrappers.suppressing_argparse import SuppressingArgumentParser

COMPARISONS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}


class UsageError(Exception):
    """Bad user input (unknown task, impossible count, conflicting output dir, ...)."""


class EnvWorkerError(RuntimeError):
    """An env worker process failed (its env raised, or the process died): the worker printed its traceback."""


@contextmanager
def parse_errors_as_usage_errors() -> Iterator[None]:
    """Make draccus's parser raise its error as a ``UsageError`` instead of printing every option first, and its
    decoding errors (a value of the wrong type, a config class that refuses its arguments) too, with their cause,
    instead of LeRobot's exit code 1 or draccus's "Couldn't instantiate class" that hides which value and why."""

    def error(parser: SuppressingArgumentParser, message: str) -> NoReturn:
        raise UsageError(message)

    def parse(*args: Any, **kwargs: Any) -> Any:
        try:
            return original_parse(*args, **kwargs)
        except ParsingError as e:
            raise UsageError(_with_causes(e)) from None

    global _usage_errors_raised
    original, original_parse = SuppressingArgumentParser.error, draccus.parse
    SuppressingArgumentParser.error = error  # type: ignore[method-assign]
    draccus.parse = parse
    _usage_errors_raised += 1
    try:
        yield
    finally:
        SuppressingArgumentParser.error = original  # type: ignore[method-assign]
        draccus.parse = original_parse
        _usage_errors_raised -= 1


_usage_errors_raised = 0  # how many parse_errors_as_usage_errors blocks are open


def policy_refusal(error: BaseException | None) -> str | None:
    """Why a cso policy config refused its settings (its ``ValueError``), where ``error``, a draccus parse error,
    ends in that refusal; draccus hides the reason in the chain of errors behind "Couldn't instantiate class"."""
    while error is not None:
        cause = error.__cause__ or error.__context__
        refused = str(error).startswith("Couldn't instantiate class CSOConfig")
        if isinstance(error, ParsingError) and refused and isinstance(cause, ValueError):
            return " ".join(str(cause).split())
        error = cause
    return None


def one_line_policy_refusals(parse: Callable[..., Any]) -> Callable[..., Any]:
    """``draccus.parse`` whose failure to make a cso policy config (``lerobot-train --policy.type=cso
    --policy.image_resize=0``) is one ``error: cso policy: <why>`` line and exit code 2, as ``lerobot-cso``'s bad
    input (inside it: its ``UsageError``), instead of LeRobot's exit code 1 after draccus's "Couldn't instantiate
    class CSOConfig using the given arguments", which hides which value and why. The cso plugin installs it."""

    @functools.wraps(parse)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        try:
            return parse(*args, **kwargs)
        except ParsingError as e:
            reason = policy_refusal(e)
            if reason is None:
                raise
            if _usage_errors_raised:
                raise UsageError(f"cso policy: {reason}") from None
            print(f"error: cso policy: {reason}", file=sys.stderr)
            raise SystemExit(2) from None

    return wrapped


def _with_causes(error: BaseException) -> str:
    """``error``'s message followed by its causes', on one line."""
    messages = []
    while error is not None:
        messages.append(" ".join(str(error).split()).rstrip("."))
        error = error.__cause__
    return ": ".join(messages)


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


def check_config_path(args: list[str]) -> None:
    """Refuse a ``--config_path=FILE`` that cannot be read or is not a mapping of settings, naming the file, before
    LeRobot's parser and draccus read it (they end in a traceback)."""
    for arg in args:
        if not arg.startswith("--config_path="):
            continue
        path = Path(arg.removeprefix("--config_path="))
        try:
            with open(path, encoding="utf-8") as f:
                settings = load_config(f, file=path)
        except OSError as e:
            raise UsageError(f"--config_path={path}: {e.strerror}") from None
        except (ParsingError, ValueError) as e:  # not YAML / JSON / TOML, or not UTF-8
            cause = e.__cause__ or e
            raise UsageError(
                f"--config_path={path} is not a valid config file ({' '.join(str(cause).split())})"
            ) from None
        if not isinstance(settings, dict):
            held = "nothing" if settings is None else f"a {type(settings).__name__}"
            raise UsageError(f"--config_path={path} must hold a mapping of settings (key: value), not {held}")


@contextmanager
def interruptible(where: str) -> Iterator[None]:
    """Name the work inside the block on a ``KeyboardInterrupt`` that stops it (the innermost block names it)."""
    try:
        yield
    except KeyboardInterrupt as e:
        if interrupted_where(e) is None:
            e.add_note(where)
        raise


def interrupted_where(error: KeyboardInterrupt) -> str | None:
    """What :func:`interruptible` named, if anything."""
    notes = getattr(error, "__notes__", None)
    return notes[0] if notes else None


def check_output_dir(path: Path, flag: str = "--output_dir") -> None:
    """Refuse an output directory that cannot be made or written into (a file, or under a read-only directory),
    before any work rather than at the first write. Writing is tried (a directory made and removed at once in the
    nearest existing one), as permission bits do not tell: root ignores them, and /proc or /sys refuse root too."""
    existing = path.absolute()
    if not existing.resolve().name:
        raise UsageError(f"{flag}={path} is the root of the file system: choose a directory of the run's own")
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{flag}={path}: {existing} is a file, not a directory")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".write-test-", dir=existing))
    except OSError as e:
        raise UsageError(f"{flag}={path}: {existing} is not writable ({e.strerror})") from None
