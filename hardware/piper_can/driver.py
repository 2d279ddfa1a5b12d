"""Safe driver for one PiPER follower arm: enable handshake, clamped joint/gripper commands that are
refused unless feedback shows every motor enabled in the mode we set, stale-feedback watchdog, e-stop
that no motion frame can overtake, resume / clear-error / reset recovery, firmware limits, faults as
exceptions, disconnect policy.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum

from .clock import SYSTEM_CLOCK, Clock
from .codec import (
    GRIPPER_EFFORT_MAX_NM,
    ID_ARM_STATUS,
    ID_EMERGENCY_STOP,
    ID_GRIPPER_FEEDBACK,
    ID_HIGH_SPEED,
    ID_JOINT_FEEDBACK,
    ID_LOW_SPEED,
    ID_MODE_CONTROL,
    LIMIT_QUERY_ANGLE_SPEED,
    MIT_MODE_HIGH_FOLLOW,
    MIT_MODE_POSITION_VELOCITY,
    MOTOR_ALL_JOINTS,
    NUM_JOINTS,
    PARAM_QUERY_COLLISION,
    ArmStatusCode,
    CtrlMode,
    EmergencyStop,
    EStopAction,
    FirmwareQuery,
    Frame,
    GripperCommand,
    GripperStatusCode,
    JointConfig,
    LimitQuery,
    ModeControl,
    MotorEnable,
    MotorLimitsSet,
    MoveMode,
    ParamQuery,
    decode_command,
    encode,
    encode_joint_targets,
    firmware_release,
)
from .errors import (
    ArmNotReadyError,
    CollisionProtectionOffError,
    EmergencyStopError,
    EnableTimeoutError,
    Fault,
    FeedbackStaleError,
    FirmwareFaultError,
    HighFollowError,
    PartialCommandError,
    PiperConnectionError,
    PiperError,
)
from .interlock import NOT_ENABLED, Interlock
from .link import PiperLink
from .safety import SDK_SOFT_LIMITS, JointLimits, check_finite, clamp, safe_target
from .state import ArmState

log = logging.getLogger(__name__)

FEEDBACK_PERIOD_S = 0.005  # 0x2A1..0x2A8 and 0x251..0x256 at 200 Hz
LOW_SPEED_PERIOD_S = 0.025  # 0x261..0x266 (the enable bits) at 40 Hz
ENABLE_BACKOFF_START_S = 0.01
ENABLE_BACKOFF_CAP_S = 0.2
REST_PERIOD_S = 0.02
MODE_RESEND_S = 0.05
REST_TOLERANCE_RAD = 0.01
REST_TOLERANCE_M = 0.002
# The firmware switches the motors off this long after a reset (measured on a real arm).
RESET_MOTOR_OFF_S = 0.73
# An e-stop frame the bus refuses (a full TX queue) is retried every period until this much time passed.
ESTOP_RETRY_S = 0.1
ESTOP_RETRY_PERIOD_S = 0.001
# A joint that stays disabled further than this past its limit is named as why (the firmware does not
# enable a joint past its limit); the rest pose sits exactly on J2's and J3's limits, which is fine.
PAST_LIMIT_RAD = math.radians(0.01)
# Joint feedback that keeps arriving with the very same angles for this long while every command asks
# for a move of at least FROZEN_MIN_MOVE_RAD counts as frozen (a stuck sender, a replayed capture).
FROZEN_AFTER_S = 0.25
# Feedback stamped this long after a reset was sent after the firmware acted on it (it handles host frames
# within its 5 ms cycle): only such a frame showing a motor on proves the reset's countdown is still running.
RESET_ACTED_WITHIN_S = 2 * FEEDBACK_PERIOD_S
FROZEN_MIN_MOVE_RAD = 0.01
# Firmware from this release on leaves high-follow on a plain 0x151; older firmware needs a reset.
LEAVES_HIGH_FOLLOW_WITHOUT_RESET = (1, 8, 5)
# A firmware limit counts as different from a soft limit beyond half its 0.1° resolution.
LIMIT_MISMATCH_RAD = math.radians(0.05)
# An enable() that another host's reset or high-follow request interrupts starts over at most this often.
MAX_ENABLE_RESTARTS = 5
MOTION_MODES = ("position", "high_follow")
# A watchdog looser than this is no watchdog (200 feedback periods; the emulator over UDP needs 0.1-0.3 s).
MAX_FEEDBACK_TIMEOUT_S = 1.0
MAX_JOINT_SPEED_RAD_S = 3.0  # the firmware's own cap (0x474 accepts 0-3 rad/s)
MAX_JOINT_ACCEL_RAD_S2 = 5.0  # the firmware's own cap (0x475 accepts 0-5 rad/s^2)


class DisconnectPolicy(StrEnum):
    """What ``disconnect`` does to an enabled arm."""

    HOLD = "hold"  # stay enabled, holding the last target (the arm does not fall)
    REST = "rest"  # move slowly to the rest pose, then disable; if it cannot get there, hold


class Recovery(StrEnum):
    """What ``enable`` does about faults the firmware reports (``recovery``)."""

    NONE = "none"  # refuse: raise FirmwareFaultError
    CLEAR_ERRORS = "clear_errors"  # 0x475 clear-error (joints) and 0x159 clear-error (gripper), then enable
    RESET = "reset"  # 0x150 reset (the motors switch off for a moment), then enable


class CollisionOff(StrEnum):
    """What ``connect`` does when the arm reports its collision protection off (level 0) on a joint."""

    WARN = "warn"  # log an error and go on
    REFUSE = "refuse"  # raise CollisionProtectionOffError


class HighFollowExit(StrEnum):
    """What ``enable`` in position mode does when old firmware may still be in high-follow."""

    RESET = "reset"  # leave it with the reset sequence (the motors switch off for a moment)
    REFUSE = "refuse"  # raise HighFollowError


@dataclass
class DriverSettings:
    """The plain-valued driver settings, shared as they are by ``PiperFollowerConfig`` (one source)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    # "position": the firmware plans each move at speed_percent; "high_follow": 0xAD, no planning.
    motion_mode: str = "position"
    speed_percent: int = 50
    gripper_effort_nm: float = 1.0
    # Stale-feedback watchdog: no joint, gripper or status frame for longer than this stops commanding.
    feedback_timeout_s: float = 3 * FEEDBACK_PERIOD_S
    connect_timeout_s: float = 1.0
    enable_timeout_s: float = 2.0
    # After a reset, wait up to this long for the firmware's delayed motor-off (~0.73 s) before enabling.
    reset_settle_s: float = 1.0
    high_follow_exit: str = HighFollowExit.RESET
    recovery: str = Recovery.NONE
    read_firmware_limits: bool = True
    # Also read (and watch) 0x251..0x256: joint velocities and efforts.
    use_velocity_and_torque: bool = False
    disconnect_policy: str = DisconnectPolicy.HOLD
    rest_pose_rad: tuple[float, ...] = (0.0,) * NUM_JOINTS
    rest_gripper_m: float = 0.0
    rest_speed_rad_s: float = 0.5
    rest_timeout_s: float = 10.0
    # The arm's collision protection (0x47B) read on connect; level 0 (off) on a joint: warn or refuse.
    collision_off: str = CollisionOff.WARN
    # The firmware's own per-joint caps, written on connect (they persist in the arm): max joint speed
    # (0x474, sent in 0.01 rad/s) and max joint acceleration (0x475, 0.01 rad/s^2). None: left as they are.
    max_joint_speed_rad_s: float | None = None
    max_joint_accel_rad_s2: float | None = None

    def __post_init__(self) -> None:
        self._check_motion()
        if len(self.rest_pose_rad) != NUM_JOINTS:
            raise ValueError(f"rest_pose_rad needs {NUM_JOINTS} angles, got {len(self.rest_pose_rad)}")
        for j, angle in enumerate(self.rest_pose_rad, start=1):
            _check_range(f"rest_pose_rad[{j}]", angle, -math.pi, math.pi)
        _check_range("rest_gripper_m", self.rest_gripper_m, 0.0, 0.1)
        _check_range("gripper_effort_nm", self.gripper_effort_nm, 0.0, GRIPPER_EFFORT_MAX_NM)
        _check_range("feedback_timeout_s", self.feedback_timeout_s, 0.0, MAX_FEEDBACK_TIMEOUT_S, positive=True)
        _check_range("rest_speed_rad_s", self.rest_speed_rad_s, 0.0, MAX_JOINT_SPEED_RAD_S, positive=True)
        # Shorter than the firmware's delayed motor-off, a reset's re-enable would be lost (the arm left limp).
        _check_range("reset_settle_s", self.reset_settle_s, RESET_MOTOR_OFF_S, 60.0)
        for name in ("connect_timeout_s", "enable_timeout_s", "rest_timeout_s"):
            _check_range(name, getattr(self, name), 0.0, 600.0, positive=True)
        if self.max_joint_speed_rad_s is not None:
            _check_range("max_joint_speed_rad_s", self.max_joint_speed_rad_s, 0.01, MAX_JOINT_SPEED_RAD_S)
        if self.max_joint_accel_rad_s2 is not None:
            _check_range("max_joint_accel_rad_s2", self.max_joint_accel_rad_s2, 0.01, MAX_JOINT_ACCEL_RAD_S2)
        if isinstance(self.bitrate, bool) or not isinstance(self.bitrate, int) or self.bitrate <= 0:
            raise ValueError(f"bitrate must be a positive integer, got {self.bitrate!r}")
        for name, kind in (
            ("disconnect_policy", DisconnectPolicy),
            ("recovery", Recovery),
            ("high_follow_exit", HighFollowExit),
            ("collision_off", CollisionOff),
        ):
            value = getattr(self, name)
            if value not in set(kind):
                raise ValueError(f"{name} must be one of {[k.value for k in kind]}, got {value!r}")

    def _check_motion(self) -> None:
        if self.motion_mode not in MOTION_MODES:
            raise ValueError(f"motion_mode must be one of {MOTION_MODES}, got {self.motion_mode!r}")
        check_speed_percent(self.speed_percent)


def check_speed_percent(value: object) -> None:
    """``speed_percent``: an integer 0..100 (the 0x151 byte)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 100:
        raise ValueError(f"speed_percent must be an integer 0..100, got {value!r}")


def _check_range(name: str, value: object, lower: float, upper: float, positive: bool = False) -> None:
    """One clear error unless ``value`` is a finite number in ``[lower, upper]`` (above ``lower`` when
    ``positive``); NaN fails every bound."""
    number = not isinstance(value, bool) and isinstance(value, int | float)
    if number and math.isfinite(value) and (lower < value if positive else lower <= value) and value <= upper:
        return
    bounds = f"({lower}, {upper}]" if positive else f"[{lower}, {upper}]"
    raise ValueError(f"{name} must be a finite number in {bounds}, got {value!r}")


@dataclass
class DriverConfig(DriverSettings):
    """Bus, motion and safety settings of a ``PiperDriver`` (all safety features on by default)."""

    bus_options: Mapping[str, object] = field(default_factory=dict)
    limits: JointLimits = SDK_SOFT_LIMITS
    # LeRobot ``max_relative_target`` semantics: per command, each target stays within this of the
    # measured position. One value or one per joint; None turns the step limit off.
    max_step_rad: float | Sequence[float] | None = 0.2
    max_gripper_step_m: float | None = 0.02

    def __post_init__(self) -> None:
        super().__post_init__()
        steps = self.joint_steps()
        if steps is not None and not all(0 < s and math.isfinite(s) for s in steps):
            raise ValueError(f"max_step_rad must be positive and finite, got {self.max_step_rad}")
        if self.max_gripper_step_m is not None:
            _check_range("max_gripper_step_m", self.max_gripper_step_m, 0.0, math.inf, positive=True)
        for j, (angle, (lower, upper)) in enumerate(zip(self.rest_pose_rad, self.limits.joints_rad, strict=True), 1):
            if not lower <= angle <= upper:
                raise ValueError(f"rest_pose_rad joint_{j} = {angle} is outside its limits [{lower}, {upper}]")
        lower, upper = self.limits.gripper_m
        if not lower <= self.rest_gripper_m <= upper:
            raise ValueError(f"rest_gripper_m = {self.rest_gripper_m} is outside the gripper range [{lower}, {upper}]")

    @classmethod
    def from_settings(cls, settings: DriverSettings, **extra: object) -> DriverConfig:
        """Every ``DriverSettings`` field of ``settings`` (e.g. a robot config), replaced or added by ``extra``."""
        return cls(**{f.name: getattr(settings, f.name) for f in fields(DriverSettings)} | extra)

    @property
    def high_follow(self) -> bool:
        return self.motion_mode == "high_follow"

    def joint_steps(self) -> tuple[float, ...] | None:
        """The per-joint step limit, or None when off."""
        if self.max_step_rad is None:
            return None
        if isinstance(self.max_step_rad, int | float):
            return (float(self.max_step_rad),) * NUM_JOINTS
        steps = tuple(float(s) for s in self.max_step_rad)
        if len(steps) != NUM_JOINTS:
            raise ValueError(f"max_step_rad needs one value or {NUM_JOINTS}, got {len(steps)}")
        return steps


@dataclass(frozen=True, slots=True)
class SentCommand:
    """What actually went on the bus after clamping (``gripper_m`` None: no gripper frame)."""

    joints_rad: tuple[float, ...]
    gripper_m: float | None


def is_motion_recoverable(fault: Fault) -> bool:
    """Faults that commands moving back inside the limits clear (so they do not block them)."""
    return fault.fault in ("angle limit exceeded", "target exceeds limit")


class PiperDriver:
    """Drives one PiPER follower over python-can; every method is safe to call from any thread.

    ``clock`` is the time it runs on (``piper_can.clock``): the system's, or a ``SimulatedClock`` that
    tests step together with an emulated arm, without threads.
    """

    def __init__(self, config: DriverConfig | None = None, clock: Clock = SYSTEM_CLOCK) -> None:
        self.config = config or DriverConfig()
        self.clock = clock
        cfg = self.config
        watched = (*ID_JOINT_FEEDBACK, ID_GRIPPER_FEEDBACK, ID_ARM_STATUS)
        if cfg.use_velocity_and_torque:
            watched += ID_HIGH_SPEED
        watch = dict.fromkeys(watched, cfg.feedback_timeout_s)
        # The enable bits come at 40 Hz: allow them two of their periods more.
        watch |= dict.fromkeys(ID_LOW_SPEED, cfg.feedback_timeout_s + 2 * LOW_SPEED_PERIOD_S)
        self.link = PiperLink(cfg.interface, cfg.channel, cfg.bitrate, cfg.bus_options, watch, "feedback frame", clock)
        self.limits: JointLimits = cfg.limits  # the soft limits, narrowed to the firmware's on connect
        self._interlock = Interlock()
        # One lifecycle operation (enable, reset, recover, disable, disconnect) at a time; e-stops never wait.
        self._operation = threading.RLock()
        self._disconnecting = False  # only the disconnect policy's own rest walk may command meanwhile
        self._reset_sent_at: float | None = None
        self._may_be_high_follow = False
        # All on the monotonic clock the link stamps frames on. When the running (or last) enable() began.
        self._session_start = 0.0
        # Another host's resets stamped up to this were waited out; a newer one restarts an enable in
        # flight, or latches motion after it.
        self._resets_waited = 0.0
        # Another host's high-follow requests (0x151 … AD) after this need the exit (set by enable and reset).
        self._high_follow_since = 0.0
        # Another host's mode changes (0x151) after our confirmed 0x151 latch motion unless they are ours.
        self._mode_mark = 0.0
        self._reported_faults: tuple[Fault, ...] = ()
        # While commanding moves: the joint angles last seen, the stamp they were first seen with, and the
        # stamp of the last command that asked for a move.
        self._unchanged: tuple[tuple[float, ...], float, float] | None = None

    # ------------------------------------------------------------------------------ lifecycle
    @property
    def is_connected(self) -> bool:
        return self.link.is_open

    @property
    def estopped(self) -> bool:
        return self._interlock.estopped

    def connect(self, listen_only: bool = False) -> None:
        """Open the bus and wait for the arm's feedback (joints, gripper, status, driver info). Unless
        ``listen_only``, also ask for the firmware version (``state().firmware_version``) and read the
        firmware's joint limits (0x472 -> 0x473), which narrow ``limits``."""
        first = (*ID_JOINT_FEEDBACK, ID_GRIPPER_FEEDBACK, ID_ARM_STATUS, *ID_LOW_SPEED)
        if self.config.use_velocity_and_torque:
            first += ID_HIGH_SPEED
        self.link.open(first, self.config.connect_timeout_s)
        self.limits = self.config.limits
        self._interlock.close(NOT_ENABLED)
        now = self.clock.monotonic()
        self._session_start = self._resets_waited = self._high_follow_since = self._mode_mark = now
        if listen_only:
            return
        try:
            self.link.send(encode(FirmwareQuery()))
            self._check_collision_protection()
            self._write_joint_caps()
            if self.config.read_firmware_limits:
                self.link.send(*(encode(LimitQuery(m, LIMIT_QUERY_ANGLE_SPEED)) for m in range(1, NUM_JOINTS + 1)))
                self._apply_firmware_limits()
                self._confirm_speed_cap()
            status = self.link.state().status
            # Someone put the arm in CAN mode before us: it may be in high-follow (not in any feedback).
            self._may_be_high_follow = status is not None and status.value.ctrl_mode == CtrlMode.CAN
        except BaseException:
            self.link.close()
            raise

    def _check_collision_protection(self) -> None:
        """Ask for the collision-protection levels (0x477 02 -> 0x47B); level 0 (off) warns or refuses."""
        asked_at = self.clock.monotonic()
        self.link.send(encode(ParamQuery(PARAM_QUERY_COLLISION)))

        def answered(s: ArmState) -> bool:
            return s.collision_levels is not None and s.collision_levels.timestamp > asked_at

        if not self.link.wait_for(answered, self.config.connect_timeout_s):
            log.warning(
                "PiPER on %s did not report its collision-protection levels (0x47B): whether it stops on a "
                "collision is unknown",
                self.link.where,
            )
            return
        levels = self.link.state().collision_levels.value.levels  # type: ignore[union-attr]
        off = [f"joint_{j}" for j, level in enumerate(levels, start=1) if level == 0]
        if not off:
            return
        message = (
            f"PiPER on {self.link.where} reports collision protection OFF (level 0) on {', '.join(off)}: the arm "
            "will not stop when it hits something; set a level 1..8 (0x47A, vendor tools)"
        )
        if self.config.collision_off == CollisionOff.REFUSE:
            raise CollisionProtectionOffError(message + ", or set collision_off=warn")
        log.error("%s", message)

    def _write_joint_caps(self) -> None:
        """Write the firmware's own joint speed / acceleration caps, if configured (they persist in the arm).

        The speed unit of 0x474 is disputed (0.01 or 0.001 rad/s): it is sent in 0.01 rad/s, so if the
        firmware reads 0.001 the arm moves ten times slower than asked, never faster."""
        cfg = self.config
        if cfg.max_joint_speed_rad_s is not None:
            raw = round(cfg.max_joint_speed_rad_s * 100)
            self.link.send(*(encode(MotorLimitsSet(m, max_speed_raw=raw)) for m in range(1, NUM_JOINTS + 1)))
            log.warning("PiPER on %s: joint speed capped at %.2f rad/s (0x474)", self.link.where, raw / 100)
        if cfg.max_joint_accel_rad_s2 is not None:
            raw = round(cfg.max_joint_accel_rad_s2 * 100)
            self.link.send(encode(JointConfig(NUM_JOINTS + 1, accel_valid=True, max_accel_raw=raw)))
            log.warning("PiPER on %s: joint acceleration capped at %.2f rad/s^2 (0x475)", self.link.where, raw / 100)

    def _confirm_speed_cap(self) -> None:
        """Log an error for every motor whose 0x473 reply does not show the speed cap we wrote."""
        if self.config.max_joint_speed_rad_s is None:
            return
        raw = round(self.config.max_joint_speed_rad_s * 100)
        limits = self.link.state().motor_limits
        ignored = [f"joint_{m}" for m in range(1, NUM_JOINTS + 1) if m in limits and limits[m].max_speed_raw != raw]
        if ignored:
            log.error("PiPER on %s did not take the joint speed cap (0x474) on %s", self.link.where, ", ".join(ignored))

    def _apply_firmware_limits(self) -> None:
        got_all = self.link.wait_for(lambda s: len(s.motor_limits) >= NUM_JOINTS, self.config.connect_timeout_s)
        firmware = self.link.state().motor_limits
        if not got_all:
            missing = [f"joint_{m}" for m in range(1, NUM_JOINTS + 1) if m not in firmware]
            log.warning(
                "PiPER on %s sent no firmware limits (0x473) for %s; using the soft limits only",
                self.link.where,
                ", ".join(missing),
            )
        joints = []
        for j, (lower, upper) in enumerate(self.config.limits.joints_rad, start=1):
            if j not in firmware:
                joints.append((lower, upper))
                continue
            fw_lower, fw_upper = firmware[j].min_angle_rad, firmware[j].max_angle_rad
            narrowed = (max(lower, fw_lower), min(upper, fw_upper))
            if narrowed[0] > narrowed[1]:
                raise PiperError(
                    f"PiPER on {self.link.where}: joint_{j} soft limits [{lower:.4f}, {upper:.4f}] rad and firmware "
                    f"limits [{fw_lower:.4f}, {fw_upper:.4f}] rad do not overlap; fix joint_limits"
                )
            if abs(fw_lower - lower) > LIMIT_MISMATCH_RAD or abs(fw_upper - upper) > LIMIT_MISMATCH_RAD:
                log.warning(
                    "PiPER on %s: joint_%d firmware limits [%.4f, %.4f] rad differ from the soft limits "
                    "[%.4f, %.4f] rad; using [%.4f, %.4f]",
                    self.link.where,
                    j,
                    fw_lower,
                    fw_upper,
                    lower,
                    upper,
                    *narrowed,
                )
            joints.append(narrowed)
        self.limits = JointLimits(tuple(joints), self.config.limits.gripper_m)

    def close(self) -> None:
        """Release the bus without touching the arm (no disconnect policy)."""
        self._interlock.close("the driver is disconnected")
        self.link.close()

    def disconnect(self) -> None:
        """Apply the disconnect policy (best effort), then release the bus. From the call on, other
        threads' commands are refused (only the rest walk moves the arm); an e-stop requested meanwhile
        stops the walk and keeps the rest policy's disable frame off the bus (the arm stays damped)."""
        if not self.link.is_open:
            return
        token = self._interlock.estops
        with self._operation:
            self._disconnecting = True
            try:
                if self.config.disconnect_policy == DisconnectPolicy.REST:
                    if self._walk_to_rest(own=True):
                        if not self._disable(self._abort_on_estop(token, "disconnect's rest policy")):
                            log.warning("PiPER did not confirm it disabled its motors")
                    else:
                        log.warning("PiPER did not reach the rest pose; left enabled and holding (not dropped)")
            except Exception as exc:  # never let cleanup hide the original error or skip closing the bus
                log.warning("PiPER disconnect policy not applied (%s); arm left as it was", exc)
            finally:
                self.close()
                self._disconnecting = False

    # ---------------------------------------------------------------------------------- state
    def state(self) -> ArmState:
        """The latest feedback, without any check."""
        return self.link.state()

    def checked_state(self) -> ArmState:
        """The latest feedback; raises if the watchdog tripped, the bus is off, or the firmware reports
        faults. A joint past its limit is only logged: commands move it back (they are clamped)."""
        self.link.raise_if_unhealthy()
        state = self.link.state()
        faults = state.faults()
        blocking = tuple(f for f in faults if not is_motion_recoverable(f))
        if blocking:
            raise FirmwareFaultError(blocking)
        if faults != self._reported_faults:
            self._reported_faults = faults
            if faults:
                log.warning(
                    "PiPER on %s reports %s; commands are clamped back inside the limits",
                    self.link.where,
                    "; ".join(map(str, faults)),
                )
        return state

    def rearm_watchdog(self) -> None:
        """Resume after a watchdog trip or bus-off, once fresh feedback arrives again (logged).

        Nothing is known of the gap: the arm may have been power-cycled into high-follow (by a linked
        leader), reset, or given another speed by another host while our reader was down. On every
        firmware motion stays latched until ``enable()`` has selected and confirmed our mode (and, on
        firmware that needs one, run the high-follow exit)."""
        self.link.rearm()
        if not self.config.high_follow:
            self._may_be_high_follow = True
        self._interlock.close(
            "feedback stopped for a while and the arm may have been put in high-follow meanwhile (or power-cycled, "
            "reset, or given another speed); call enable()"
        )

    # -------------------------------------------------------------------------------- enable
    def enable(self) -> None:
        """Recover faults per ``recovery``, leave high-follow if needed, enable every joint and the
        gripper, then select and confirm the motion mode; motion is allowed again only once it has.

        A reset's delayed motor-off (~0.73 s) is waited out first: after our reset, after another
        host's reset seen on the bus, and when the arm is in standby with its enable bits still set
        (a reset we did not see, e.g. just before we connected). There is no acknowledgement: the
        handshake resends 0x471 with capped exponential back-off (at least twice) until driver-info
        frames received *after* the first request show every enable bit, then sends 0x151 and waits
        for the status frame to report CAN mode and MOVE J. Refused while the e-stop is engaged
        (``resume`` leaves it); an e-stop requested meanwhile aborts it before its next frame.
        """
        token = self._interlock.estops
        with self._operation:
            self._refuse_if_estopped()
            self._enable(token, resuming=False)

    def _enable(self, token: int, resuming: bool) -> None:
        """Another host's reset (0x150 02) or high-follow request seen at any point of the handshake or the
        mode selection, up to the status that confirms our 0x151, starts it over from the wait for the
        motor-off (at most ``MAX_ENABLE_RESTARTS`` times). One bus delivers frames in order, so a reset the
        firmware acted on before our 0x151 reaches our reader before the status that confirms it."""
        self._interlock.close("enable() is in progress")
        began = self.clock.monotonic()
        if self._foreign_high_follow_since(min(self._mode_mark, self._high_follow_since)):
            self._may_be_high_follow = True
        self._session_start = self._high_follow_since = began
        try:
            self._recover_faults(token)
            restarts = 0
            while True:
                try:
                    self._enable_once(token)
                    break
                except _Restart as exc:
                    restarts += 1
                    if restarts > MAX_ENABLE_RESTARTS:
                        raise EnableTimeoutError(
                            f"PiPER on {self.link.where}: {exc.reason} during enable() {restarts} times; "
                            "find the other host and stop it, then call enable() again"
                        ) from None
                    log.warning("PiPER on %s: %s during enable(); starting over", self.link.where, exc.reason)
        except BaseException as exc:
            self._interlock.close(f"the last enable() failed ({type(exc).__name__}); call enable()")
            raise
        if not self._interlock.open(token, clear_estop=resuming):
            self._abort_on_estop(token, "enable")()  # raises: an e-stop was requested after the last frame

    def _enable_once(self, token: int) -> None:
        """Leave high-follow if needed, wait out any reset's motor-off, run the 0x471 handshake, then
        select and confirm the mode; raises ``_Restart`` on another host's reset or high-follow request."""
        self._leave_high_follow(token)
        self._wait_out_resets(token)
        timeout = self.config.enable_timeout_s
        started = self.clock.monotonic()  # frames are stamped on this clock: only later ones count
        deadline = started + timeout
        backoff = ENABLE_BACKOFF_START_S
        requests = 0
        request = encode(MotorEnable(MOTOR_ALL_JOINTS, True))
        guard = self._enable_guard(token)
        while True:
            try:
                self._send(request, self._gripper_hold(GripperStatusCode.ENABLE), guard=guard)
                requests += 1
            except PiperConnectionError as exc:  # e.g. ENOBUFS: a full TX queue; back off and retry
                log.debug("enable request not sent: %s", exc)
            remaining = deadline - self.clock.monotonic()
            enabled = self._wait(guard, lambda s: not _disabled_parts(s, started), max(min(backoff, remaining), 0))
            if enabled and requests >= 2:
                break
            if self.clock.monotonic() >= deadline:
                raise EnableTimeoutError(self._enable_failure(started, requests))
            backoff = min(backoff * 2, ENABLE_BACKOFF_CAP_S)
        mode_sent_at = self._select_mode(deadline, guard)
        guard()  # a reset acted on before our confirmed 0x151 has been read by now
        self._mode_mark = mode_sent_at

    def _enable_guard(self, token: int) -> Callable[[], None]:
        """The e-stop guard of the handshake and the mode selection, which also raises ``_Restart`` once
        another host's reset or (where it needs the exit) high-follow request arrives."""
        estop = self._abort_on_estop(token, "enable")

        def guard() -> None:
            estop()
            if self._foreign_reset_since(self._resets_waited) is not None:
                raise _Restart("another host reset the arm (0x150 02)")
            if (
                not self.config.high_follow
                and self._foreign_high_follow_since(self._high_follow_since)
                and self._high_follow_exit_needs_reset()
            ):
                self._may_be_high_follow = True
                raise _Restart("another host asked for high-follow (0x151 … AD)")

        return guard

    def _enable_failure(self, started: float, requests: int) -> str:
        """Why the enable handshake timed out, with the remedy."""
        state = self.link.state()
        missing = _disabled_parts(state, started)
        message = (
            f"PiPER on {self.link.where} did not report enabled within {self.config.enable_timeout_s:.1f} s after "
            f"{requests} enable requests (still disabled: {', '.join(missing)}); "
        )
        powered = [f"joint_{j}" for j, on in enumerate(state.joints_enabled, start=1) if on]
        if powered:
            message += f"{', '.join(powered)} stay enabled and holding (disable() switches them off: the arm falls); "
        angles = state.joint_positions_rad or ()
        at_limit = [
            f"joint_{j} at {angle:.4f} rad, limits [{lower:.4f}, {upper:.4f}]"
            for j, (angle, (lower, upper)) in enumerate(zip(angles, self.limits.joints_rad, strict=False), start=1)
            if f"joint_{j}" in missing and not lower - PAST_LIMIT_RAD <= angle <= upper + PAST_LIMIT_RAD
        ]
        if at_limit:
            return message + (
                f"the firmware does not enable a joint past its limit ({'; '.join(at_limit)}): support the arm, "
                "move that joint back inside its limits by hand (its motor is off), then enable again"
            )
        return message + "check the e-stop button and the arm's power"

    def _recover_faults(self, token: int) -> None:
        self.link.raise_if_unhealthy()
        faults = tuple(f for f in self.link.state().faults() if not is_motion_recoverable(f))
        if not faults:
            return
        how = Recovery(self.config.recovery)
        if how == Recovery.NONE:
            raise FirmwareFaultError(faults)
        log.warning("PiPER on %s reports %s; recovering (%s)", self.link.where, "; ".join(map(str, faults)), how)
        if how == Recovery.CLEAR_ERRORS:
            left = self._clear_errors(token)
            if left:
                raise FirmwareFaultError(left)
        else:
            self._reset(token)

    def _high_follow_exit_needs_reset(self) -> bool:
        """Whether this firmware (older than S-V1.8-5, or of unknown version) leaves high-follow only by a reset."""
        release = firmware_release(self.link.state().firmware_version)
        return release is None or release < LEAVES_HIGH_FOLLOW_WITHOUT_RESET

    def _foreign_modes_since(self, since: float) -> list[ModeControl]:
        """Every distinct mode change (0x151) another host (a plugged-in leader) sent after ``since``, oldest first."""
        payloads = self.link.cache.payloads_since(ID_MODE_CONTROL, since)
        found = (decode_command(ID_MODE_CONTROL, data) for data, _ in payloads)
        return [mode for mode in found if isinstance(mode, ModeControl)]

    def _foreign_high_follow_since(self, since: float) -> bool:
        """Whether another host (a plugged-in leader) asked for high-follow (0x151 … AD) after ``since``."""
        return any(mode.mit_mode == MIT_MODE_HIGH_FOLLOW for mode in self._foreign_modes_since(since))

    def _is_our_mode(self, mode: ModeControl) -> bool:
        """Whether ``mode`` moves the arm as ours does (the speed matters only outside high-follow)."""
        ours = self._mode()
        same = (mode.ctrl_mode, mode.move_mode, mode.mit_mode) == (ours.ctrl_mode, ours.move_mode, ours.mit_mode)
        return same and (self.config.high_follow or mode.speed_percent == ours.speed_percent)

    def _foreign_reset_since(self, since: float) -> float | None:
        """When another host last reset the arm (0x150 02), if after ``since`` (a later e-stop hides nothing)."""
        payloads = self.link.cache.payloads_since(ID_EMERGENCY_STOP, since)
        return max((stamp for data, stamp in payloads if data[0] == EStopAction.RESUME), default=None)

    def _leave_high_follow(self, token: int) -> None:
        if self.config.high_follow or not self._may_be_high_follow or not self._high_follow_exit_needs_reset():
            return
        version = self.link.state().firmware_version or "of unknown version"
        if self.config.high_follow_exit == HighFollowExit.REFUSE:
            raise HighFollowError(
                f"PiPER on {self.link.where} may still be in high-follow (0xAD), and firmware {version} (older "
                "than S-V1.8-5) ignores the switch to position mode until a reset; support the arm and run "
                "piper-recover --reset, or set high_follow_exit=reset"
            )
        log.warning(
            "PiPER on %s may be in high-follow (0xAD) and firmware %s ignores leaving it without a reset: "
            "resetting (the motors switch off for a moment)",
            self.link.where,
            version,
        )
        self._reset(token)

    def _wait_out_resets(self, token: int) -> None:
        """Wait until the firmware has switched the motors off after the newest reset: ours, another host's
        seen on the bus, or one inferred from standby with enable bits set. A newer foreign reset during the
        wait restarts the firmware's countdown, and the wait follows it. Motors still on ``reset_settle_s``
        after a reset is a failure (``EnableTimeoutError``); after an inferred one it only shows there was
        none (a reset before we watched switches them off within ~0.73 s)."""
        now = self.clock.monotonic()
        settle = self.config.reset_settle_s
        state = self.link.state()
        target, self._reset_sent_at = self._reset_sent_at, None
        inferred = False
        foreign = self._foreign_reset_since(self._resets_waited)
        if foreign is not None and (target is None or foreign > target):
            if now - foreign < settle:
                log.warning(
                    "PiPER on %s: another host reset the arm %.3f s ago; waiting out its delayed motor-off",
                    self.link.where,
                    now - foreign,
                )
                target = foreign
            else:  # long enough ago that its motor-off has happened
                self._resets_waited = foreign
        if target is None:
            if not _may_be_counting_down(state):
                return
            log.warning(
                "PiPER on %s is in standby with motors enabled, as in the %.2f s after a reset: waiting up to "
                "%.1f s for the motor-off before enabling",
                self.link.where,
                RESET_MOTOR_OFF_S,
                settle,
            )
            target, inferred = now, True
        guard = self._abort_on_estop(token, "the wait for a reset's motor-off")
        while True:
            motor_off = _MotorOff(target)

            def off_or_newer(s: ArmState, at: float = target, off: _MotorOff = motor_off) -> bool:
                return self._foreign_reset_since(at) is not None or off.seen(s)

            self._wait(guard, off_or_newer, max(target + settle - self.clock.monotonic(), 0.0))
            newer = self._foreign_reset_since(target)
            if newer is None:
                break
            log.warning(
                "PiPER on %s: another host reset the arm again %.3f s after the reset being waited out; waiting "
                "out its delayed motor-off",
                self.link.where,
                newer - target,
            )
            target, inferred = newer, False
        state = self.link.state()
        if any(state.joints_enabled) and not motor_off.seen(state):
            if inferred:
                log.info("PiPER on %s: motors still on %.1f s on: no reset was pending", self.link.where, settle)
                return
            raise EnableTimeoutError(
                f"PiPER on {self.link.where}: motors still on {settle:.2f} s after a reset (the firmware switches "
                f"them off ~{RESET_MOTOR_OFF_S:.2f} s after one): not enabling into a motor-off that may still "
                "come; support the arm, then call enable() again"
            )
        self._resets_waited = max(self._resets_waited, target)

    def _select_mode(self, deadline: float, guard: Callable[[], None]) -> float:
        """Send 0x151 until the status confirms it (resent every ``MODE_RESEND_S``: a frame can be lost);
        returns when the first was sent."""
        sent_at = self.clock.monotonic()
        end = max(deadline, self.clock.monotonic() + FEEDBACK_PERIOD_S * 4)

        def confirmed(s: ArmState) -> bool:
            return s.status is not None and s.status.timestamp > sent_at and _mode_problem(s) is None

        while True:
            self._send(self._mode_frame(), guard=guard)
            if self._wait(guard, confirmed, max(min(MODE_RESEND_S, end - self.clock.monotonic()), 0.0)):
                break
            if self.clock.monotonic() >= end:
                problem = _mode_problem(self.link.state()) or "no status frame"
                raise EnableTimeoutError(f"PiPER on {self.link.where} did not confirm the 0x151 mode change: {problem}")
        self._may_be_high_follow = self.config.high_follow
        return sent_at

    def disable(self) -> bool:
        """Disable all motors and the gripper; True once the arm reports every enable bit clear. Motion
        is latched off from the call on (until ``enable``).

        Warning: a raised arm falls when its motors lose power.
        """
        with self._operation:
            return self._disable(None)

    def _disable(self, guard: Callable[[], None] | None) -> bool:
        self._interlock.close("the motors were disabled; call enable()")
        sent_at = self.clock.monotonic()
        frames = (encode(MotorEnable(MOTOR_ALL_JOINTS, False)), self._gripper_hold(GripperStatusCode.DISABLE))
        self.link.send(*frames, guard=guard)
        self.link.send(*frames, guard=guard)
        return self.link.wait_for(lambda s: _all_disabled_since(s, sent_at), self.config.enable_timeout_s)

    # ----------------------------------------------------------------------------- recovery
    def clear_errors(self) -> tuple[Fault, ...]:
        """Clear the joints' (0x475) and the gripper's (0x159) error codes, without touching the motors'
        power; returns the faults still reported afterwards (logged)."""
        token = self._interlock.estops
        with self._operation:
            return self._clear_errors(token)

    def _clear_errors(self, token: int) -> tuple[Fault, ...]:
        log.warning("PiPER on %s: clearing error codes (0x475, 0x159)", self.link.where)
        gripper = self.link.state().gripper
        code = GripperStatusCode.ENABLE_CLEAR_ERROR
        if gripper is None or not gripper.value.enabled:
            code = GripperStatusCode.DISABLE_CLEAR_ERROR
        sent_at = self.clock.monotonic()
        guard = self._abort_on_estop(token, "clear_errors")
        self._send(encode(JointConfig(NUM_JOINTS + 1, clear_error=True)), self._gripper_hold(code), guard=guard)

        self._wait(guard, lambda s: _fault_free_since(s, sent_at), self.config.enable_timeout_s)
        left = _blocking(self.link.state())
        if left:
            log.error("PiPER on %s still reports %s after clearing errors", self.link.where, "; ".join(map(str, left)))
        else:
            log.warning("PiPER on %s: error codes cleared", self.link.where)
        return left

    def reset(self) -> None:
        """Reset the firmware (0x150 02): clears errors and the e-stop, drops to standby, and ~0.73 s
        later switches the motors off. Motion is latched off from the call on; call ``enable`` next (it
        waits the motor-off out). The driver's own e-stop stays engaged (``resume`` leaves it).

        Warning: a raised arm drops a little between the motor-off and the re-enable.
        """
        token = self._interlock.estops
        with self._operation:
            self._reset(token)

    def _reset(self, token: int) -> None:
        log.warning("PiPER on %s: reset (0x150 02)", self.link.where)
        # Latched before the reset frame takes the send lock: no command frame can follow it.
        self._interlock.close(
            f"the arm was reset: its motors switch off ~{RESET_MOTOR_OFF_S:.2f} s later and stay off; call enable()"
        )
        sent_at = self.clock.monotonic()
        guard = self._abort_on_estop(token, "the reset")
        self._send(encode(EmergencyStop(EStopAction.RESUME)), guard=guard)
        self._reset_sent_at = sent_at
        self._may_be_high_follow = False
        self._high_follow_since = sent_at  # the reset left any high-follow requested before it

        # Frames sent after ours but before the firmware acted on it are fresh too and still show the old
        # state: the reset counts once fresh feedback shows its effect (no blocking fault, the e-stop included).
        if not self._wait(guard, lambda s: _fault_free_since(s, sent_at), self.config.enable_timeout_s):
            state = self.link.state()
            if state.status is not None and state.status.value.arm_status == ArmStatusCode.EMERGENCY_STOP:
                raise EnableTimeoutError(f"PiPER on {self.link.where} still reports the e-stop after a reset")
            left = _blocking(state)
            if not left:
                raise EnableTimeoutError(
                    f"PiPER on {self.link.where} sent no fresh status and driver-info feedback after a reset"
                )
            log.error("PiPER on %s still reports %s after a reset", self.link.where, "; ".join(map(str, left)))
            raise FirmwareFaultError(left)

    def recover(self, how: str = Recovery.RESET) -> None:
        """Bring a faulted or e-stopped arm back: ``clear_errors`` or ``reset``, then re-enable, then leave
        the driver's e-stop. An e-stop requested at any moment of it wins: the recovery stops before its
        next frame and raises ``EmergencyStopError``, and the e-stop stays engaged."""
        token = self._interlock.estops
        how = Recovery(how)
        with self._operation:
            if how == Recovery.CLEAR_ERRORS:
                left = self._clear_errors(token)
                if left:
                    raise FirmwareFaultError(left)
            elif how == Recovery.RESET:
                self._reset(token)
            self._enable(token, resuming=True)

    # ------------------------------------------------------------------------------- motion
    def command(self, joints_rad: Sequence[float], gripper_m: float | None = None) -> SentCommand:
        """Clamp to the limits and the step limit, then send 0x155..0x157 (+ 0x159).

        Refused (nothing sent) unless the latest feedback shows every joint (and the gripper, if it
        gets a target) enabled, CAN command mode and MOVE J, no blocking fault, no e-stop request and
        no motion latch (a reset, disable, disconnect, foreign reset or foreign mode change since the
        last confirmed enable); the e-stop and the latch are checked again under the send lock before
        every frame.

        No 0x151 goes with a command: the mode is selected, and confirmed by the status, only by
        ``enable``. A firmware that another host reset meanwhile is in standby, where it ignores joint
        frames; a 0x151 in front of them would put it back into CAN command mode until the delayed
        motor-off.
        """
        steps = self.config.joint_steps()
        return self._command(joints_rad, gripper_m, steps, self.config.max_gripper_step_m)

    def _command(
        self,
        joints_rad: Sequence[float],
        gripper_m: float | None,
        steps: Sequence[float] | None,
        gripper_step: float | None,
        own: bool = False,
    ) -> SentCommand:
        if len(joints_rad) != NUM_JOINTS:
            raise ValueError(f"expected {NUM_JOINTS} joint targets, got {len(joints_rad)}")
        goals = [float(v) for v in joints_rad]
        check_finite(goals, "joint target")
        if gripper_m is not None:
            gripper_m = float(gripper_m)
            check_finite([gripper_m], "gripper target")
        self._refuse_motion(own)
        state = self.checked_state()
        self._refuse_if_not_ready(state, gripper_m is not None)
        present = state.joint_positions_rad
        if present is None or state.gripper is None:  # connect() waited for both: never after connect
            raise ArmNotReadyError(f"PiPER on {self.link.where}: no joint or gripper feedback yet")
        safe = tuple(
            safe_target(goal, now, bounds, None if steps is None else steps[j])
            for j, (goal, now, bounds) in enumerate(zip(goals, present, self.limits.joints_rad, strict=True))
        )
        self._refuse_if_frozen(state, safe)
        frames: list[Frame] = list(encode_joint_targets(safe))
        safe_gripper = None
        if gripper_m is not None:
            safe_gripper = safe_target(gripper_m, state.gripper.value.opening_m, self.limits.gripper_m, gripper_step)
            frames.append(self._gripper_frame(safe_gripper, GripperStatusCode.ENABLE))
        self._send(*frames, guard=lambda: self._refuse_motion(own))
        return SentCommand(safe, safe_gripper)

    def _refuse_if_frozen(self, state: ArmState, targets: Sequence[float]) -> None:
        """Raise ``FeedbackStaleError`` when joint frames keep arriving with the same angles for
        ``FROZEN_AFTER_S`` of frame time while every command asks for a move (the watchdog only sees frames
        stop). A pause in commanding that long starts the count again."""
        present = state.joint_positions_rad
        if present is None or max(abs(t - p) for t, p in zip(targets, present, strict=True)) < FROZEN_MIN_MOVE_RAD:
            self._unchanged = None
            return
        newest = min(s.timestamp for s in state.joints if s is not None)
        kept = self._unchanged
        if kept is None or kept[0] != present or newest - kept[2] > FROZEN_AFTER_S:
            self._unchanged = (present, newest, newest)
            return
        self._unchanged = (present, kept[1], newest)
        unchanged_for = newest - kept[1]
        if unchanged_for > FROZEN_AFTER_S:
            raise FeedbackStaleError(
                f"PiPER on {self.link.where}: joint feedback keeps arriving with the same angles for "
                f"{unchanged_for * 1e3:.0f} ms while the arm is commanded to move: frozen feedback, or an arm that "
                "cannot move; command refused (check the arm and the bus)"
            )

    def _send(self, *frames: Frame, guard: Callable[[], None]) -> None:
        """Send back to back, ``guard`` checked under the send lock before each frame; a guard that stops
        the frames half-way raises its own error, naming what was sent."""
        try:
            self.link.send(*frames, guard=guard)
        except PartialCommandError as exc:
            if isinstance(exc.cause, _Restart):  # the enable starts over: nothing to name
                raise exc.cause from exc
            if isinstance(exc.cause, EmergencyStopError | ArmNotReadyError):
                raise type(exc.cause)(str(exc)) from exc
            raise

    def _wait(self, guard: Callable[[], None], predicate: Callable[[ArmState], bool], timeout_s: float) -> bool:
        """``link.wait_for``, checking ``guard`` at every look (it raises to abort the wait)."""

        def checked(state: ArmState) -> bool:
            guard()
            return predicate(state)

        return self.link.wait_for(checked, timeout_s)

    def _abort_on_estop(self, token: int, what: str) -> Callable[[], None]:
        """A guard that raises ``EmergencyStopError`` once an e-stop was requested after ``token``."""

        def guard() -> None:
            if self._interlock.stopped_since(token):
                raise EmergencyStopError(
                    f"PiPER on {self.link.where}: emergency stop requested during {what}; aborted, the e-stop "
                    "stays engaged; call resume()"
                )

        return guard

    def _refuse_if_estopped(self) -> None:
        if self._interlock.estopped:
            raise EmergencyStopError(f"PiPER on {self.link.where}: emergency stop engaged; call resume() first")

    def _refuse_motion(self, own: bool = False) -> None:
        """Raise unless motion may reach the bus now: no e-stop, no latch, no disconnect under way (but for
        its ``own`` rest walk), and no reset or high-follow request from another host since the enable."""
        self._refuse_if_estopped()
        problem = self._interlock.latch
        if problem is None and self._disconnecting and not own:
            problem = "the driver is disconnecting"
        if problem is None:
            problem = self._foreign_problem()
            if problem is not None:
                self._interlock.close(problem)
        if problem is not None:
            raise ArmNotReadyError(f"PiPER on {self.link.where}: {problem}; command refused")

    def _foreign_problem(self) -> str | None:
        """A reset, or a mode change other than ours, from another host since the enable. Commands send no
        0x151, so nothing else would put our mode back."""
        if self._foreign_reset_since(self._resets_waited) is not None:
            return (
                f"another host reset the arm (0x150 02): its motors switch off ~{RESET_MOTOR_OFF_S:.2f} s later; "
                "call enable()"
            )
        modes = self._foreign_modes_since(self._mode_mark)  # every one of them, not only the latest
        if (
            not self.config.high_follow
            and any(mode.mit_mode == MIT_MODE_HIGH_FOLLOW for mode in modes)
            and self._high_follow_exit_needs_reset()
        ):
            self._may_be_high_follow = True
            return (
                "another host (a plugged-in leader?) put the arm in high-follow (0x151 … AD), which this firmware "
                "leaves only after a reset; call enable()"
            )
        mode = next((m for m in modes if not self._is_our_mode(m)), None)
        if mode is None:
            return None
        theirs, ours = (
            " ".join(f"{byte:02x}" for byte in (m.ctrl_mode, m.move_mode, m.speed_percent, m.mit_mode))
            for m in (mode, self._mode())
        )
        return (
            f"another host (a plugged-in leader?) changed the arm's mode (0x151 {theirs} …, ours is {ours} …); "
            "call enable() to select ours again"
        )

    def _refuse_if_not_ready(self, state: ArmState, with_gripper: bool) -> None:
        problem = _mode_problem(state)
        if problem is not None:
            raise ArmNotReadyError(f"PiPER on {self.link.where}: {problem}; command refused, call enable()")
        disabled = [f"joint_{j}" for j, on in enumerate(state.joints_enabled, start=1) if not on]
        if with_gripper and not state.gripper_enabled:
            disabled.append("gripper")
        if disabled:
            raise ArmNotReadyError(
                f"PiPER on {self.link.where}: feedback shows {', '.join(disabled)} disabled (limp); "
                "command refused, call enable()"
            )

    def move_to_rest(self) -> bool:
        """Walk to the rest pose at ``rest_speed_rad_s``; True once there (within 0.01 rad, 2 mm)."""
        return self._walk_to_rest(own=False)

    def _walk_to_rest(self, own: bool) -> bool:
        cfg = self.config
        step = cfg.rest_speed_rad_s * REST_PERIOD_S
        steps = tuple(min(step, s) for s in (cfg.joint_steps() or (step,) * NUM_JOINTS))
        deadline = self.clock.monotonic() + cfg.rest_timeout_s
        while self.clock.monotonic() < deadline:
            state = self.checked_state()
            joints, gripper = state.joint_positions_rad, state.gripper
            if joints is not None and gripper is not None and _at(joints, gripper.value.opening_m, cfg):
                return True
            self._command(cfg.rest_pose_rad, cfg.rest_gripper_m, steps, cfg.max_gripper_step_m, own)
            self.link.sleep(REST_PERIOD_S)
        return False

    # ------------------------------------------------------------------------------- e-stop
    def emergency_stop(self) -> None:
        """Quick stop (0x150 01): the firmware damps the arm, which sinks slowly. From this call on no
        motion frame leaves the driver (checked under the send lock) until ``resume``, and an enable or
        recovery in flight stops before its next frame. A frame the bus refuses (a full transmit queue)
        is retried for up to ``ESTOP_RETRY_S``."""
        self._interlock.stop()
        frame = encode(EmergencyStop(EStopAction.STOP))
        deadline = self.clock.monotonic() + ESTOP_RETRY_S
        while True:
            try:
                self.link.send(frame)
                return
            except PiperConnectionError as exc:
                if not self.link.is_open or self.clock.monotonic() >= deadline:
                    raise
                log.warning("PiPER on %s: e-stop frame not sent (%s); retrying", self.link.where, exc)
                self.clock.sleep(ESTOP_RETRY_PERIOD_S)

    def resume(self) -> None:
        """Leave the e-stop: reset (0x150 02), wait out the firmware's delayed motor-off, re-enable and
        reselect the motion mode. An e-stop requested while it runs aborts it (``EmergencyStopError``).

        Warning: the reset switches the motors off for a moment, so a raised arm drops a little before
        the re-enable catches it.
        """
        self.recover(Recovery.RESET)

    # ------------------------------------------------------------------------------ frames
    def _mode(self) -> ModeControl:
        mit = MIT_MODE_HIGH_FOLLOW if self.config.high_follow else MIT_MODE_POSITION_VELOCITY
        return ModeControl(CtrlMode.CAN, MoveMode.J, self.config.speed_percent, mit)

    def _mode_frame(self) -> Frame:
        return encode(self._mode())

    def _gripper_frame(self, opening_m: float, code: GripperStatusCode) -> Frame:
        return encode(GripperCommand(opening_m, self.config.gripper_effort_nm, code))

    def _gripper_hold(self, code: GripperStatusCode) -> Frame:
        """A gripper frame with ``code`` that targets where the gripper is now (within its range)."""
        gripper = self.link.state().gripper
        opening = gripper.value.opening_m if gripper is not None else 0.0
        return self._gripper_frame(clamp(opening, *self.limits.gripper_m), code)


class _MotorOff:
    """Whether feedback shows the motor-off of the reset at ``reset_at``: some joint reported enabled in a frame
    stamped ``RESET_ACTED_WITHIN_S`` after it, then every joint reported disabled after that frame. A reset
    restarts the countdown, so a motor-off after a frame sent once the firmware acted on the reset is its own;
    motors not seen on then show nothing (the delay itself must pass: a motor-off just before may be an
    earlier reset's)."""

    def __init__(self, reset_at: float) -> None:
        self.after = reset_at + RESET_ACTED_WITHIN_S
        self.on_at: float | None = None

    def seen(self, state: ArmState) -> bool:
        for info in state.low_speed:
            if info is not None and info.timestamp > max(self.after, self.on_at or 0.0) and info.value.enabled:
                self.on_at = info.timestamp
        return self.on_at is not None and _joints_disabled_since(state, self.on_at)


class _Restart(ArmNotReadyError):
    """Another host reset the arm or asked for high-follow while ``enable`` ran: it starts over."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _blocking(state: ArmState) -> tuple[Fault, ...]:
    return tuple(f for f in state.faults() if not is_motion_recoverable(f))


def _mode_problem(state: ArmState) -> str | None:
    """Why the status frame does not show CAN command mode and MOVE J (None when it does)."""
    if state.status is None:
        return "no status frame yet"
    status = state.status.value
    if status.ctrl_mode == CtrlMode.CAN and status.mode_feed == MoveMode.J:
        return None
    return f"the arm reports control mode {_name(CtrlMode, status.ctrl_mode)} and move mode " + (
        f"{_name(MoveMode, status.mode_feed)}, not CAN command mode and MOVE J"
    )


def _name(kind: type[CtrlMode] | type[MoveMode], value: int) -> str:
    try:
        return kind(value).name
    except ValueError:
        return f"0x{value:02X}"


def _fault_free_since(state: ArmState, since: float) -> bool:
    """Status and driver-info frames all received after ``since``, and no blocking fault (the e-stop is one)."""
    fresh = (state.status, *state.low_speed)
    return all(f is not None and f.timestamp > since for f in fresh) and not _blocking(state)


def _may_be_counting_down(state: ArmState) -> bool:
    """Standby with enable bits set: how the arm looks between a reset and its delayed motor-off."""
    standby = state.status is not None and state.status.value.ctrl_mode == CtrlMode.STANDBY
    return standby and any(state.joints_enabled)


def _joints_disabled_since(state: ArmState, since: float) -> bool:
    return all(f is not None and f.timestamp > since and not f.value.enabled for f in state.low_speed)


def _all_disabled_since(state: ArmState, since: float) -> bool:
    gripper = state.gripper
    fresh_gripper_off = gripper is not None and gripper.timestamp > since and not gripper.value.enabled
    return _joints_disabled_since(state, since) and fresh_gripper_off


def _disabled_parts(state: ArmState, since: float) -> list[str]:
    parts = [
        f"joint_{j}"
        for j, info in enumerate(state.low_speed, start=1)
        if info is None or info.timestamp <= since or not info.value.enabled
    ]
    gripper = state.gripper
    if gripper is None or gripper.timestamp <= since or not gripper.value.enabled:
        parts.append("gripper")
    return parts


def _at(joints: Sequence[float], gripper_m: float, cfg: DriverConfig) -> bool:
    """At the rest pose (within 0.01 rad and 2 mm)."""
    near = all(abs(a - b) <= REST_TOLERANCE_RAD for a, b in zip(joints, cfg.rest_pose_rad, strict=True))
    return near and abs(gripper_m - cfg.rest_gripper_m) <= REST_TOLERANCE_M
