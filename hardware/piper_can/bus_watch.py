"""What the bus shows of resets and of other hosts beyond the feedback values: another host's resets
(0x150 02) and mode changes (0x151), every distinct one kept with its newest stamp (one frame cannot hide
an earlier one), and the evidence that a reset's delayed motor-off has happened.
"""

from __future__ import annotations

from .codec import ID_EMERGENCY_STOP, ID_MODE_CONTROL, MIT_MODE_HIGH_FOLLOW, EStopAction, ModeControl, decode_command
from .link import PiperLink
from .settings import FEEDBACK_PERIOD_S
from .state import ArmState

# Feedback stamped this long after a reset was sent after the firmware acted on it (it handles host frames
# within its 5 ms cycle): only such a frame showing a motor on proves the reset's countdown is still running.
RESET_ACTED_WITHIN_S = 2 * FEEDBACK_PERIOD_S


class ForeignFrames:
    """Another host's (a plugged-in leader's, a vendor script's) resets and mode changes, as ``link`` caches them."""

    def __init__(self, link: PiperLink) -> None:
        self._link = link

    def modes_since(self, since: float) -> list[ModeControl]:
        """Every distinct mode change (0x151) another host (a plugged-in leader) sent after ``since``, oldest first."""
        payloads = self._link.cache.payloads_since(ID_MODE_CONTROL, since)
        found = (decode_command(ID_MODE_CONTROL, data) for data, _ in payloads)
        return [mode for mode in found if isinstance(mode, ModeControl)]

    def high_follow_since(self, since: float) -> bool:
        """Whether another host (a plugged-in leader) asked for high-follow (0x151 … AD) after ``since``."""
        return any(mode.mit_mode == MIT_MODE_HIGH_FOLLOW for mode in self.modes_since(since))

    def reset_since(self, since: float) -> float | None:
        """When another host last reset the arm (0x150 02), if after ``since`` (a later e-stop hides nothing)."""
        payloads = self._link.cache.payloads_since(ID_EMERGENCY_STOP, since)
        return max((stamp for data, stamp in payloads if data[0] == EStopAction.RESUME), default=None)


class MotorOff:
    """Whether feedback shows the motor-off of the reset at ``reset_at``: some joint reported enabled in a frame
    stamped ``RESET_ACTED_WITHIN_S`` after it, then every joint reported disabled after that frame. A reset
    restarts the countdown, so a motor-off after a frame sent once the firmware acted on the reset is its own;
    motors not seen on then show nothing (the delay itself must pass: a motor-off just before may be an
    earlier reset's)."""

    def __init__(self, reset_at: float) -> None:
        self.after = reset_at + RESET_ACTED_WITHIN_S
        self.on_at: float | None = None

    def seen(self, state: ArmState) -> bool:
        for info in state.low_speed:
            if info is not None and info.timestamp > max(self.after, self.on_at or 0.0) and info.value.enabled:
                self.on_at = info.timestamp
        return self.on_at is not None and joints_disabled_since(state, self.on_at)


def joints_disabled_since(state: ArmState, since: float) -> bool:
    return all(f is not None and f.timestamp > since and not f.value.enabled for f in state.low_speed)
