"""Pure safety clamps applied to every target before it is encoded: soft limits, then step limit."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from .codec import NUM_JOINTS


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Soft limits: per-joint ``(lower_rad, upper_rad)`` and the gripper opening range in metres."""

    joints_rad: tuple[tuple[float, float], ...]
    gripper_m: tuple[float, float] = (0.0, 0.07)

    def __post_init__(self) -> None:
        if len(self.joints_rad) != NUM_JOINTS:
            raise ValueError(f"joint limits need {NUM_JOINTS} (lower, upper) pairs, got {len(self.joints_rad)}")
        for j, (lower, upper) in enumerate((*self.joints_rad, self.gripper_m), start=1):
            if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
                raise ValueError(f"limit {j} must be finite with lower <= upper, got ({lower}, {upper})")


# piper_sdk soft limits (piper_param_manager / JointCtrl docstring / pyAgxArm piper.json).
SDK_SOFT_LIMITS = JointLimits(
    joints_rad=(
        (math.radians(-150), math.radians(150)),
        (0.0, math.radians(180)),
        (math.radians(-170), 0.0),
        (math.radians(-100), math.radians(100)),
        (math.radians(-70), math.radians(70)),
        (math.radians(-120), math.radians(120)),
    ),
    gripper_m=(0.0, 0.07),
)


def clamp(value: float, lower: float, upper: float) -> float:
    """``value`` limited to ``[lower, upper]``."""
    return min(max(value, lower), upper)


def check_finite(values: Sequence[float], what: str) -> None:
    """Refuse NaN and infinities before anything else looks at a target."""
    for i, v in enumerate(values, start=1):
        if not math.isfinite(v):
            raise ValueError(f"{what} {i} must be a finite number, got {v!r}")


def safe_target(goal: float, present: float, bounds: tuple[float, float], max_step: float | None) -> float:
    """Clamp to the soft limits, then cap the move from ``present`` (LeRobot's ``max_relative_target``).

    The result is always within ``max_step`` of ``present``; it is within the limits whenever
    ``present`` is, and otherwise moves toward them. A step that is not positive and finite is refused
    (a negative one would move away from the goal, NaN would remove the cap).
    """
    target = clamp(goal, *bounds)
    if max_step is not None:
        if not (max_step > 0 and math.isfinite(max_step)):
            raise ValueError(f"the step limit must be positive and finite, got {max_step!r}")
        target = clamp(target, present - max_step, present + max_step)
    return target
