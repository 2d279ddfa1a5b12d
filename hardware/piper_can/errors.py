"""Exceptions raised by the PiPER driver; each message is one line that says what to do."""

from __future__ import annotations

from dataclasses import dataclass


class PiperError(Exception):
    """Base class of every error this package raises on purpose."""


class PiperConnectionError(PiperError):
    """The CAN bus could not be opened, or no PiPER answers on it."""


class EnableTimeoutError(PiperError):
    """The arm did not report its motors enabled (or CAN mode) before the handshake timed out."""


class FeedbackStaleError(PiperError):
    """The stale-feedback watchdog tripped: the driver stopped commanding the arm."""


class EmergencyStopError(PiperError):
    """A motion command was refused because the emergency stop is engaged."""


@dataclass(frozen=True, slots=True)
class Fault:
    """One fault reported by the firmware: ``part`` is ``joint_N``, ``gripper`` or ``arm``."""

    part: str
    fault: str

    def __str__(self) -> str:
        return f"{self.part}: {self.fault}"


class FirmwareFaultError(PiperError):
    """The firmware reports error bits; ``faults`` lists every part and fault."""

    def __init__(self, faults: tuple[Fault, ...]):
        self.faults = faults
        super().__init__("PiPER firmware reports " + "; ".join(str(f) for f in faults))

    @property
    def part(self) -> str:
        """The first faulty part (``joint_N``, ``gripper`` or ``arm``)."""
        return self.faults[0].part

    @property
    def fault(self) -> str:
        """The first fault's description."""
        return self.faults[0].fault
