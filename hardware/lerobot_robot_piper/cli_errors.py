"""Show the driver's own errors as one line when they end a LeRobot CLI (no traceback)."""

from __future__ import annotations

import sys
from types import TracebackType

from piper_can.errors import PiperError

_previous_hook = sys.excepthook


def _one_line_hook(exc_type: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
    if isinstance(exc, PiperError):
        print(f"error: {exc}", file=sys.stderr)
    else:
        _previous_hook(exc_type, exc, tb)


def install() -> None:
    """Route uncaught ``PiperError``s to one ``error: …`` line on stderr (the exit status stays 1)."""
    sys.excepthook = _one_line_hook
