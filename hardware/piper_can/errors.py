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


class ArmNotReadyError(PiperError):
    """A command was refused: feedback says a motor is disabled or the arm is not in the mode we set."""


class HighFollowError(PiperError):
    """The arm may be in high-follow (0xAD), which this firmware leaves only after a reset."""


class CollisionProtectionOffError(PiperError):
    """The arm reports its collision protection off (level 0) and the driver was told to refuse that."""


class CanBusError(PiperConnectionError):
    """The CAN controller reported bus-off (or the bus failed): nothing reaches the arm."""


class PartialCommandError(PiperError):
    """A multi-frame command stopped half-way: some of its frames are on the bus, the rest are not."""

    def __init__(self, where: str, sent: tuple[int, ...], unsent: tuple[int, ...], cause: Exception):
        self.sent = sent
        self.unsent = unsent
        self.cause = cause
        ids = ", ".join(f"0x{i:X}" for i in sent)
        missing = ", ".join(f"0x{i:X}" for i in unsent)
        super().__init__(
            f"PiPER on {where}: command stopped after {len(sent)} of {len(sent) + len(unsent)} frames "
            f"(sent {ids}; not sent {missing}): {cause}"
        )


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
