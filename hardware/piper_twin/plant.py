"""``TwinPlant``: the physical arm behind the simulated firmware (``piper_can.firmware.Plant``).

Each firmware tick hands it the planner's setpoints and a drive per motor. ``servo``: the joint servo
``kp (setpoint - q) + kv (planned velocity - qdot)`` plus gravity compensation (what the real motor
controller's integrator achieves); ``limp``: no torque, the arm falls under gravity; ``damped``: the
e-stop's brake ``-ESTOP_DAMPING qdot``, the arm sinks slowly. The physics advances by exactly the firmware's
time (the remainder carried to the next tick), in ``TIMESTEP_S`` steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import mujoco
import numpy as np
from piper_can.firmware import Drive, PlantCommand, PlantState

from .model import (
    ESTOP_DAMPING,
    FINGER_JOINTS,
    GRIPPER_KP,
    GRIPPER_KV,
    JOINT_KP,
    JOINT_KV,
    JOINT_NAMES,
    NUM_JOINTS,
)
from .scenes import Scene, compile_scene, get_scene
from .state_channel import TwinSnapshot

Listener = Callable[["TwinPlant"], None]


class TwinPlant:
    """A scene's MuJoCo model and state; ``step`` is called by the firmware, under the emulator's lock."""

    def __init__(
        self,
        scene: str | Scene = "table",
        seed: int = 0,
        pose_rad: Sequence[float] | None = None,
        gripper_m: float = 0.0,
    ) -> None:
        self.scene = get_scene(scene) if isinstance(scene, str) else scene
        self.model = compile_scene(self.scene)
        self.data = mujoco.MjData(self.model)
        self.seed = seed
        self.listeners: list[Listener] = []  # called after every step (e.g. the state publisher)
        self._qpos = np.array([self.model.joint(n).qposadr[0] for n in JOINT_NAMES])
        self._dof = np.array([self.model.joint(n).dofadr[0] for n in JOINT_NAMES])
        self._fingers_qpos = np.array([self.model.joint(n).qposadr[0] for n in FINGER_JOINTS])
        self._fingers_dof = np.array([self.model.joint(n).dofadr[0] for n in FINGER_JOINTS])
        self._debt_s = 0.0
        self.placement = 0  # how many times the objects were placed
        self.reset(seed, pose_rad, gripper_m)

    def reset(self, seed: int, pose_rad: Sequence[float] | None = None, gripper_m: float = 0.0) -> None:
        """Everything at rest: the arm at ``pose_rad`` (default all zero; kept inside the joints' stops), the
        scene placed for ``seed``."""
        mujoco.mj_resetData(self.model, self.data)
        pose = np.zeros(NUM_JOINTS) if pose_rad is None else np.asarray(pose_rad, dtype=float)
        stops = self.model.jnt_range[[self.model.joint(n).id for n in JOINT_NAMES]]
        self.data.qpos[self._qpos] = np.clip(pose, stops[:, 0], stops[:, 1])
        self.data.qpos[self._fingers_qpos] = gripper_m / 2
        self.place(seed)

    def place(self, seed: int) -> None:
        """Place the scene's objects for ``seed`` (the arm stays as it is); the task is not done yet."""
        self.seed = seed
        self.placement += 1
        self.scene.place(self.model, self.data, seed)
        self._succeeded = False
        mujoco.mj_forward(self.model, self.data)

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def succeeded(self) -> bool:
        """Whether the task succeeded at some step since the objects were placed (a pressed button counts
        after it springs back)."""
        return self._succeeded or self.scene.succeeded(self.model, self.data)

    def snapshot(self) -> TwinSnapshot:
        """The world state a renderer needs, with the scene's verdict."""
        d = self.data
        return TwinSnapshot(
            self.scene.name,
            self.seed,
            self.placement,
            self.time_s,
            time.time(),
            self.succeeded(),
            d.qpos.copy(),
            d.mocap_pos.copy(),
            d.mocap_quat.copy(),
        )

    def state(self) -> PlantState:
        d = self.data
        return PlantState(
            tuple(float(q) for q in d.qpos[self._qpos]),
            tuple(float(v) for v in d.qvel[self._dof]),
            float(d.qpos[self._fingers_qpos].sum()),
        )

    def _set_drive(self, actuator: int, drive: Drive, kp: float, kv: float) -> None:
        gain, bias = self.model.actuator_gainprm[actuator], self.model.actuator_biasprm[actuator]
        if drive == "servo":
            gain[0], bias[1], bias[2] = kp, -kp, -kv
        else:
            gain[0], bias[1], bias[2] = 0.0, 0.0, -ESTOP_DAMPING if drive == "damped" else 0.0

    def step(self, dt: float, command: PlantCommand) -> PlantState:
        """Advance ``dt`` seconds under ``command``; returns where the motors are."""
        m, d = self.model, self.data
        servo = np.array([drive == "servo" for drive in command.drives])
        for j, drive in enumerate(command.drives):
            self._set_drive(j, drive, JOINT_KP, JOINT_KV)
        self._set_drive(NUM_JOINTS, command.gripper_drive, GRIPPER_KP, GRIPPER_KV)
        # Velocity feed-forward through the setpoint: kp (ctrl - q) - kv qdot = kp (s - q) + kv (v - qdot).
        d.ctrl[:NUM_JOINTS] = np.asarray(command.setpoints_rad) + JOINT_KV / JOINT_KP * np.asarray(
            command.velocities_rad_s
        )
        d.ctrl[NUM_JOINTS] = command.gripper_setpoint_m / 2
        compensated = np.concatenate([self._dof[servo], self._fingers_dof if command.gripper_drive == "servo" else []])
        compensated = compensated.astype(int)
        self._debt_s += dt
        steps = int(self._debt_s / m.opt.timestep + 1e-9)
        self._debt_s -= steps * m.opt.timestep
        for _ in range(steps):
            mujoco.mj_step1(m, d)
            d.qfrc_applied[:] = 0.0
            d.qfrc_applied[compensated] = d.qfrc_bias[compensated]
            mujoco.mj_step2(m, d)
        self._succeeded = self.succeeded()
        for listener in self.listeners:
            listener(self)
        return self.state()
