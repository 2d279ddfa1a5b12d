"""Table-top scenes for the twin (the paper's Table 5): objects, their placement from a seed, success.

A scene adds its objects to the arm's spec (``add``), places them for an episode from
``numpy.random.default_rng(seed)`` (``place``), and says whether its task has succeeded (``succeeded``).
Static objects are mocap bodies, so a new placement needs no recompilation. Every body has an explicit
mass: the model takes no inertia from geometry (the arm's comes from ``piper_control``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from .model import WORLD_CONTACT, arm_spec


def _body(parent: mujoco.MjsBody, name: str, pos: tuple[float, ...], mass: float = 0.0) -> mujoco.MjsBody:
    body = parent.add_body()
    body.name, body.pos = name, list(pos)
    if mass:  # centred (an unset ipos is NaN in a spec)
        body.mass, body.inertia, body.explicitinertial = mass, [mass * 1e-4] * 3, True
        body.ipos, body.iquat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    return body


def _geom(
    body: mujoco.MjsBody,
    kind: int,
    size: tuple[float, ...],
    pos: tuple[float, ...],
    rgba: tuple[float, ...],
    **attrs: object,
) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.type, geom.size, geom.pos, geom.rgba = kind, [*size, 0.0, 0.0][:3], list(pos), list(rgba)
    geom.contype, geom.conaffinity = WORLD_CONTACT
    for name, value in attrs.items():
        setattr(geom, name, value)
    return geom


def _uniform_xy(rng: np.random.Generator, x: tuple[float, float], y: tuple[float, float]) -> np.ndarray:
    return np.array([rng.uniform(*x), rng.uniform(*y)])


@dataclass(frozen=True)
class Scene:
    """The table alone (no task: ``succeeded`` is always False). ``instruction``: the task's words, as a
    dataset records them (``--dataset.single_task``)."""

    name: str = "table"
    instruction: str = ""

    def add(self, spec: mujoco.MjSpec) -> None:
        """Add this scene's objects to ``spec``."""

    def place(self, model: mujoco.MjModel, data: mujoco.MjData, seed: int) -> None:
        """Place the objects for the episode of ``seed`` (the arm is left as it is)."""

    def succeeded(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return False


@dataclass(frozen=True)
class PressButton(Scene):
    """A spring-loaded button on a base: pressed once its cap went down by ``press_depth_m``."""

    name: str = "press_button"
    instruction: str = "press the button"
    travel_m: float = 0.012
    press_depth_m: float = 0.006
    x_range: tuple[float, float] = (0.25, 0.38)
    y_range: tuple[float, float] = (-0.15, 0.15)

    def add(self, spec: mujoco.MjSpec) -> None:
        base = _body(spec.worldbody, "button_base", (0.3, 0.0, 0.0))
        base.mocap = True
        _geom(base, mujoco.mjtGeom.mjGEOM_BOX, (0.035, 0.035, 0.012), (0, 0, 0.012), (0.25, 0.25, 0.28, 1))
        cap = _body(base, "button_cap", (0, 0, 0.024), mass=0.01)
        joint = cap.add_joint()
        joint.name, joint.type, joint.axis = "button", mujoco.mjtJoint.mjJNT_SLIDE, [0, 0, 1]
        joint.range, joint.limited = [-self.travel_m, 0.0], mujoco.mjtLimited.mjLIMITED_TRUE
        joint.stiffness, joint.damping = 150.0, 1.0  # ~1 N to hold it down
        _geom(cap, mujoco.mjtGeom.mjGEOM_CYLINDER, (0.02, 0.008), (0, 0, 0.008), (0.85, 0.1, 0.1, 1))
        inside = spec.add_exclude()  # the cap sinks into its base (a mocap body counts as the world's)
        inside.bodyname1, inside.bodyname2 = "button_base", "button_cap"

    def place(self, model: mujoco.MjModel, data: mujoco.MjData, seed: int) -> None:
        xy = _uniform_xy(np.random.default_rng(seed), self.x_range, self.y_range)
        data.mocap_pos[model.body("button_base").mocapid[0]] = [*xy, 0.0]
        button = model.joint("button")
        data.qpos[button.qposadr[0]], data.qvel[button.dofadr[0]] = 0.0, 0.0  # released

    def depth(self, model: mujoco.MjModel, data: mujoco.MjData) -> float:
        """How far the cap is pressed down (m)."""
        return -float(data.qpos[model.joint("button").qposadr[0]])

    def succeeded(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        return self.depth(model, data) >= self.press_depth_m


@dataclass(frozen=True)
class CubeInBowl(Scene):
    """A 3 cm cube and a bowl: done once the cube rests inside the bowl (within its wall, below its rim)."""

    name: str = "cube_in_bowl"
    instruction: str = "put the cube in the bowl"
    cube_half_m: float = 0.015
    bowl_radius_m: float = 0.07
    bowl_height_m: float = 0.04
    min_distance_m: float = 0.15
    x_range: tuple[float, float] = (0.24, 0.38)
    y_range: tuple[float, float] = (-0.18, 0.18)

    def add(self, spec: mujoco.MjSpec) -> None:
        bowl = _body(spec.worldbody, "bowl", (0.3, 0.15, 0.0))
        bowl.mocap = True
        rgba = (0.2, 0.45, 0.8, 1)
        # The floor: a box (a thin cylinder's contact with a box lets the cube sink through it).
        half = self.bowl_radius_m / math.sqrt(2)
        _geom(bowl, mujoco.mjtGeom.mjGEOM_BOX, (half, half, 0.003), (0, 0, 0.003), rgba)
        walls = 16
        half_len = self.bowl_radius_m * math.tan(math.pi / walls) + 0.003
        for k in range(walls):
            angle = 2 * math.pi * k / walls
            wall = _geom(
                bowl,
                mujoco.mjtGeom.mjGEOM_BOX,
                (0.003, half_len, self.bowl_height_m / 2),
                (self.bowl_radius_m * math.cos(angle), self.bowl_radius_m * math.sin(angle), self.bowl_height_m / 2),
                rgba,
            )
            wall.quat = [math.cos(angle / 2), 0, 0, math.sin(angle / 2)]
        cube = _body(spec.worldbody, "cube", (0.3, -0.1, self.cube_half_m), mass=0.03)
        cube.inertia = [0.03 * (2 * self.cube_half_m) ** 2 / 6] * 3
        cube.add_freejoint().name = "cube"
        _geom(
            cube,
            mujoco.mjtGeom.mjGEOM_BOX,
            (self.cube_half_m,) * 3,
            (0, 0, 0),
            (0.9, 0.75, 0.1, 1),
            friction=[1.5, 0.01, 0.001],
            condim=4,
        )

    def place(self, model: mujoco.MjModel, data: mujoco.MjData, seed: int) -> None:
        rng = np.random.default_rng(seed)
        bowl = _uniform_xy(rng, self.x_range, self.y_range)
        cube = _uniform_xy(rng, self.x_range, self.y_range)
        while np.linalg.norm(cube - bowl) < self.min_distance_m:
            cube = _uniform_xy(rng, self.x_range, self.y_range)
        yaw = rng.uniform(-math.pi / 4, math.pi / 4)
        data.mocap_pos[model.body("bowl").mocapid[0]] = [*bowl, 0.0]
        adr = model.joint("cube").qposadr[0]
        data.qpos[adr : adr + 7] = [*cube, self.cube_half_m, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
        data.qvel[model.joint("cube").dofadr[0] : model.joint("cube").dofadr[0] + 6] = 0.0

    def succeeded(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        cube = data.xpos[model.body("cube").id]
        bowl = data.mocap_pos[model.body("bowl").mocapid[0]]
        inside = np.linalg.norm(cube[:2] - bowl[:2]) < self.bowl_radius_m - self.cube_half_m
        return bool(inside and cube[2] < self.bowl_height_m)


def compile_scene(scene: Scene) -> mujoco.MjModel:
    """The arm on its table with ``scene``'s objects, compiled."""
    spec = arm_spec()
    scene.add(spec)
    return spec.compile()


SCENES: dict[str, Scene] = {s.name: s for s in (Scene(), PressButton(), CubeInBowl())}


def get_scene(name: str) -> Scene:
    """The scene called ``name``; a ValueError lists the known ones."""
    if name not in SCENES:
        raise ValueError(f"unknown twin scene {name!r}; known: {', '.join(SCENES)}")
    return SCENES[name]
