"""Inverse kinematics of the twin's arm: joint angles that put the grasp point at a pose, fingers down.

Damped least squares on MuJoCo's Jacobians of the arm model (position and orientation error together),
clamped to the stops. The grasp point is ``GRASP_POINT_M`` along the gripper's axis (between the finger
pads). The wrist's ±70° (J5) cannot point the gripper straight down much above the table, so "down" leans
``tilt`` radians outward (away from the base), which reaches the whole workspace from the table to 0.15 m.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from .model import JOINT_NAMES, NUM_JOINTS

GRASP_POINT_M = np.array([0.0, 0.0, 0.115])  # in the gripper frame: the middle of the finger pads
TIP_M = 0.02  # the finger tips lie this much further along the gripper's axis
TILT_RAD = 0.3
_DAMPING = 0.05
_MAX_STEP_RAD = 0.3


def down_rotation(position: np.ndarray, yaw: float, tilt: float = TILT_RAD) -> np.ndarray:
    """The gripper frame at ``position`` pointing down but leaning ``tilt`` outward, its fingers opening
    along ``(-sin yaw, cos yaw, 0)`` (made perpendicular to the lean)."""
    outward = math.atan2(position[1], position[0])
    z_axis = np.array([math.sin(tilt) * math.cos(outward), math.sin(tilt) * math.sin(outward), -math.cos(tilt)])
    y_axis = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    y_axis -= (y_axis @ z_axis) * z_axis
    y_axis /= np.linalg.norm(y_axis)
    return np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis])


class ArmIK:
    """IK on its own copy of the model's state (the model itself is only read)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self._qpos = np.array([model.joint(n).qposadr[0] for n in JOINT_NAMES])
        self._dof = np.array([model.joint(n).dofadr[0] for n in JOINT_NAMES])
        self._range = model.jnt_range[[model.joint(n).id for n in JOINT_NAMES]]
        self._gripper = model.body("gripper").id

    def joints(self, qpos: np.ndarray) -> np.ndarray:
        """The arm's six angles in a full ``qpos`` of this model."""
        return qpos[self._qpos]

    def grasp_pose(self, joints_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World position of the grasp point and the gripper's rotation at ``joints_rad``."""
        self.data.qpos[self._qpos] = joints_rad
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)  # what mj_jac reads
        rotation = self.data.xmat[self._gripper].reshape(3, 3).copy()
        return self.data.xpos[self._gripper] + rotation @ GRASP_POINT_M, rotation

    def solve(
        self, seed_rad: np.ndarray, position: np.ndarray, rotation: np.ndarray, iterations: int = 60
    ) -> tuple[np.ndarray, float]:
        """Joint angles near ``seed_rad`` reaching ``position`` with ``rotation``; and the residual error
        (metres of position plus radians of orientation)."""
        q = np.array(seed_rad, dtype=float)
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        error = math.inf
        for _ in range(iterations):
            point, current = self.grasp_pose(q)
            e_pos = position - point
            e_rot = 0.5 * sum(np.cross(current[:, i], rotation[:, i]) for i in range(3))
            error = float(np.linalg.norm(e_pos) + np.linalg.norm(e_rot))
            if error < 1e-5:
                break
            mujoco.mj_jac(self.model, self.data, jacp, jacr, point, self._gripper)
            jac = np.vstack([jacp[:, self._dof], jacr[:, self._dof]])
            step = jac.T @ np.linalg.solve(jac @ jac.T + _DAMPING**2 * np.eye(6), np.concatenate([e_pos, e_rot]))
            q = np.clip(q + np.clip(step, -_MAX_STEP_RAD, _MAX_STEP_RAD), self._range[:, 0], self._range[:, 1])
        return q[:NUM_JOINTS], error
