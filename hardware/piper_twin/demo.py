"""Scripted demonstrations: waypoints for a scene's task, followed the way a person teleoperates.

``plan`` reads where the scene's objects are and returns grasp-point waypoints with a gripper opening each
(each waypoint jittered by ``noise_m``, as a person's hand is). ``ScriptedDemo.step`` moves the commanded
grasp point toward the next waypoint at ``speed_m_s`` and turns it into joint targets by IK; it moves on
once the arm (as measured) is there and the waypoint's dwell (e.g. for the gripper to close) has passed.

With ``detour_m`` > 0 a demonstration first reaches a point beside each approach waypoint (the one above the
object), off by ``detour_m`` / 2 … ``detour_m`` in a random horizontal direction, and then corrects to it, as a
person's coarse move is followed by a fine one. Without it every demonstration arrives exactly above the
object, and a policy that arrives a little beside it has never seen what to do there.

With ``regrasp_m`` > 0, half of the demonstrations (drawn per demonstration) first close the gripper on nothing:
``regrasp_m`` / 2 … ``regrasp_m`` beside the grasp point, across the direction the fingers close in, so that they
pass beside the object; then they reopen, rise ``REGRASP_RISE_M`` and go on to the real grasp. A policy whose
grasp misses has seen the gripper close to nothing and what follows it; without it every close holds the object.

``close_s`` is how long every close (the real one and a missed one) stays closed before the arm moves on. The
gripper takes ≈ 0.6 s to close on nothing; with a longer stay, a policy that decides every 0.8 s sees the settled
opening (the cube's width, or nothing) before it must choose between lifting and reopening.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from .ik import TIP_M, ArmIK, down_rotation
from .scenes import CubeInBowl, PressButton, Scene

OPEN_M = 0.06
ABOVE_M = 0.12
REACHED_M = 0.01
REGRASP_RISE_M = 0.04
CLOSE_S, REOPEN_S = 0.8, 0.3


@dataclass(frozen=True)
class Waypoint:
    """Where the grasp point goes (m, world), the gripper opening there, how long to stay once reached."""

    position: np.ndarray
    gripper_m: float
    dwell_s: float = 0.0
    approach: bool = False  # above the object, before going down to it (``detour_m`` detours before it)


def _press_button(scene: PressButton, model: mujoco.MjModel, data: mujoco.MjData) -> tuple[list[Waypoint], float]:
    base = data.mocap_pos[model.body("button_base").mocapid[0]]
    yaw = math.atan2(base[1], base[0])
    axis = down_rotation(base, yaw)[:, 2]
    cap_top = np.array([base[0], base[1], 0.04])
    pressed = cap_top + axis * (scene.travel_m * 0.8) / abs(axis[2])  # the closed tips, 80 % of the travel down
    grasp = pressed - axis * TIP_M
    above = grasp + [0.0, 0.0, ABOVE_M - grasp[2]]
    return [Waypoint(above, 0.0, approach=True), Waypoint(grasp, 0.0, 0.3), Waypoint(above, 0.0)], yaw


def _cube_in_bowl(
    scene: CubeInBowl, model: mujoco.MjModel, data: mujoco.MjData, close_s: float
) -> tuple[list[Waypoint], float]:
    cube = data.xpos[model.body("cube").id].copy()
    bowl = data.mocap_pos[model.body("bowl").mocapid[0]]
    cube_yaw = 2 * math.atan2(data.xquat[model.body("cube").id][3], data.xquat[model.body("cube").id][0])
    outward = math.atan2(cube[1], cube[0])
    # The fingers close on two faces: the face direction nearest the outward one (J6 stays small).
    yaw = outward + (cube_yaw - outward + math.pi / 4) % (math.pi / 2) - math.pi / 4
    grasp = np.array([cube[0], cube[1], scene.cube_half_m + 0.01])
    lift = np.array([cube[0], cube[1], 0.15])
    over_bowl = np.array([bowl[0], bowl[1], 0.15])
    drop = np.array([bowl[0], bowl[1], scene.bowl_height_m + 0.05])
    return [
        Waypoint(grasp + [0, 0, ABOVE_M - grasp[2]], OPEN_M, approach=True),
        Waypoint(grasp, OPEN_M),
        Waypoint(grasp, 0.0, close_s),
        Waypoint(lift, 0.0),
        Waypoint(over_bowl, 0.0),
        Waypoint(drop, 0.0),
        Waypoint(drop, OPEN_M, 0.6),
        Waypoint(over_bowl, OPEN_M),
    ], yaw


def plan(
    scene: Scene, model: mujoco.MjModel, data: mujoco.MjData, close_s: float = CLOSE_S
) -> tuple[list[Waypoint], float]:
    """The waypoints of ``scene``'s task in the state ``data`` (after ``mj_kinematics``), and the gripper's yaw;
    a close stays closed ``close_s`` before the arm moves on."""
    if isinstance(scene, PressButton):
        return _press_button(scene, model, data)
    if isinstance(scene, CubeInBowl):
        return _cube_in_bowl(scene, model, data, close_s)
    raise ValueError(f"no scripted demonstration for scene {scene.name!r}")


Planner = Callable[[Scene, mujoco.MjModel, mujoco.MjData, float], tuple[list[Waypoint], float]]


def missed_grasp(
    waypoints: list[Waypoint], yaw: float, rng: np.random.Generator, size_m: float, close_s: float = CLOSE_S
) -> list[Waypoint]:
    """``waypoints`` with, before the descent to their first close, a close on nothing beside it (``size_m`` / 2 …
    ``size_m`` off across the fingers' closing direction, either side) that stays closed ``close_s``, the reopen
    and the rise; unchanged when no waypoint closes the gripper."""
    closes = [k for k in range(1, len(waypoints)) if waypoints[k].gripper_m < waypoints[k - 1].gripper_m]
    if not closes:
        return waypoints
    descent = waypoints[closes[0] - 1]
    across = np.array([math.cos(yaw), math.sin(yaw), 0.0]) * rng.choice([-1.0, 1.0]) * rng.uniform(size_m / 2, size_m)
    beside = descent.position + across
    miss = [
        Waypoint(beside, descent.gripper_m),
        Waypoint(beside, 0.0, close_s),
        Waypoint(beside, descent.gripper_m, REOPEN_S),
        Waypoint(beside + [0.0, 0.0, REGRASP_RISE_M], descent.gripper_m),
    ]
    return waypoints[: closes[0] - 1] + miss + waypoints[closes[0] - 1 :]


def detour(rng: np.random.Generator, size_m: float) -> np.ndarray:
    """A horizontal offset of ``size_m`` / 2 … ``size_m`` in a uniformly random direction."""
    angle, length = rng.uniform(0.0, 2 * math.pi), rng.uniform(size_m / 2, size_m)
    return np.array([length * math.cos(angle), length * math.sin(angle), 0.0])


class ScriptedDemo:
    """One demonstration of ``scene``: ``start`` plans it, ``step`` gives the next joint and gripper targets."""

    def __init__(
        self,
        scene: Scene,
        model: mujoco.MjModel,
        speed_m_s: float = 0.12,
        noise_m: float = 0.003,
        detour_m: float = 0.0,
        regrasp_m: float = 0.0,
        close_s: float = CLOSE_S,
        planner: Planner = plan,
    ) -> None:
        """``planner`` gives the waypoints and the yaw (``plan``, or a test rig's variant of it)."""
        self.scene, self.model = scene, model
        self.speed_m_s, self.noise_m, self.detour_m, self.regrasp_m = speed_m_s, noise_m, detour_m, regrasp_m
        self.close_s, self.planner = close_s, planner
        self.ik = ArmIK(model)
        self.waypoints: list[Waypoint] = []
        self.index = 0
        self._yaw = 0.0
        self._point = np.zeros(3)
        self._joints = np.zeros(6)
        self._dwell_s = 0.0

    @property
    def done(self) -> bool:
        return self.index >= len(self.waypoints)

    @property
    def yaw(self) -> float:
        """The gripper's yaw about the vertical in the plan ``start`` made (rad)."""
        return self._yaw

    def start(self, data: mujoco.MjData, joints_rad: Sequence[float], rng: np.random.Generator) -> None:
        """Plan from the objects in ``data`` (its kinematics computed), starting where the arm is."""
        waypoints, self._yaw = self.planner(self.scene, self.model, data, self.close_s)
        jitter = rng.normal(0.0, self.noise_m, (len(waypoints), 3)) * [1, 1, 0.3]
        # A waypoint repeated (e.g. to close the gripper there) keeps its predecessor's jitter.
        for k in range(1, len(waypoints)):
            if np.array_equal(waypoints[k].position, waypoints[k - 1].position):
                jitter[k] = jitter[k - 1]
        self.waypoints = []
        for w, j in zip(waypoints, jitter, strict=True):
            if w.approach and self.detour_m > 0:
                self.waypoints.append(Waypoint(w.position + j + detour(rng, self.detour_m), w.gripper_m))
            self.waypoints.append(Waypoint(w.position + j, w.gripper_m, w.dwell_s, w.approach))
        if self.regrasp_m > 0 and rng.random() < 0.5:
            self.waypoints = missed_grasp(self.waypoints, self._yaw, rng, self.regrasp_m, self.close_s)
        self.index = 0
        self._joints = np.asarray(joints_rad, dtype=float)
        self._point = self.ik.grasp_pose(self._joints)[0]
        self._dwell_s = 0.0

    def step(self, dt: float, joints_rad: Sequence[float]) -> tuple[np.ndarray, float]:
        """Joint targets (rad) and gripper opening (m) for the next ``dt`` seconds, the arm measured at
        ``joints_rad``; after the last waypoint it holds there."""
        if self.done:
            return self._joints, self.waypoints[-1].gripper_m
        waypoint = self.waypoints[self.index]
        offset = waypoint.position - self._point
        distance = float(np.linalg.norm(offset))
        self._point = (
            waypoint.position
            if distance <= self.speed_m_s * dt
            else (self._point + offset / distance * self.speed_m_s * dt)
        )
        rotation = down_rotation(self._point, self._yaw)
        self._joints, _ = self.ik.solve(self._joints, self._point, rotation)
        measured = self.ik.grasp_pose(np.asarray(joints_rad, dtype=float))[0]
        if np.array_equal(self._point, waypoint.position) and np.linalg.norm(measured - waypoint.position) < REACHED_M:
            self._dwell_s += dt
            if self._dwell_s >= waypoint.dwell_s:
                self.index, self._dwell_s = self.index + 1, 0.0
        return self._joints, waypoint.gripper_m
