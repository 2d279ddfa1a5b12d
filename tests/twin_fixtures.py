"""Helpers for the tests of the unattended twin: the arm pose that presses a placed button."""

from __future__ import annotations

import numpy as np
from piper_twin.demo import plan
from piper_twin.ik import ArmIK, down_rotation
from piper_twin.plant import TwinPlant

START_POSE = (0.0, 1.0, -1.0, 0.0, 0.5, 0.0)  # where the IK starts: an arm bent over the table


def pressing_pose(seed: int) -> list[float]:
    """Joint angles and a closed gripper whose finger tips press the button placed from ``seed`` 80 % of its travel
    down (the scripted demonstration's press), reached by IK along straight lines from above."""
    plant = TwinPlant("press_button", seed)
    waypoints, yaw = plan(plant.scene, plant.model, plant.data)
    above, press = waypoints[0].position, waypoints[1].position
    ik = ArmIK(plant.model)
    joints, error = np.array(START_POSE), np.inf
    for start, end in ((ik.grasp_pose(joints)[0], above), (above, press)):
        for fraction in np.linspace(0.0, 1.0, 21)[1:]:
            point = start + fraction * (end - start)
            joints, error = ik.solve(joints, point, down_rotation(point, yaw))
    assert error < 1e-4, error
    return [*map(float, joints), 0.0]


def button_xy(seed: int) -> np.ndarray:
    """Where the button of ``seed`` stands on the table (m)."""
    return TwinPlant("press_button", seed).snapshot().mocap_pos[0, :2]
