"""The PiPER as a MuJoCo model: ``piper_control``'s joints and inertias, our geometry, actuators and cameras.

The kinematics and inertias come from the installed ``piper-control`` package
(``piper_control/models/piper_grav_comp.xml``, MIT, loaded at run time, never copied). That file has no
geometry and no actuators; this module adds primitives sized from the arm's published dimensions (base
column 123 mm, upper arm 285 mm, forearm 252 mm, wrist 91 mm, gripper 135 mm to the finger tips), the
table the arm stands on, six joint servos and the gripper servo (``piper_twin.plant`` sets their gains per
drive mode), the parallel gripper coupled to one opening of 0 … 70 mm, and a front and a wrist camera.

Joint angles are the firmware's, as ``piper_control`` itself uses this XML with the angles an arm reports;
its kinematics equal ``piper_sdk``'s FK with ``dh_is_offset=0`` (the SDK's default ``1`` moves the J2 and J3
zeros by 2°; both are checked in the tests). The mechanical stops sit ``STOP_MARGIN_RAD`` inside the
firmware's soft limits, so a limp arm never comes to rest where the firmware refuses to enable it.
"""

from __future__ import annotations

import math
from importlib.resources import files

import mujoco
import numpy as np
from piper_can.safety import SDK_SOFT_LIMITS

NUM_JOINTS = 6
JOINT_NAMES = tuple(f"joint{j}" for j in range(1, NUM_JOINTS + 1))
FINGER_JOINTS = ("joint7", "joint8")
STOP_MARGIN_RAD = math.radians(0.2)
# Arm geoms collide with the world and the objects, never with each other (contype, conaffinity).
ARM_CONTACT = (2, 1)
WORLD_CONTACT = (1, 3)
GRIPPER_MAX_M = 0.07  # the opening between the fingers; each finger travels half of it
TIMESTEP_S = 0.002

# Servo gains, per joint: the firmware plans at most 3 rad/s and the servo tracks that plan with velocity
# feed-forward. With the XML's armature (0.1 kg m^2), kp = 400 N m/rad and kv = 25 N m s/rad (near critical)
# track a 3 rad/s plan within 0.025 rad; the plan's velocity steps at once (the firmware model has no
# acceleration limit), so the joint overshoots the planned speed by < 10 % while it catches up.
JOINT_KP = 400.0
JOINT_KV = 25.0
JOINT_TORQUE_LIMIT_NM = 40.0
GRIPPER_KP = 2000.0  # N/m on one finger's travel
GRIPPER_KV = 30.0
GRIPPER_FORCE_LIMIT_N = 20.0
ESTOP_DAMPING = 30.0  # N m s/rad: an e-stopped arm's motors brake, so it sinks slowly under gravity

_ARM_RGBA = (0.82, 0.83, 0.85, 1.0)
_DARK_RGBA = (0.15, 0.15, 0.17, 1.0)
_TABLE_RGBA = (0.55, 0.42, 0.30, 1.0)


def piper_control_xml() -> str:
    """Path of the installed ``piper_control`` model (joints and inertias only)."""
    return str(files("piper_control") / "models" / "piper_grav_comp.xml")


def _geom(body: mujoco.MjsBody, kind: int, size: tuple[float, ...], **attrs: object) -> mujoco.MjsGeom:
    geom = body.add_geom()
    geom.type = kind
    geom.size = [*size, 0.0, 0.0][:3]
    for name, value in attrs.items():
        setattr(geom, name, value)
    return geom


def _capsule(body: mujoco.MjsBody, start: tuple[float, ...], end: tuple[float, ...], radius: float) -> None:
    _geom(
        body,
        mujoco.mjtGeom.mjGEOM_CAPSULE,
        (radius,),
        fromto=[*start, *end],
        rgba=_ARM_RGBA,
        contype=ARM_CONTACT[0],
        conaffinity=ARM_CONTACT[1],
    )


def look_at_quat(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Orientation (w, x, y, z) of a MuJoCo camera at ``eye`` looking at ``target`` (it looks along its -z)."""
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    mat = np.column_stack([right, np.cross(back, right), back])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, mat.flatten())
    return quat


def _add_arm_geometry(spec: mujoco.MjSpec) -> None:
    base = spec.body("arm_base_link")
    _geom(
        base, mujoco.mjtGeom.mjGEOM_CYLINDER, (0.055, 0.05), pos=[0, 0, 0.05], rgba=_DARK_RGBA, contype=0, conaffinity=0
    )
    _capsule(spec.body("link1"), (0, 0, -0.02), (0, 0, 0.0), 0.045)
    _capsule(spec.body("link2"), (0, 0, 0), tuple(spec.body("link3").pos), 0.04)
    _capsule(spec.body("link3"), (0, 0, 0), tuple(spec.body("link4").pos), 0.035)
    _capsule(spec.body("link5"), (0, 0, 0), tuple(spec.body("link6").pos)[:2] + (0.0,), 0.032)
    # The gripper frame: z along the fingers, y the direction they open in.
    palm = spec.body("gripper")
    _geom(
        palm,
        mujoco.mjtGeom.mjGEOM_BOX,
        (0.03, 0.05, 0.035),
        pos=[0, 0, 0.045],
        rgba=_DARK_RGBA,
        contype=ARM_CONTACT[0],
        conaffinity=ARM_CONTACT[1],
    )
    for name, along in (("finger0", -1.0), ("finger1", 1.0)):
        # Finger frame: the tip at the origin, the finger back toward the palm along y (-y for finger0, +y for
        # the mirrored finger1), its inner face at z = 0.
        _geom(
            spec.body(name),
            mujoco.mjtGeom.mjGEOM_BOX,
            (0.01, 0.028, 0.006),
            pos=[0, along * 0.028, -0.006],
            rgba=_DARK_RGBA,
            friction=[1.5, 0.01, 0.001],
            condim=4,
            contype=ARM_CONTACT[0],
            conaffinity=ARM_CONTACT[1],
        )


def _add_actuators(spec: mujoco.MjSpec) -> None:
    """Servos ``kp (ctrl - q) - kv qdot`` (``piper_twin.plant`` turns them into limp or braking drives)."""
    for name in (*JOINT_NAMES, FINGER_JOINTS[0]):
        finger = name == FINGER_JOINTS[0]
        kp, kv = (GRIPPER_KP, GRIPPER_KV) if finger else (JOINT_KP, JOINT_KV)
        act = spec.add_actuator()
        act.name = "gripper" if finger else name
        act.target = name
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        act.gainprm = [kp] + [0.0] * 9
        act.biasprm = [0.0, -kp, -kv] + [0.0] * 7
        limit = GRIPPER_FORCE_LIMIT_N if finger else JOINT_TORQUE_LIMIT_NM
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-limit, limit]


def _set_joint_stops(spec: mujoco.MjSpec) -> None:
    """Stops just inside the firmware's limits, stiff enough that a resting arm stays inside them."""
    for name, (lower, upper) in zip(JOINT_NAMES, SDK_SOFT_LIMITS.joints_rad, strict=True):
        spec.joint(name).range = [lower + STOP_MARGIN_RAD, upper - STOP_MARGIN_RAD]
    for name in FINGER_JOINTS:
        spec.joint(name).range = [0.0, GRIPPER_MAX_M / 2]
    for joint in spec.joints:
        joint.solref_limit, joint.solimp_limit = [0.004, 1.0], [0.95, 0.99, 0.001, 0.5, 2.0]
    coupling = spec.add_equality()
    coupling.type = mujoco.mjtEq.mjEQ_JOINT
    coupling.objtype = mujoco.mjtObj.mjOBJ_JOINT
    coupling.name1, coupling.name2 = FINGER_JOINTS[1], FINGER_JOINTS[0]


def _add_world(spec: mujoco.MjSpec) -> None:
    world = spec.worldbody
    _geom(
        world,
        mujoco.mjtGeom.mjGEOM_BOX,
        (0.45, 0.5, 0.02),
        pos=[0.25, 0, -0.02],
        rgba=_TABLE_RGBA,
        name="table",
        contype=WORLD_CONTACT[0],
        conaffinity=WORLD_CONTACT[1],
    )
    _geom(
        world,
        mujoco.mjtGeom.mjGEOM_PLANE,
        (2.0, 2.0, 0.1),
        pos=[0, 0, -0.75],
        rgba=(0.3, 0.3, 0.32, 1.0),
        contype=0,
        conaffinity=0,
    )
    light = world.add_light()
    light.pos, light.dir, light.castshadow = [0.3, -0.3, 1.5], [0, 0.2, -1], False
    front = world.add_camera()
    front.name = "front"
    eye = np.array([0.8, 0.0, 0.5])
    front.pos, front.quat = eye, look_at_quat(eye, np.array([0.22, 0.0, 0.1]), np.array([0.0, 0.0, 1.0]))
    front.fovy = 55.0
    wrist = spec.body("gripper").add_camera()
    wrist.name = "wrist"
    # On the palm's x side, past its front face, looking along the fingers and slightly toward them.
    eye = np.array([0.055, 0.0, 0.085])
    wrist.pos = eye
    wrist.quat = look_at_quat(eye, np.array([0.0, 0.0, 0.25]), np.array([1.0, 0.0, 0.0]))
    wrist.fovy = 75.0


def arm_spec() -> mujoco.MjSpec:
    """The PiPER on its table with geometry, servos and cameras, as an editable spec (scenes add objects)."""
    spec = mujoco.MjSpec.from_file(piper_control_xml())
    spec.modelname = "piper_twin"
    # The XML's inertials are the arm's mass model: our geometry must not add to it.
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    spec.option.timestep = TIMESTEP_S
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.visual.global_.offwidth, spec.visual.global_.offheight = 640, 480
    _add_arm_geometry(spec)
    _set_joint_stops(spec)
    _add_actuators(spec)
    _add_world(spec)
    return spec
