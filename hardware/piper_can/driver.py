"""Safe driver for one PiPER follower arm: enable handshake, clamped joint/gripper commands,
stale-feedback watchdog, e-stop / resume, firmware faults as exceptions, disconnect policy.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

from .codec import (
    ID_ARM_STATUS,
    ID_GRIPPER_FEEDBACK,
    ID_JOINT_FEEDBACK,
    ID_LOW_SPEED,
    MIT_MODE_HIGH_FOLLOW,
    MIT_MODE_POSITION_VELOCITY,
    MOTOR_ALL_JOINTS,
    NUM_JOINTS,
    ArmStatusCode,
    CtrlMode,
    EmergencyStop,
    EStopAction,
    FirmwareQuery,
    Frame,
    GripperCommand,
    GripperStatusCode,
    ModeControl,
    MotorEnable,
    MoveMode,
    encode,
    encode_joint_targets,
)
from .errors import EmergencyStopError, EnableTimeoutError, FirmwareFaultError, PiperConnectionError
from .link import PiperLink
from .safety import SDK_SOFT_LIMITS, JointLimits, check_finite, clamp, safe_target
from .state import ArmState

log = logging.getLogger(__name__)

FEEDBACK_PERIOD_S = 0.005  # 0x2A1..0x2A8 at 200 Hz
ENABLE_BACKOFF_START_S = 0.01
ENABLE_BACKOFF_CAP_S = 0.2
REST_PERIOD_S = 0.02
REST_TOLERANCE_RAD = 0.01
REST_TOLERANCE_M = 0.002


class DisconnectPolicy(StrEnum):
    """What ``disconnect`` does to an enabled arm."""

    HOLD = "hold"  # stay enabled, holding the last target (the arm does not fall)
    REST = "rest"  # move slowly to the rest pose, then disable; if it cannot get there, hold


@dataclass(frozen=True)
class DriverConfig:
    """Bus, motion and safety settings of a ``PiperDriver`` (all safety features on by default)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    bus_options: Mapping[str, object] = field(default_factory=dict)
    limits: JointLimits = SDK_SOFT_LIMITS
    # LeRobot ``max_relative_target`` semantics: per command, each target stays within this of the
    # measured position. One value or one per joint; None turns the step limit off.
    max_step_rad: float | Sequence[float] | None = 0.2
    max_gripper_step_m: float | None = 0.02
    feedback_timeout_s: float = 3 * FEEDBACK_PERIOD_S
    connect_timeout_s: float = 1.0
    enable_timeout_s: float = 2.0
    speed_percent: int = 50
    high_follow: bool = False
    gripper_effort_nm: float = 1.0
    disconnect_policy: DisconnectPolicy = DisconnectPolicy.HOLD
    rest_pose_rad: tuple[float, ...] = (0.0,) * NUM_JOINTS
    rest_gripper_m: float = 0.0
    rest_speed_rad_s: float = 0.5
    rest_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if not 0 <= self.speed_percent <= 100:
            raise ValueError(f"speed_percent must be 0..100, got {self.speed_percent}")
        if len(self.rest_pose_rad) != NUM_JOINTS:
            raise ValueError(f"rest_pose_rad needs {NUM_JOINTS} angles, got {len(self.rest_pose_rad)}")
        steps = self.joint_steps()
        if steps is not None and any(s <= 0 or not math.isfinite(s) for s in steps):
            raise ValueError(f"max_step_rad must be positive and finite, got {self.max_step_rad}")
        DisconnectPolicy(self.disconnect_policy)

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


class PiperDriver:
    """Drives one PiPER follower over python-can; every method is safe to call from any thread."""

    def __init__(self, config: DriverConfig | None = None) -> None:
        self.config = config or DriverConfig()
        self.link = PiperLink(
            self.config.interface,
            self.config.channel,
            self.config.bitrate,
            self.config.bus_options,
            watch_ids=ID_JOINT_FEEDBACK,
            stale_timeout_s=self.config.feedback_timeout_s,
        )
        self._estopped = threading.Event()

    # ------------------------------------------------------------------------------ lifecycle
    @property
    def is_connected(self) -> bool:
        return self.link.is_open

    @property
    def estopped(self) -> bool:
        return self._estopped.is_set()

    def connect(self, listen_only: bool = False) -> None:
        """Open the bus, wait for the arm's feedback (joints, gripper, status, driver info) and, unless
        ``listen_only``, ask for the firmware version (it appears in ``state().firmware_version``)."""
        first = (*ID_JOINT_FEEDBACK, ID_GRIPPER_FEEDBACK, ID_ARM_STATUS, *ID_LOW_SPEED)
        self.link.open(first, self.config.connect_timeout_s)
        if not listen_only:
            self.link.send(encode(FirmwareQuery()))

    def close(self) -> None:
        """Release the bus without touching the arm (no disconnect policy)."""
        self.link.close()

    def disconnect(self) -> None:
        """Apply the disconnect policy (best effort), then release the bus."""
        if not self.link.is_open:
            return
        try:
            if self.config.disconnect_policy == DisconnectPolicy.REST:
                if self.move_to_rest():
                    if not self.disable():
                        log.warning("PiPER did not confirm it disabled its motors")
                else:
                    log.warning("PiPER did not reach the rest pose; left enabled and holding (not dropped)")
        except Exception as exc:  # never let cleanup hide the original error or skip closing the bus
            log.warning("PiPER disconnect policy not applied (%s); arm left as it was", exc)
        finally:
            self.link.close()

    # ---------------------------------------------------------------------------------- state
    def state(self) -> ArmState:
        """The latest feedback, without any check."""
        return self.link.state()

    def checked_state(self) -> ArmState:
        """The latest feedback; raises if the watchdog tripped or the firmware reports faults."""
        self.link.raise_if_stale()
        state = self.link.state()
        faults = state.faults()
        if faults:
            raise FirmwareFaultError(faults)
        return state

    # -------------------------------------------------------------------------------- enable
    def enable(self) -> None:
        """Enable all joints and the gripper, then select CAN command mode.

        There is no acknowledgement: the handshake resends 0x471 with capped exponential back-off
        (at least twice) until driver-info frames received *after* the first request show every
        enable bit, then sends 0x151 and waits for the status frame to report CAN mode.
        """
        timeout = self.config.enable_timeout_s
        started = time.time()  # frames are stamped on this clock: only later ones count
        deadline = time.monotonic() + timeout
        backoff = ENABLE_BACKOFF_START_S
        requests = 0
        while True:
            try:
                self.link.send(encode(MotorEnable(MOTOR_ALL_JOINTS, True)), self._gripper_hold(True))
                requests += 1
            except PiperConnectionError as exc:  # e.g. ENOBUFS: a full TX queue; back off and retry
                log.debug("enable request not sent: %s", exc)
            remaining = deadline - time.monotonic()
            enabled = self.link.wait_for(lambda s: _fresh_enabled(s, started), max(min(backoff, remaining), 0))
            if enabled and requests >= 2:
                break
            if time.monotonic() >= deadline:
                missing = _disabled_parts(self.link.state(), started)
                raise EnableTimeoutError(
                    f"PiPER on {self.link.where} did not report enabled within {timeout:.1f} s after "
                    f"{requests} enable requests (still disabled: {', '.join(missing)}); "
                    "check the e-stop button and the arm's power"
                )
            backoff = min(backoff * 2, ENABLE_BACKOFF_CAP_S)
        self._select_mode(deadline)

    def _select_mode(self, deadline: float) -> None:
        sent_at = time.time()
        self.link.send(self._mode_frame())

        def in_can_mode(s: ArmState) -> bool:
            return s.status is not None and s.status.timestamp > sent_at and s.status.value.ctrl_mode == CtrlMode.CAN

        if not self.link.wait_for(in_can_mode, max(deadline - time.monotonic(), FEEDBACK_PERIOD_S * 4)):
            raise EnableTimeoutError(
                f"PiPER on {self.link.where} did not enter CAN command mode (0x151) after enabling"
            )

    def disable(self) -> bool:
        """Disable all motors and the gripper; True once the arm reports every enable bit clear.

        Warning: a raised arm falls when its motors lose power.
        """
        sent_at = time.time()
        frames = (encode(MotorEnable(MOTOR_ALL_JOINTS, False)), self._gripper_hold(False))
        self.link.send(*frames)
        self.link.send(*frames)

        def all_disabled(s: ArmState) -> bool:
            fresh = [*s.low_speed, s.gripper]
            return all(f is not None and f.timestamp > sent_at and not f.value.enabled for f in fresh)

        return self.link.wait_for(all_disabled, self.config.enable_timeout_s)

    # ------------------------------------------------------------------------------- motion
    def command(self, joints_rad: Sequence[float], gripper_m: float | None = None) -> SentCommand:
        """Clamp to the soft limits and the step limit, then send 0x151 + 0x155..0x157 (+ 0x159)."""
        steps = self.config.joint_steps()
        return self._command(joints_rad, gripper_m, steps, self.config.max_gripper_step_m)

    def _command(
        self,
        joints_rad: Sequence[float],
        gripper_m: float | None,
        steps: Sequence[float] | None,
        gripper_step: float | None,
    ) -> SentCommand:
        if len(joints_rad) != NUM_JOINTS:
            raise ValueError(f"expected {NUM_JOINTS} joint targets, got {len(joints_rad)}")
        goals = [float(v) for v in joints_rad]
        check_finite(goals, "joint target")
        if gripper_m is not None:
            gripper_m = float(gripper_m)
            check_finite([gripper_m], "gripper target")
        if self.estopped:
            raise EmergencyStopError(f"PiPER on {self.link.where}: emergency stop engaged; call resume() first")
        state = self.checked_state()
        present = state.joint_positions_rad
        assert present is not None and state.gripper is not None  # connect() waited for both
        limits = self.config.limits
        safe = tuple(
            safe_target(goal, now, bounds, None if steps is None else steps[j])
            for j, (goal, now, bounds) in enumerate(zip(goals, present, limits.joints_rad, strict=True))
        )
        frames: list[Frame] = [self._mode_frame(), *encode_joint_targets(safe)]
        safe_gripper = None
        if gripper_m is not None:
            safe_gripper = safe_target(gripper_m, state.gripper.value.opening_m, limits.gripper_m, gripper_step)
            frames.append(self._gripper_frame(safe_gripper, GripperStatusCode.ENABLE))
        self.link.send(*frames)
        return SentCommand(safe, safe_gripper)

    def move_to_rest(self) -> bool:
        """Walk to the rest pose at ``rest_speed_rad_s``; True once there (within 0.01 rad, 2 mm)."""
        cfg = self.config
        step = cfg.rest_speed_rad_s * REST_PERIOD_S
        steps = tuple(min(step, s) for s in (cfg.joint_steps() or (step,) * NUM_JOINTS))
        deadline = time.monotonic() + cfg.rest_timeout_s
        while time.monotonic() < deadline:
            state = self.checked_state()
            joints = state.joint_positions_rad
            assert joints is not None and state.gripper is not None
            if all(abs(a - b) <= REST_TOLERANCE_RAD for a, b in zip(joints, cfg.rest_pose_rad, strict=True)) and (
                abs(state.gripper.value.opening_m - cfg.rest_gripper_m) <= REST_TOLERANCE_M
            ):
                return True
            self._command(cfg.rest_pose_rad, cfg.rest_gripper_m, steps, cfg.max_gripper_step_m)
            time.sleep(REST_PERIOD_S)
        return False

    # ------------------------------------------------------------------------------- e-stop
    def emergency_stop(self) -> None:
        """Quick stop (0x150 01): the firmware damps the arm, which sinks slowly. Motion is refused
        until ``resume``."""
        self._estopped.set()
        self.link.send(encode(EmergencyStop(EStopAction.STOP)))

    def resume(self) -> None:
        """Leave the e-stop: reset (0x150 02), re-enable and reselect CAN mode.

        Warning: the firmware's reset cuts motor power for a moment, so a raised arm drops a little
        before the re-enable catches it.
        """
        sent_at = time.time()
        self.link.send(encode(EmergencyStop(EStopAction.RESUME)))

        def reset_seen(s: ArmState) -> bool:
            return (
                s.status is not None
                and s.status.timestamp > sent_at
                and s.status.value.arm_status != ArmStatusCode.EMERGENCY_STOP
            )

        if not self.link.wait_for(reset_seen, self.config.enable_timeout_s):
            raise EnableTimeoutError(f"PiPER on {self.link.where} still reports the e-stop after a reset")
        self._estopped.clear()
        self.enable()

    # ------------------------------------------------------------------------------ frames
    def _mode_frame(self) -> Frame:
        mit = MIT_MODE_HIGH_FOLLOW if self.config.high_follow else MIT_MODE_POSITION_VELOCITY
        return encode(ModeControl(CtrlMode.CAN, MoveMode.J, self.config.speed_percent, mit))

    def _gripper_frame(self, opening_m: float, code: GripperStatusCode) -> Frame:
        return encode(GripperCommand(opening_m, self.config.gripper_effort_nm, code))

    def _gripper_hold(self, enable: bool) -> Frame:
        """A gripper frame that (dis)enables it and targets where it is now (within its range)."""
        gripper = self.link.state().gripper
        opening = gripper.value.opening_m if gripper is not None else 0.0
        opening = clamp(opening, *self.config.limits.gripper_m)
        return self._gripper_frame(opening, GripperStatusCode.ENABLE if enable else GripperStatusCode.DISABLE)


def _fresh_enabled(state: ArmState, since: float) -> bool:
    """Every joint's and the gripper's enable bit set, in frames received after ``since``."""
    return not _disabled_parts(state, since)


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
