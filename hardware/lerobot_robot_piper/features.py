"""LeRobot feature names shared by the PiPER follower and leader (radians for joints, metres for the gripper)."""

from __future__ import annotations

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
    """The six joint targets and the gripper target of a LeRobot action; every key is required."""
    missing = [k for k in MOTOR_KEYS if k not in action]
    if missing:
        raise ValueError(f"PiPER action is missing {', '.join(missing)}")
    return tuple(float(action[k]) for k in JOINT_KEYS), float(action[GRIPPER_KEY])  # type: ignore[arg-type]
