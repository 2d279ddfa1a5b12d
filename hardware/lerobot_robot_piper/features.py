"""LeRobot feature names shared by the PiPER follower and leader (radians for joints, metres for the gripper)."""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence

JOINT_KEYS = tuple(f"joint_{j}.pos" for j in range(1, 7))
GRIPPER_KEY = "gripper.pos"
MOTOR_KEYS = (*JOINT_KEYS, GRIPPER_KEY)
# Optional observations (``use_velocity_and_torque``), named as LeRobot's openarm names them.
VELOCITY_KEYS = tuple(f"joint_{j}.vel" for j in range(1, 7))
TORQUE_KEYS = tuple(f"joint_{j}.torque" for j in range(1, 7))


def motor_features() -> dict[str, type]:
    """``joint_1.pos … joint_6.pos, gripper.pos``, all floats."""
    return dict.fromkeys(MOTOR_KEYS, float)


def to_action(joints_rad: Sequence[float], gripper_m: float) -> dict[str, float]:
    """Six joint angles and a gripper opening as a LeRobot action / observation dict."""
    return {**dict(zip(JOINT_KEYS, map(float, joints_rad), strict=True)), GRIPPER_KEY: float(gripper_m)}


def from_action(action: Mapping[str, object]) -> tuple[tuple[float, ...], float]:
    """The six joint targets and the gripper target of a LeRobot action; every key is required, and
    each value must be a real number (a NumPy or torch scalar too), never a string or a boolean."""
    missing = [k for k in MOTOR_KEYS if k not in action]
    if missing:
        raise ValueError(f"PiPER action is missing {', '.join(missing)}")
    return tuple(_number(k, action[k]) for k in JOINT_KEYS), _number(GRIPPER_KEY, action[GRIPPER_KEY])


def _number(key: str, value: object) -> float:
    item = getattr(value, "item", None)  # a NumPy or torch scalar: its Python value
    plain = item() if callable(item) and not isinstance(value, str | bytes) else value
    if isinstance(plain, bool) or not isinstance(plain, numbers.Real):
        raise ValueError(f"PiPER action {key} must be a real number, got {type(value).__name__} {value!r}")
    return float(plain)
