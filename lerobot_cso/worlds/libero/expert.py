"""A closed-loop scripted expert for LIBERO's pick-and-place tasks (LIBERO-Object: the named object into the
basket; LIBERO-Spatial: the named bowl onto the plate), as a pool controller.

The expert reads the simulator's true state — a demonstrator may, the policy never does: the env adds it to its
observation as ``expert`` (:func:`expert_view`, only when built for demos) and datasets never store it. It acts
through LIBERO's own 7-d controller (OSC pose deltas in the world frame, action 1 ≈ 1 cm per step at 20 Hz; gripper
-1 open, +1 closed) along waypoints: above the object with the fingers across its narrowest side → down → close →
lift, checking the object came along (else open, back up and try again) → above the container → lower → open.
Every step steers toward the current waypoint from the current state, so noise and slips are corrected.

Demos differ: each episode draws its own hover height and grasp offset, and N(0, ``noise_std``²) noise is added
to the translation actions (a quarter of it to the rotation ones), from a generator seeded by
``(seed, task, init_seed)`` — the same episode whatever slot runs it.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from lerobot_cso.rollout.backend import Job

# The layout of the expert's view (:func:`expert_view`): slices into one float vector.
EEF = slice(0, 3)  # grip site position
APPROACH = slice(3, 6)  # the gripper's pointing axis (world)
FINGERS = slice(6, 9)  # left finger − right finger (world)
OPENING = 9  # finger joint 1 − finger joint 2 (m)
TARGET = slice(10, 13)  # the object's bounding-box centre
TARGET_LO, TARGET_HI = 13, 14  # the object's lowest and highest z
TARGET_YAW = 15  # the horizontal direction across the object's narrowest side (rad, mod π)
CONTAINER = slice(16, 19)  # where the object must go: the container's contain region, else its box centre
CONTAINER_HI = 19  # the container's highest z
VIEW_DIM = 20

ACTION_DIM = 7
CARRY_Z = 0.25  # the height at which a held object is carried, at least
CLEARANCE = 0.04  # a carried object's bottom stays this far above the container's rim
POSITION_GAIN = 25.0  # action per metre of position error (saturates at 4 cm)
ROTATION_GAIN = 3.0  # action per radian of orientation error
CLOSE_STEPS = 14  # the fingers close fully in ≈ 12 steps
OPEN_STEPS = 10
MIN_HOLD_OPENING = 0.004  # fingers closer than this hold nothing
LIFT_CHECK = 0.03  # the object must have risen this much once the hand has risen 0.06 m


def _points(sim: Any, body: int) -> np.ndarray:
    """World-frame corners of the collision geoms' boxes of ``body`` and its descendants."""
    model, data = sim.model._model, sim.data._data
    bodies = {body}
    for b in range(model.nbody):  # bodies are stored parents first
        if model.body_parentid[b] in bodies and b != 0:
            bodies.add(b)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    corners = []
    for g in np.flatnonzero(np.isin(model.geom_bodyid, list(bodies))):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only
        centre, half = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
        local = centre + signs * half
        corners.append(data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T)
    return np.concatenate(corners)


def narrowest_yaw(points: np.ndarray) -> tuple[float, float]:
    """The horizontal direction (rad, in [0, π)) along which ``points`` are narrowest, and that width."""
    angles = np.deg2rad(np.arange(0, 180, 5))
    widths = np.ptp(points[:, :2] @ np.stack([np.cos(angles), np.sin(angles)]), axis=0)
    best = int(np.argmin(widths))
    return float(angles[best]), float(widths[best])


def expert_view(env: Any) -> np.ndarray:
    """The expert's view of a LIBERO robosuite env (the layout above): its first object of interest is what to
    move, its second where to put it."""
    sim = env.sim
    robot = env.robots[0]
    target, container = env.obj_of_interest[:2]
    view = np.zeros(VIEW_DIM, dtype=np.float64)
    view[EEF] = sim.data.site_xpos[robot.eef_site_id]
    view[APPROACH] = robot.controller.ee_ori_mat[:, 2]
    left, right = (sim.data.body_xpos[sim.model.body_name2id(f"gripper0_{side}finger")] for side in ("left", "right"))
    view[FINGERS] = left - right
    joints = sim.data.qpos[robot._ref_gripper_joint_pos_indexes]
    view[OPENING] = joints[0] - joints[1]
    points = _points(sim, env.obj_body_id[target])
    lo, hi = points.min(0), points.max(0)
    view[TARGET] = (lo + hi) / 2
    view[TARGET_LO], view[TARGET_HI] = lo[2], hi[2]
    view[TARGET_YAW] = narrowest_yaw(points)[0]
    box = _points(sim, env.obj_body_id[container])
    region = f"{container}_contain_region"
    names = [sim.model.site_id2name(i) for i in range(sim.model.nsite)]
    view[CONTAINER] = sim.data.site_xpos[names.index(region)] if region in names else (box.min(0) + box.max(0)) / 2
    view[CONTAINER_HI] = box.max(0)[2]
    return view.astype(np.float32)


def _wrap_half_turn(angle: float) -> float:
    """``angle`` wrapped into [-π/2, π/2): a two-finger grasp is the same turned by π."""
    return (angle + np.pi / 2) % np.pi - np.pi / 2


@dataclass
class _Episode:
    """One episode's plan and progress."""

    rng: np.random.Generator
    hover: float  # height above the object's top of the approach
    offset: np.ndarray  # grasp point offset from the object's centre (xy)
    phase: str = "approach"
    steps: int = 0  # steps in the current phase
    grasp_z: float = 0.0  # the hand's height when it closed
    lifted_from: float = 0.0  # the object's lowest z when the hand closed

    def goto(self, phase: str) -> None:
        self.phase, self.steps = phase, 0


class PickPlaceExpert:
    """The waypoint state machine of one episode (see the module docstring)."""

    def __init__(self, rng: np.random.Generator, noise_std: float) -> None:
        self.noise_std = noise_std
        self.ep = _Episode(rng, hover=float(rng.uniform(0.06, 0.10)), offset=rng.normal(0.0, 0.003, 2))

    def _steer(self, view: np.ndarray, goal: np.ndarray, yaw: float | None, gripper: float) -> np.ndarray:
        action = np.zeros(ACTION_DIM)
        action[:3] = POSITION_GAIN * (goal - view[EEF])
        down = np.array([0.0, 0.0, -1.0])
        rotvec = np.cross(view[APPROACH], down)  # tilt back to pointing straight down (small angles)
        if yaw is not None:
            fingers = view[FINGERS]
            rotvec[2] += _wrap_half_turn(yaw - np.arctan2(fingers[1], fingers[0]))
        action[3:6] = ROTATION_GAIN * rotvec
        action[6] = gripper
        noise = self.ep.rng.normal(0.0, self.noise_std, ACTION_DIM)
        action[:3] += noise[:3]
        action[3:6] += noise[3:6] / 4
        return np.clip(action, -1.0, 1.0)

    def act(self, view: np.ndarray) -> np.ndarray:
        ep = self.ep
        ep.steps += 1
        eef = view[EEF]
        target = view[TARGET].copy()
        target[:2] += ep.offset
        height = view[TARGET_HI] - view[TARGET_LO]
        grasp_z = max(view[TARGET_LO] + 0.012, view[TARGET_HI] - 0.035) if height > 0.03 else view[TARGET_LO] + 0.008
        yaw = view[TARGET_YAW]
        if ep.phase == "approach":
            goal = np.array([target[0], target[1], view[TARGET_HI] + ep.hover])
            fingers = view[FINGERS]
            aligned = abs(_wrap_half_turn(yaw - np.arctan2(fingers[1], fingers[0]))) < 0.08
            if np.linalg.norm(goal[:2] - eef[:2]) < 0.01 and abs(goal[2] - eef[2]) < 0.02 and aligned:
                ep.goto("descend")
            return self._steer(view, goal, yaw, -1.0)
        if ep.phase == "descend":
            goal = np.array([target[0], target[1], grasp_z])
            if abs(goal[2] - eef[2]) < 0.006 or ep.steps > 40:
                ep.goto("close")
                ep.grasp_z, ep.lifted_from = float(eef[2]), float(view[TARGET_LO])
            return self._steer(view, goal, yaw, -1.0)
        if ep.phase == "close":
            if ep.steps >= CLOSE_STEPS:
                ep.goto("lift" if view[OPENING] > MIN_HOLD_OPENING else "retry")
            return self._steer(view, np.array([eef[0], eef[1], ep.grasp_z]), None, 1.0)
        hang = eef[2] - view[TARGET_LO]  # how far the object reaches below the hand
        carry_z = max(CARRY_Z, view[CONTAINER_HI] + hang + CLEARANCE)  # a tall object clears the rim
        if ep.phase == "lift":
            if eef[2] > ep.grasp_z + 0.06 and view[TARGET_LO] < ep.lifted_from + LIFT_CHECK:
                ep.goto("retry")  # the object stayed behind
            elif eef[2] > carry_z - 0.02:
                ep.goto("carry")
            return self._steer(view, np.array([eef[0], eef[1], carry_z]), None, 1.0)
        container = view[CONTAINER]
        if ep.phase == "carry":
            if view[OPENING] < MIN_HOLD_OPENING:
                ep.goto("retry")  # dropped on the way
            elif np.linalg.norm(container[:2] - eef[:2]) < 0.015:
                ep.goto("lower")
            return self._steer(view, np.array([container[0], container[1], carry_z]), None, 1.0)
        if ep.phase == "lower":
            release_z = view[CONTAINER_HI] + hang + 0.01
            if eef[2] < release_z + 0.01 or ep.steps > 40:
                ep.goto("open")
            return self._steer(view, np.array([container[0], container[1], release_z]), None, 1.0)
        if ep.phase == "open":
            if ep.steps >= OPEN_STEPS:
                ep.goto("retreat")
            return self._steer(view, eef.astype(np.float64), None, -1.0)
        if ep.phase == "retreat":
            return self._steer(view, np.array([eef[0], eef[1], CARRY_Z]), None, -1.0)
        # retry: open, rise to the approach height, then approach again from the object's new place
        if ep.steps > OPEN_STEPS and eef[2] > view[TARGET_HI] + ep.hover - 0.02:
            ep.goto("approach")
        return self._steer(view, np.array([eef[0], eef[1], view[TARGET_HI] + ep.hover]), None, -1.0)


class LiberoExpertController:
    """Per slot: the pick-and-place expert on the env's ``expert`` observation, plus noise (module docstring)."""

    def __init__(self, num_envs: int, noise_std: float = 0.05, seed: int = 0) -> None:
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std}")
        self.noise_std = noise_std
        self.seed = seed
        self._experts: list[PickPlaceExpert | None] = [None] * num_envs

    def start(self, slot: int, job: Job) -> None:
        rng = np.random.default_rng([self.seed, zlib.crc32(job.task.encode()), job.init_seed])
        self._experts[slot] = PickPlaceExpert(rng, self.noise_std)

    def act(self, obs: dict[str, Any], active: np.ndarray) -> np.ndarray:
        actions = np.zeros((len(active), ACTION_DIM), dtype=np.float32)
        for slot in np.flatnonzero(active):
            actions[slot] = self._experts[slot].act(np.asarray(obs["expert"][slot], np.float64))
        return actions

    def finish(self, slot: int) -> None:
        self._experts[slot] = None

    def current_skill(self, slot: int) -> None:
        return None  # an expert acts step by step, not by skills
