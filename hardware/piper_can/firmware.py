"""The simulated PiPER firmware as a pure model: ``handle(frame)`` and ``tick(dt) -> frames``.

No threads, no clock, no I/O: time advances only through ``tick``, so tests step it exactly.
``piper_can.emulator`` runs this model on a python-can bus.

Follower role: 200 Hz feedback (0x2A1..0x2A8, 0x251..0x256) and 40 Hz driver info (0x261..0x266); an
enable state machine with latency and no acknowledgement; joint frames taken only in CAN command mode
(0x151 01) with MOVE J or high-follow, so ignored in standby, e.g. right after a reset (the gripper's
0x159 is taken in any mode, as the vendor's gripper demo, which sends no 0x151, relies on); joints that
move toward their targets at ``max_speed × speed %`` (position mode) or with fast first-order tracking
(high-follow 0xAD); flash limits (clamp or reject, with the firmware's status and error bits); the
gripper; e-stop, and a reset that clears the status at once but switches the motors off
``reset_motor_off_delay_s`` later (as measured on a real arm); firmware older than S-V1.8-5 ignoring
0x151 in high-follow until a reset; no enable for a joint past its limit; 0x475 clear-error; 0x474 /
0x475 joint speed and acceleration caps; 0x477 / 0x47A / 0x47B collision-protection levels;
firmware-version and limit replies; host frames lost on the firmware's side (``lose_next``); motor currents
(0x25x) that grow with the position error a motor is driven against, e.g. a joint held by contact
(``block_joint`` here, the plant's contact with one), with the current sensor's 1 mA noise. Leader role
(0x470 0xFA): emits 0x151 / 0x155..0x157 / 0x159 from a scripted or given trajectory and ignores host
commands.

The joints and the gripper move kinematically unless a ``Plant`` is given (``piper_twin``'s physics): then
the firmware's motion planner produces setpoints and drive modes (servo, limp when disabled, damped when
e-stopped) and reports whatever positions the plant reaches.
"""

from __future__ import annotations

import logging
import math
import random
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

from .codec import (
    ACCEL_NO_CHANGE,
    DLC,
    ENABLED_BIT,
    FEEDBACK_IDS,
    GRIPPER_EFFORT_MAX_NM,
    ID_END_POSE,
    ID_FIRMWARE,
    ID_LOW_SPEED,
    MIT_MODE_HIGH_FOLLOW,
    MIT_MODE_POSITION_VELOCITY,
    MOTOR_ALL,
    MOTOR_ALL_JOINTS,
    NUM_JOINTS,
    PARAM_QUERY_COLLISION,
    ArmStatus,
    ArmStatusCode,
    CodecError,
    CollisionProtectionConfig,
    CollisionProtectionLevels,
    CtrlMode,
    EmergencyStop,
    EStopAction,
    FirmwareChunk,
    FirmwareQuery,
    Frame,
    GripperCommand,
    GripperFeedback,
    GripperStatusCode,
    HighSpeedInfo,
    InstructionResponse,
    JointCommand,
    JointConfig,
    LimitQuery,
    Linkage,
    LowSpeedInfo,
    MasterSlaveConfig,
    ModeControl,
    MotorAccelLimit,
    MotorEnable,
    MotorLimits,
    MotorLimitsSet,
    MoveMode,
    ParamQuery,
    decode_command,
    encode,
    encode_joint_positions,
    encode_joint_targets,
    firmware_release,
    parse_firmware_version,
)
from .safety import SDK_SOFT_LIMITS, JointLimits, clamp

log = logging.getLogger(__name__)

LeaderTrajectory = Callable[[float], tuple[Sequence[float], float]]

# 0x26x byte 5 bits that fault injection can set, by name.
DRIVER_FAULTS = {
    "low_voltage": 0,
    "over_temp": 1,
    "over_current": 2,
    "driver_over_temp": 3,
    "collision": 4,
    "driver_error": 5,
    "stall": 7,
}
# Firmware from this release on accepts leaving high-follow without a reset.
LEAVES_HIGH_FOLLOW_WITHOUT_RESET = (1, 8, 5)
_VALID_CTRL_MODES = {0x00, 0x01, 0x03, 0x04, 0x07}
_VALID_MIT_MODES = {MIT_MODE_POSITION_VELOCITY, MIT_MODE_HIGH_FOLLOW, 0xFF}
_CLEARABLE_STATUS = {ArmStatusCode.COLLISION, ArmStatusCode.JOINT_COMM_ERROR, ArmStatusCode.JOINT_STATUS_ERROR}
_REACHED_TOLERANCE_RAD = 1e-4
_LIMIT_TOLERANCE_RAD = 1e-6
_TIME_EPS = 1e-12
_ARM_IDS = FEEDBACK_IDS | set(ID_END_POSE)  # arm -> host frames (0x4AF only when it is not a query)
# The 0x25x current of an enabled motor (A): what it draws holding, per rad/s of speed, and per rad of
# position error it is driven against (its position controller's P effort: the planner's setpoint minus
# where the joint is, which only contact or a load makes large), up to the motor's limit; then the current
# sensor's noise, a uniform whole number of mA in ±CURRENT_NOISE_MA (0x25x carries 1 mA steps), so a live
# arm's 0x25x frames do not repeat for long while a stuck sender's do.
CURRENT_HOLD_A = 0.2
CURRENT_PER_RAD_S_A = 0.5
CURRENT_PER_RAD_A = 10.0
CURRENT_MAX_A = 8.0
CURRENT_NOISE_MA = 1


def scripted_leader(t: float) -> tuple[tuple[float, ...], float]:
    """Default leader trajectory: slow sines (< 0.5 rad/s) around a pose well inside the limits."""
    centre = (0.0, 0.8, -0.8, 0.0, 0.3, 0.0)
    amplitude = (0.4, 0.3, 0.3, 0.4, 0.3, 0.5)
    joints = tuple(
        c + a * math.sin(2 * math.pi * 0.15 * t + j) for j, (c, a) in enumerate(zip(centre, amplitude, strict=True))
    )
    return joints, 0.035 + 0.025 * math.sin(2 * math.pi * 0.2 * t)


Drive = Literal["servo", "limp", "damped"]


@dataclass(frozen=True, slots=True)
class PlantCommand:
    """What the firmware asks of the motors for one step: the planned setpoints (rad, m), their planned
    velocities, and per motor ``servo`` (track), ``limp`` (no torque) or ``damped`` (e-stop brake)."""

    setpoints_rad: tuple[float, ...]
    velocities_rad_s: tuple[float, ...]
    drives: tuple[Drive, ...]
    gripper_setpoint_m: float
    gripper_drive: Drive


@dataclass(frozen=True, slots=True)
class PlantState:
    """Where the motors are: joint angles (rad), joint velocities (rad/s), gripper opening (m)."""

    joints_rad: tuple[float, ...]
    velocities_rad_s: tuple[float, ...]
    gripper_m: float


class Plant(Protocol):
    """The physical arm the firmware drives (``piper_twin.plant.TwinPlant``)."""

    def state(self) -> PlantState: ...

    def step(self, dt: float, command: PlantCommand) -> PlantState: ...


@dataclass
class EmulatorConfig:
    """Behaviour of the simulated firmware (and, for ``rate_scale`` / ``jitter_s``, of its bus runner)."""

    role: Literal["follower", "leader"] = "follower"
    profile: Literal["full", "light"] = "full"  # light: 0x2A1, 0x2A5..0x2A8 and 0x261..0x266 only
    period_s: float = 0.005
    low_speed_period_s: float = 0.025
    rate_scale: float = 1.0  # real-time runner only: wall period = period_s / rate_scale
    jitter_s: float = 0.0  # real-time runner only: extra random delay per cycle
    seed: int = 0
    rest_pose_rad: tuple[float, ...] = (0.0,) * NUM_JOINTS
    initial_pose_rad: tuple[float, ...] | None = None
    limits: JointLimits = SDK_SOFT_LIMITS  # the flash limits (0x473)
    limit_policy: Literal["clamp", "reject"] = "clamp"
    max_speed_rad_s: float = 3.0
    follow_time_constant_s: float = 0.02
    gripper_speed_m_s: float = 0.1
    enable_latency_s: float = 0.02
    double_enable_after_reset: bool = False
    # After a reset (0x150 02) the status clears at once but the motors switch off this much later.
    reset_motor_off_delay_s: float = 0.727
    apply_joint_targets: Literal["pair", "full"] = "pair"
    estop_sag_rad_s: float = 0.05
    disabled_behaviour: Literal["hold", "drop"] = "hold"
    drop_rad_s: float = 1.0
    start_enabled: bool = False  # enabled in CAN mode and high-follow, as after a hardware-linked leader
    # A real arm refuses to enable a joint that sits past its limit (e.g. J2 slightly below 0 rad).
    refuse_enable_past_limit: bool = True
    # Collision-protection level per joint as stored in flash (0 = detection off, 1..8); 0x47A changes it.
    collision_levels: tuple[int, ...] = (1,) * NUM_JOINTS
    strict: bool = False  # log every ignored frame
    firmware_text: str = "H-V1.2-1 S-V1.8-2 P-V1.0.0 PiPER emulator"
    firmware_frames: int = 11
    leader_trajectory: LeaderTrajectory | None = scripted_leader
    log_size: int = 20_000

    @property
    def high_follow_needs_reset(self) -> bool:
        """Whether this firmware ignores 0x151 in high-follow until a reset (older than S-V1.8-5)."""
        release = firmware_release(parse_firmware_version(self.firmware_text.encode("ascii")))
        return release is None or release < LEAVES_HIGH_FOLLOW_WITHOUT_RESET


@dataclass(frozen=True, slots=True)
class LoggedFrame:
    """One frame in the firmware's log: simulated time, direction (``rx`` host->arm, ``tx``), frame."""

    time_s: float
    direction: Literal["rx", "tx"]
    arbitration_id: int
    data: bytes


@dataclass
class _Joint:
    position: float
    target: float
    setpoint: float  # the planner's output: the position itself on the kinematic model
    velocity: float = 0.0
    enabled: bool = False
    fault_bits: int = 0
    blocked: bool = False  # held where it is (kinematic model): contact, a hard stop


@dataclass
class _PendingEnable:
    due_s: float
    joints: tuple[int, ...]
    enable: bool


@dataclass
class _Gripper:
    opening: float = 0.0
    target: float = 0.0
    setpoint: float = 0.0
    effort: float = 0.0
    enabled: bool = False
    zero_offset: float = 0.0
    fault_bits: int = 0


class PiperFirmware:
    """The firmware of one simulated PiPER. Inspect ``joints_rad``, ``enabled``, ``gripper_m``,
    ``ctrl_mode``, ``ignored`` (reason -> count) and ``frame_log`` in tests. With ``plant`` the motors are
    that plant's (the pose at power-on is the plant's, not ``initial_pose_rad``)."""

    def __init__(self, config: EmulatorConfig | None = None, plant: Plant | None = None) -> None:
        self.config = config or EmulatorConfig()
        self.plant = plant
        self.frame_log: deque[LoggedFrame] = deque(maxlen=self.config.log_size)
        self.ignored: Counter[str] = Counter()
        self.drop_ids: set[int] = set()
        # Host frames that reach the bus but are lost on the firmware's side: ID -> how many more to lose.
        self.lose_next: Counter[int] = Counter()
        self.silent = False
        self.leader_pose: tuple[tuple[float, ...], float] | None = None
        self._frozen: list[Frame] | None = None
        self._last_feedback: dict[int, Frame] = {}  # the newest feedback frame per ID, for freeze_feedback
        self._pending_role: str | None = None
        # Flash settings (kept over power cycles): 0x474 joint speed caps (the model reads 0x474/0x473 speeds
        # in 0.01 rad/s), 0x475 acceleration caps (reported, not modelled), 0x47A collision levels.
        self.joint_max_speed_rad_s = [self.config.max_speed_rad_s] * NUM_JOINTS
        self.joint_max_accel_rad_s2 = [5.0] * NUM_JOINTS
        self.collision_levels = tuple(self.config.collision_levels)
        self._sensor_noise = random.Random(self.config.seed)
        self.power_cycle()

    # ------------------------------------------------------------------------- ground truth
    @property
    def joints_rad(self) -> tuple[float, ...]:
        return tuple(j.position for j in self._joints)

    @property
    def targets_rad(self) -> tuple[float, ...]:
        return tuple(j.target for j in self._joints)

    @property
    def enabled(self) -> tuple[bool, ...]:
        return tuple(j.enabled for j in self._joints)

    @property
    def gripper_m(self) -> float:
        return self._gripper.opening - self._gripper.zero_offset

    @property
    def gripper_enabled(self) -> bool:
        return self._gripper.enabled

    @property
    def estopped(self) -> bool:
        return self._estop

    @property
    def motor_off_pending(self) -> bool:
        """A reset was received and the motors have not switched off yet."""
        return self._motor_off_at is not None

    def power_cycle(self) -> None:
        """Power off and on: everything back to the initial state; a pending role change applies."""
        cfg = self.config
        pose = cfg.initial_pose_rad or cfg.rest_pose_rad
        gripper = 0.0
        if self.plant is not None:
            state = self.plant.state()
            pose, gripper = state.joints_rad, state.gripper_m
        if len(pose) != NUM_JOINTS:
            raise ValueError(f"the emulator pose needs {NUM_JOINTS} angles, got {len(pose)}")
        self.role = self._pending_role or cfg.role
        self._pending_role = None
        self._joints = [_Joint(p, p, p, enabled=cfg.start_enabled) for p in pose]
        self._gripper = _Gripper(gripper, gripper, gripper, enabled=cfg.start_enabled)
        self._pending: list[_PendingEnable] = []
        self._latched: dict[int, tuple[float, float]] = {}  # JointCtrl pairs by first joint
        self._rejected: set[int] = set()
        self._motor_off_at: float | None = None
        self.time_s = 0.0
        self._next_low_speed_s = cfg.period_s  # the first cycle carries 0x261..0x266
        self.ctrl_mode = CtrlMode.CAN if cfg.start_enabled else CtrlMode.STANDBY
        self.move_mode = MoveMode.J
        self.speed_percent = 100 if cfg.start_enabled else 0
        self.mit_mode = MIT_MODE_HIGH_FOLLOW if cfg.start_enabled else MIT_MODE_POSITION_VELOCITY
        self.arm_status = ArmStatusCode.NORMAL
        self.comm_error_mask = 0
        self._estop = False
        self._enables_since_reset = 0
        self._high_follow_locked = cfg.start_enabled and cfg.high_follow_needs_reset
        if self.role == "leader":
            self.ctrl_mode = CtrlMode.LINKAGE_TEACH

    # --------------------------------------------------------------------------- faults
    def inject_fault(self, kind: str, joint: int) -> None:
        """Set a fault: ``comm_error`` (0x2A1 byte 7 + status 0x05) or a driver bit of ``DRIVER_FAULTS``
        (``collision`` also sets status 0x07). ``joint`` 7 is the gripper (driver bits only)."""
        if kind == "comm_error":
            if not 1 <= joint <= NUM_JOINTS:
                raise ValueError(f"comm_error needs a joint 1..6, got {joint}")
            self.comm_error_mask |= 1 << (joint - 1)
            self.arm_status = ArmStatusCode.JOINT_COMM_ERROR
            return
        if kind not in DRIVER_FAULTS:
            raise ValueError(f"unknown fault {kind!r}; known: comm_error, {', '.join(DRIVER_FAULTS)}")
        bit = 1 << DRIVER_FAULTS[kind]
        if joint == NUM_JOINTS + 1:
            self._gripper.fault_bits |= bit
        elif 1 <= joint <= NUM_JOINTS:
            self._joints[joint - 1].fault_bits |= bit
            if kind == "collision":
                self.arm_status = ArmStatusCode.COLLISION
        else:
            raise ValueError(f"joint must be 1..7 (7 = gripper), got {joint}")

    def clear_faults(self, joints: Sequence[int] | None = None, gripper: bool = True) -> None:
        """Clear the driver bits of ``joints`` (default all) and the gripper's, and their communication
        errors; the status returns to normal once no joint fault is left (an e-stop stays)."""
        for j in range(1, NUM_JOINTS + 1) if joints is None else joints:
            self._joints[j - 1].fault_bits = 0
            self.comm_error_mask &= ~(1 << (j - 1))
        if gripper:
            self._gripper.fault_bits = 0
        no_faults = self.comm_error_mask == 0 and not any(j.fault_bits for j in self._joints)
        if no_faults and self.arm_status in _CLEARABLE_STATUS:
            self.arm_status = ArmStatusCode.NORMAL

    def freeze_feedback(self, frozen: bool = True) -> None:
        """Keep emitting, but the frames last emitted, bit for bit (a stuck sender: values stop changing)."""
        if not frozen:
            self._frozen = None
            return
        self._frozen = [*self._last_feedback.values()] or self._feedback_frames(low_speed=True)

    def set_position(self, joint: int, position_rad: float) -> None:
        """Force a joint (e.g. pushed by hand past a limit); its target follows. Kinematic model only."""
        if self.plant is not None:
            raise RuntimeError("a plant's joints move by physics only")
        self._joints[joint - 1].position = position_rad
        self._joints[joint - 1].target = position_rad
        self._joints[joint - 1].setpoint = position_rad

    def block_joint(self, joint: int, blocked: bool = True) -> None:
        """Hold a joint where it is (pressing on a button or the table, at a hard stop): its planner's setpoint
        runs on toward the target and its motor pushes against the error. Released, it moves on from where it
        is at the mode's speed. Kinematic model only."""
        if self.plant is not None:
            raise RuntimeError("a plant's joints are held by its own contacts")
        held = self._joints[joint - 1]
        held.blocked = blocked
        if not blocked:
            held.setpoint = held.position

    def set_enabled(self, joint: int, enabled: bool) -> None:
        """Force a joint's driver on or off (e.g. a driver that cut out), without any host frame."""
        self._joints[joint - 1].enabled = enabled
        self._joints[joint - 1].target = self._joints[joint - 1].position

    # ----------------------------------------------------------------------- host frames
    def handle(self, frame: Frame, extended_id: bool = False) -> list[Frame]:
        """Apply one received frame as the firmware would; returns the frames it answers at once."""
        frame_id, data = frame.arbitration_id, bytes(frame.data)
        if frame_id in _ARM_IDS and not (frame_id == ID_FIRMWARE and data[:1] == b"\x01"):
            return []  # another arm's feedback, or our own echoed back by the bus
        self.frame_log.append(LoggedFrame(self.time_s, "rx", frame_id, data))
        if self.silent:
            return []
        if self.lose_next[frame_id] > 0:
            self.lose_next[frame_id] -= 1
            return self._ignore("lost", frame)
        if extended_id or len(data) != DLC:
            return self._ignore("wrong DLC or extended ID", frame)
        try:
            command = decode_command(frame_id, data)
        except CodecError:
            return self._ignore("invalid value", frame)
        if command is None:
            return self._ignore("unknown ID", frame)
        if self.role == "leader" and not isinstance(command, MasterSlaveConfig | FirmwareQuery):
            return self._ignore("leader ignores commands", frame)
        replies: list[Frame] = []
        match command:
            case EmergencyStop():
                self._on_estop(command)
            case ModeControl():
                self._on_mode(command, frame)
            case JointCommand():
                self._on_joints(command, frame)
            case GripperCommand():
                self._on_gripper(command, frame)
            case MotorEnable():
                self._on_enable(command, frame)
            case LimitQuery():
                replies = self._limit_replies(command)
            case FirmwareQuery():
                replies = self._firmware_replies()
            case MasterSlaveConfig():
                self._on_master_slave(command)
            case JointConfig():
                replies = self._on_joint_config(command, frame)
            case MotorLimitsSet():
                replies = self._on_limits_set(command, frame)
            case ParamQuery():
                replies = self._on_param_query(command, frame)
            case CollisionProtectionConfig():
                self.collision_levels = command.levels
                replies = [encode(InstructionResponse(0x7A))]
        return self._emit([f for f in replies if f.arbitration_id not in self.drop_ids])

    def _ignore(self, reason: str, frame: Frame) -> list[Frame]:
        self.ignored[reason] += 1
        if self.config.strict:
            log.warning("PiPER emulator ignored 0x%X %s: %s", frame.arbitration_id, bytes(frame.data).hex(" "), reason)
        return []

    def _on_estop(self, cmd: EmergencyStop) -> None:
        if cmd.action == EStopAction.STOP:
            self._estop = True
            self.arm_status = ArmStatusCode.EMERGENCY_STOP
        elif cmd.action == EStopAction.RESUME:  # reset: clear errors and modes now, motors off a bit later
            self._estop = False
            self.clear_faults()
            self.arm_status = ArmStatusCode.NORMAL
            for j in self._joints:
                j.target = j.position
            self._gripper.target = self._gripper.opening
            self._pending.clear()
            self._latched.clear()
            self.ctrl_mode = CtrlMode.STANDBY
            self.mit_mode = MIT_MODE_POSITION_VELOCITY
            self._enables_since_reset = 0
            self._high_follow_locked = False
            self._motor_off_at = self.time_s + self.config.reset_motor_off_delay_s
            self._apply_due_events()

    def _on_mode(self, cmd: ModeControl, frame: Frame) -> None:
        if (
            cmd.ctrl_mode not in _VALID_CTRL_MODES
            or cmd.move_mode > 0x06
            or cmd.speed_percent > 100
            or cmd.mit_mode not in _VALID_MIT_MODES
        ):
            self._ignore("invalid value", frame)
            return
        if self._high_follow_locked and cmd.mit_mode != MIT_MODE_HIGH_FOLLOW:
            self._ignore("leaving high-follow without reset", frame)
            return
        self.ctrl_mode = CtrlMode(cmd.ctrl_mode)
        self.move_mode = cmd.move_mode
        self.speed_percent = cmd.speed_percent
        self.mit_mode = cmd.mit_mode
        if cmd.mit_mode == MIT_MODE_HIGH_FOLLOW and self.config.high_follow_needs_reset:
            self._high_follow_locked = True

    def _motion_refusal(self, joints: Sequence[int]) -> str | None:
        if self._estop:
            return "e-stop"
        if self.ctrl_mode != CtrlMode.CAN or not (
            self.move_mode == MoveMode.J or self.mit_mode == MIT_MODE_HIGH_FOLLOW
        ):
            return "wrong mode"
        if not all(self._joints[j - 1].enabled for j in joints):
            return "disabled"
        return None

    def _on_joints(self, cmd: JointCommand, frame: Frame) -> None:
        first = cmd.first_joint
        reason = self._motion_refusal((first, first + 1))
        if reason is not None:
            self._ignore(reason, frame)
            return
        self._latched[first] = cmd.positions_rad
        if self.config.apply_joint_targets == "full" and len(self._latched) < 3:
            return
        targets: dict[int, float] = {}
        for pair_first, pair in self._latched.items():
            targets[pair_first], targets[pair_first + 1] = pair
        self._latched.clear()
        bounds = {j: self.config.limits.joints_rad[j - 1] for j in targets}
        outside = {j for j, t in targets.items() if not bounds[j][0] <= t <= bounds[j][1]}
        if outside and self.config.limit_policy == "reject":
            self._rejected |= outside
            self.arm_status = ArmStatusCode.TARGET_EXCEEDS_LIMIT
            self._ignore("out of range", frame)
            return
        self._rejected -= targets.keys()
        if not self._rejected and self.arm_status == ArmStatusCode.TARGET_EXCEEDS_LIMIT:
            self.arm_status = ArmStatusCode.NORMAL  # a valid target for every rejected joint clears it
        for j, t in targets.items():
            self._joints[j - 1].target = clamp(t, *bounds[j])

    def _on_gripper(self, cmd: GripperCommand, frame: Frame) -> None:
        if self.config.strict and cmd.effort_nm > GRIPPER_EFFORT_MAX_NM:
            self._ignore("out of range", frame)
            return
        g = self._gripper
        if cmd.status_code in (GripperStatusCode.DISABLE_CLEAR_ERROR, GripperStatusCode.ENABLE_CLEAR_ERROR):
            g.fault_bits = 0
        g.enabled = cmd.status_code in (GripperStatusCode.ENABLE, GripperStatusCode.ENABLE_CLEAR_ERROR)
        if cmd.set_zero:
            g.zero_offset = g.opening
        if not g.enabled or self._estop:
            g.target = g.opening
            return
        g.effort = min(cmd.effort_nm, GRIPPER_EFFORT_MAX_NM)
        g.target = clamp(cmd.opening_m + g.zero_offset, *self.config.limits.gripper_m)

    def _on_enable(self, cmd: MotorEnable, frame: Frame) -> None:
        if cmd.motor in (MOTOR_ALL_JOINTS, MOTOR_ALL):
            joints = tuple(range(1, NUM_JOINTS + 1))
        elif 1 <= cmd.motor <= NUM_JOINTS:
            joints = (cmd.motor,)
        else:
            self._ignore("invalid value", frame)
            return
        if cmd.enable:
            self._enables_since_reset += 1
            if self.config.double_enable_after_reset and self._enables_since_reset < 2:
                return
            if self.config.refuse_enable_past_limit:
                inside = tuple(j for j in joints if self._within_limits(j))
                if inside != joints:
                    self._ignore("joint past its limit", frame)
                    joints = inside
        self._pending.append(_PendingEnable(self.time_s + self.config.enable_latency_s, joints, cmd.enable))

    def _within_limits(self, joint: int) -> bool:
        lower, upper = self.config.limits.joints_rad[joint - 1]
        position = self._joints[joint - 1].position
        return lower - _LIMIT_TOLERANCE_RAD <= position <= upper + _LIMIT_TOLERANCE_RAD

    def _on_joint_config(self, cmd: JointConfig, frame: Frame) -> list[Frame]:
        if cmd.set_zero:
            self._ignore("unsupported setting", frame)
            return []
        if cmd.accel_valid and cmd.max_accel_raw != ACCEL_NO_CHANGE:
            for j in range(1, NUM_JOINTS + 1) if cmd.joint == NUM_JOINTS + 1 else (cmd.joint,):
                self.joint_max_accel_rad_s2[j - 1] = cmd.max_accel_raw / 100
        if cmd.clear_error:
            self.clear_faults(range(1, NUM_JOINTS + 1) if cmd.joint == NUM_JOINTS + 1 else (cmd.joint,), False)
        return [encode(InstructionResponse(0x75))]

    def _on_limits_set(self, cmd: MotorLimitsSet, frame: Frame) -> list[Frame]:
        if cmd.max_angle_rad is not None or cmd.min_angle_rad is not None:
            self._ignore("unsupported setting", frame)  # the flash angle limits stay EmulatorConfig.limits
            return []
        if cmd.max_speed_raw is not None:
            self.joint_max_speed_rad_s[cmd.motor - 1] = cmd.max_speed_raw / 100
        return [encode(InstructionResponse(0x74))]

    def _on_param_query(self, cmd: ParamQuery, frame: Frame) -> list[Frame]:
        if cmd.enquiry != PARAM_QUERY_COLLISION:
            self._ignore("unsupported setting", frame)
            return []
        return [encode(CollisionProtectionLevels(self.collision_levels))]

    def _limit_replies(self, cmd: LimitQuery) -> list[Frame]:
        motors = range(1, NUM_JOINTS + 1) if cmd.motor in (0, MOTOR_ALL) else (cmd.motor,)
        replies = []
        for m in motors:
            if not 1 <= m <= NUM_JOINTS:
                continue
            if cmd.kind == 0x01:
                lower, upper = self.config.limits.joints_rad[m - 1]
                max_speed_raw = round(self.joint_max_speed_rad_s[m - 1] * 100)
                replies.append(encode(MotorLimits(m, upper, lower, max_speed_raw)))
            elif cmd.kind == 0x02:
                replies.append(encode(MotorAccelLimit(m, self.joint_max_accel_rad_s2[m - 1])))
        return replies

    def _firmware_replies(self) -> list[Frame]:
        n = self.config.firmware_frames
        text = self.config.firmware_text.encode("ascii")[: n * DLC].ljust(n * DLC, b"\x00")
        return [encode(FirmwareChunk(text[i * DLC : (i + 1) * DLC])) for i in range(n)]

    def _on_master_slave(self, cmd: MasterSlaveConfig) -> None:
        if cmd.linkage == Linkage.LEADER:
            self.role = "leader"
            self.ctrl_mode = CtrlMode.LINKAGE_TEACH
        elif cmd.linkage == Linkage.FOLLOWER and self.role == "leader":
            self._pending_role = "follower"  # the firmware needs a power cycle to leave the leader role

    # ---------------------------------------------------------------------------- physics
    def tick(self, dt: float) -> list[Frame]:
        """Advance ``dt`` seconds and return the frames of one emission cycle."""
        if dt < 0:
            raise ValueError(f"dt must not be negative, got {dt}")
        self.time_s += dt
        self._apply_due_events()
        if self.plant is None:
            self._move_joints(dt)
            self._move_gripper(dt)
        else:
            self._drive_plant(self.plant, dt)
        return self._emit(self._cycle_frames())

    def _apply_due_events(self) -> None:
        if self._motor_off_at is not None and self._motor_off_at <= self.time_s + _TIME_EPS:
            self._motor_off_at = None
            self._pending = [p for p in self._pending if p.due_s > self.time_s + _TIME_EPS]
            for joint in self._joints:
                joint.enabled = False
                joint.target = joint.position
            self._gripper.enabled = False
        due = [p for p in self._pending if p.due_s <= self.time_s + _TIME_EPS]
        self._pending = [p for p in self._pending if p.due_s > self.time_s + _TIME_EPS]
        for p in due:
            for j in p.joints:
                joint = self._joints[j - 1]
                if joint.enabled != p.enable:  # a repeated enable keeps the current target
                    joint.enabled = p.enable
                    joint.target = joint.position

    def _speed(self, j: int) -> float:
        high_follow = self.mit_mode == MIT_MODE_HIGH_FOLLOW
        speed_all = self.config.max_speed_rad_s * (1.0 if high_follow else self.speed_percent / 100)
        return min(speed_all, self.joint_max_speed_rad_s[j])

    def _plan(self, j: int, joint: _Joint, dt: float) -> float:
        """The planner's next setpoint of an enabled joint: at the mode's speed, or high-follow tracking."""
        speed = self._speed(j)
        if self.mit_mode == MIT_MODE_HIGH_FOLLOW:
            alpha = 1.0 - math.exp(-dt / self.config.follow_time_constant_s)
            setpoint = joint.setpoint + clamp((joint.target - joint.setpoint) * alpha, -speed * dt, speed * dt)
            return joint.target if abs(joint.target - setpoint) < _REACHED_TOLERANCE_RAD else setpoint
        return _toward(joint.setpoint, joint.target, speed * dt)

    def _move_joints(self, dt: float) -> None:
        cfg = self.config
        for j, joint in enumerate(self._joints):
            before = joint.position
            if self._estop:
                joint.position = _toward(joint.position, cfg.rest_pose_rad[j], cfg.estop_sag_rad_s * dt)
                joint.target = joint.position
            elif not joint.enabled:
                if cfg.disabled_behaviour == "drop":
                    joint.position = _toward(joint.position, cfg.rest_pose_rad[j], cfg.drop_rad_s * dt)
                joint.target = joint.position
            else:
                joint.position = self._plan(j, joint, dt)
            joint.setpoint = joint.position
            if joint.blocked:
                joint.position = before
            joint.velocity = (joint.position - before) / dt if dt > 0 else 0.0

    def _move_gripper(self, dt: float) -> None:
        g = self._gripper
        if g.enabled and not self._estop:
            g.opening = _toward(g.opening, g.target, self.config.gripper_speed_m_s * dt)
        g.setpoint = g.opening

    def _drive_plant(self, plant: Plant, dt: float) -> None:
        """One step of the plant: enabled motors servo to the planned setpoints; disabled ones go limp (the
        arm falls), an e-stop brakes them all; the plan of a motor not servoing restarts where it is."""
        setpoints, velocities, drives = [], [], []
        for j, joint in enumerate(self._joints):
            if self._estop or not joint.enabled:
                joint.setpoint = joint.target = joint.position
                velocities.append(0.0)
                drives.append("damped" if self._estop else "limp")
            else:
                before = joint.setpoint
                joint.setpoint = self._plan(j, joint, dt)
                velocities.append((joint.setpoint - before) / dt if dt > 0 else 0.0)
                drives.append("servo")
            setpoints.append(joint.setpoint)
        g = self._gripper
        gripper_drive: Drive = "servo" if g.enabled and not self._estop else "limp"
        if gripper_drive == "servo":
            g.setpoint = _toward(g.setpoint, g.target, self.config.gripper_speed_m_s * dt)
        else:
            g.setpoint = g.target = g.opening
        command = PlantCommand(tuple(setpoints), tuple(velocities), tuple(drives), g.setpoint, gripper_drive)
        state = plant.step(dt, command)
        for joint, position, velocity in zip(self._joints, state.joints_rad, state.velocities_rad_s, strict=True):
            joint.position, joint.velocity = position, velocity
        g.opening = state.gripper_m

    # ---------------------------------------------------------------------------- emission
    def _emit(self, frames: list[Frame]) -> list[Frame]:
        for f in frames:
            self.frame_log.append(LoggedFrame(self.time_s, "tx", f.arbitration_id, f.data))
        return frames

    def _cycle_frames(self) -> list[Frame]:
        if self.silent:
            return []
        if self.role == "leader":
            return self._leader_frames()
        low_speed = self.time_s >= self._next_low_speed_s - 1e-9
        if low_speed:  # on an ideal 40 Hz grid, so late cycles do not lower the average rate
            self._next_low_speed_s += self.config.low_speed_period_s
            if self._next_low_speed_s <= self.time_s:  # far behind: restart the grid, no burst
                self._next_low_speed_s = self.time_s + self.config.low_speed_period_s
        if self._frozen is None:
            frames = self._feedback_frames(low_speed)
            self._last_feedback.update((f.arbitration_id, f) for f in frames)
        else:
            frames = [f for f in self._frozen if low_speed or f.arbitration_id not in ID_LOW_SPEED]
        return [f for f in frames if f.arbitration_id not in self.drop_ids]

    def _feedback_frames(self, low_speed: bool) -> list[Frame]:
        full = self.config.profile == "full"
        frames = [encode(self._status())]
        if full:
            frames += [Frame(i, bytes(DLC)) for i in ID_END_POSE]
        frames += encode_joint_positions(self.joints_rad)
        g = self._gripper
        gripper_status = g.fault_bits | (1 << ENABLED_BIT if g.enabled else 0)
        frames.append(encode(GripperFeedback(self.gripper_m, g.effort if g.enabled else 0.0, gripper_status)))
        if full:
            for j, joint in enumerate(self._joints, start=1):
                frames.append(encode(HighSpeedInfo(j, joint.velocity, self._current(joint), joint.position)))
        if low_speed:
            for j, joint in enumerate(self._joints, start=1):
                status = joint.fault_bits | (1 << ENABLED_BIT if joint.enabled else 0)
                bus_current = (0.3 if joint.enabled else 0.05) if j <= 3 else 0.0
                frames.append(encode(LowSpeedInfo(j, 24.0, 30, 28, status, bus_current)))
        return frames

    def _current(self, joint: _Joint) -> float:
        """The 0x25x current (A) of one motor; 0 when its driver is off (see ``CURRENT_PER_RAD_A``)."""
        if not joint.enabled:
            return 0.0
        pushed = CURRENT_PER_RAD_A * abs(joint.setpoint - joint.position)
        drawn = min(CURRENT_HOLD_A + CURRENT_PER_RAD_S_A * abs(joint.velocity) + pushed, CURRENT_MAX_A)
        return drawn + self._sensor_noise.randint(-CURRENT_NOISE_MA, CURRENT_NOISE_MA) / 1e3

    def _status(self) -> ArmStatus:
        reached = all(abs(j.target - j.setpoint) < _REACHED_TOLERANCE_RAD for j in self._joints)
        angle_limit_mask = 0
        for j in range(NUM_JOINTS):
            if not self._within_limits(j + 1):
                angle_limit_mask |= 1 << j
        return ArmStatus(
            ctrl_mode=self.ctrl_mode,
            arm_status=self.arm_status,
            mode_feed=self.move_mode,
            motion_status=0 if reached else 1,
            angle_limit_mask=angle_limit_mask,
            comm_error_mask=self.comm_error_mask,
        )

    def _leader_frames(self) -> list[Frame]:
        if self.leader_pose is not None:
            joints, gripper = self.leader_pose
        elif self.config.leader_trajectory is not None:
            joints, gripper = self.config.leader_trajectory(self.time_s)
        else:
            joints, gripper = self.joints_rad, self.gripper_m
        frames = [
            encode(ModeControl(CtrlMode.CAN, MoveMode.J, 100, MIT_MODE_HIGH_FOLLOW)),
            *encode_joint_targets(joints),
            encode(GripperCommand(gripper, 1.0, GripperStatusCode.ENABLE)),
        ]
        return [f for f in frames if f.arbitration_id not in self.drop_ids]


def _toward(value: float, target: float, max_delta: float) -> float:
    """Move ``value`` toward ``target`` by at most ``max_delta``."""
    return value + clamp(target - value, -max_delta, max_delta)
