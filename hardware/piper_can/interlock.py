"""What may reach the arm now: the e-stop (counted) and the motion latch, under one lock.

An e-stop request is counted, so an operation that began before it (a ``resume``, an ``enable``) can
tell it happened, however short, and abort. The motion latch closes for a reset, a disable, a
disconnect, a foreign reset or a possible high-follow, and opens only when an enable confirms, and
only if no e-stop was requested since that enable began. The driver checks both under its send lock
before every motion frame.
"""

from __future__ import annotations

import threading

NOT_ENABLED = "enable() has not confirmed the motors and the mode yet"


class Interlock:
    """Thread-safe e-stop count and motion latch (a reason, or None when motion is allowed)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._estops = 0
        self._estopped = False
        self._latch: str | None = NOT_ENABLED

    @property
    def estops(self) -> int:
        """How many e-stops were requested so far (a token: compare it later)."""
        return self._estops

    @property
    def estopped(self) -> bool:
        return self._estopped

    @property
    def latch(self) -> str | None:
        """Why motion is latched off, or None."""
        return self._latch

    def stop(self) -> None:
        """Count an e-stop request and engage the e-stop (it wins over any operation in flight)."""
        with self._lock:
            self._estops += 1
            self._estopped = True

    def close(self, reason: str) -> None:
        """Latch motion off until the next confirmed enable."""
        with self._lock:
            self._latch = reason

    def stopped_since(self, token: int) -> bool:
        """Whether an e-stop was requested after ``token`` was taken."""
        return self._estops != token

    def open(self, token: int, clear_estop: bool) -> bool:
        """Allow motion again (and, for a resume, clear the e-stop), unless an e-stop was requested
        since ``token``; returns whether it did."""
        with self._lock:
            if self._estops != token:
                return False
            self._latch = None
            if clear_estop:
                self._estopped = False
            return True
