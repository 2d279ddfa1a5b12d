"""Safe driver for one PiPER follower arm: enable handshake, clamped joint/gripper commands that are
refused unless feedback shows every motor enabled in the mode we set, stale-feedback watchdog, e-stop
that no motion frame can overtake, resume / clear-error / reset recovery, faults as exceptions,
disconnect policy.

Its settings are ``settings``; the bus, the feedback cache and its ageing ``link`` and ``state``; other
hosts' resets and mode changes and a reset's motor-off ``bus_watch``; the arm's own settings read and
written on connect (collision levels, caps, flash limits) and the high-follow quirk ``arm_setup``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from .arm_setup import (
    check_collision_protection,
    confirm_speed_cap,
    firmware_limits,
    high_follow_exit_needs_reset,
    write_joint_caps,
)
from .bus_watch import ForeignFrames, MotorOff, joints_disabled_since
from .clock import SYSTEM_CLOCK, Clock
from .codec import (
    ID_ARM_STATUS,
    ID_GRIPPER_FEEDBACK,
    ID_HIGH_SPEED,
    ID_JOINT_FEEDBACK,
    ID_LOW_SPEED,
    LIMIT_QUERY_ANGLE_SPEED,
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
    JointConfig,
    LimitQuery,
    ModeControl,
    MotorEnable,
    MoveMode,
    encode,
    encode_joint_targets,
)
from .errors import (
    ArmNotReadyError,
    EmergencyStopError,
    EnableTimeoutError,
    Fault,
    FeedbackStaleError,
    FirmwareFaultError,
    HighFollowError,
    PartialCommandError,
    PiperConnectionError,
)
from .interlock import NOT_ENABLED, Interlock
from .link import PiperLink
from .safety import JointLimits, check_finite, clamp, safe_target
from .settings import (
    FEEDBACK_PERIOD_S,
    RESET_MOTOR_OFF_S,
    DisconnectPolicy,
    DriverConfig,
    HighFollowExit,
    Recovery,
)
from .state import ArmState

log = logging.getLogger(__name__)

LOW_SPEED_PERIOD_S = 0.025  # 0x261..0x266 (the enable bits) at 40 Hz
ENABLE_BACKOFF_START_S = 0.01
ENABLE_BACKOFF_CAP_S = 0.2
REST_PERIOD_S = 0.02
MODE_RESEND_S = 0.05
REST_TOLERANCE_RAD = 0.01
REST_TOLERANCE_M = 0.002
# An e-stop frame the bus refuses (a full TX queue) is retried every period until this much time passed.
ESTOP_RETRY_S = 0.1
ESTOP_RETRY_PERIOD_S = 0.001
# A joint that stays disabled further than this past its limit is named as why (the firmware does not
# enable a joint past its limit); the rest pose sits exactly on J2's and J3's limits, which is fine.
PAST_LIMIT_RAD = math.radians(0.01)
# Joint feedback that keeps arriving with the very same angles and motor frames (0x25x: speed, current,
# position) for this long while every command asks for a move of at least FROZEN_MIN_MOVE_RAD counts as
# frozen (a stuck sender, a replayed capture). An arm held by contact keeps still too, but its motors' currents
# vary (sensor noise, the push against the error), so its 0x25x frames do not repeat.
FROZEN_AFTER_S = 0.25
FROZEN_MIN_MOVE_RAD = 0.01
# An enable() that another host's reset or high-follow request interrupts starts over at most this often.
MAX_ENABLE_RESTARTS = 5


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
        self._foreign = ForeignFrames(self.link)
        # One lifecycle operation (enable, reset, recover, disable, disconnect) at a time; e-stops never wait.
        self._operation = threading.RLock()
        self._disconnecting = False  # only the disconnect policy's own rest walk may command meanwhile
        self._reset_sent_at: float | None = None
        self._may_be_high_follow = False
        # All on the monotonic clock the link stamps frames on. Another host's resets stamped up to this were
        # waited out; a newer one restarts an enable in flight, or latches motion after it.
        self._resets_waited = 0.0
        # Another host's high-follow requests (0x151 … AD) after this need the exit (set when an enable begins,
        # and by our reset).
        self._high_follow_since = 0.0
        # Another host's mode changes (0x151) after our confirmed 0x151 latch motion unless they are ours.
        self._mode_mark = 0.0
        self._reported_faults: tuple[Fault, ...] = ()
        # While commanding moves: the feedback last seen (joint angles, 0x25x frames), the stamp it was first
        # seen with, and the stamp of the last command that asked for a move.
        self._unchanged: tuple[tuple[object, ...], float, float] | None = None

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
        self._resets_waited = self._high_follow_since = self._mode_mark = now
        if listen_only:
            return
        try:
            self.link.send(encode(FirmwareQuery()))
            check_collision_protection(self.link, self.config)
            write_joint_caps(self.link, self.config)
            if self.config.read_firmware_limits:
                self.link.send(*(encode(LimitQuery(m, LIMIT_QUERY_ANGLE_SPEED)) for m in range(1, NUM_JOINTS + 1)))
                self.limits = firmware_limits(self.link, self.config)
                confirm_speed_cap(self.link, self.config)
            status = self.link.state().status
            # Someone put the arm in CAN mode before us: it may be in high-follow (not in any feedback).
            self._may_be_high_follow = status is not None and status.value.ctrl_mode == CtrlMode.CAN
        except BaseException:
            self.link.close()
            raise

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
        if self._foreign.high_follow_since(min(self._mode_mark, self._high_follow_since)):
            self._may_be_high_follow = True
        self._high_follow_since = began
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
        before = self.link.state()
        was_off = [j for j, on in enumerate(before.joints_enabled, start=1) if not on]
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
                raise EnableTimeoutError(self._enable_failure(started, requests, was_off, before.gripper_enabled))
            backoff = min(backoff * 2, ENABLE_BACKOFF_CAP_S)
        mode_sent_at = self._select_mode(deadline, guard)
        # A reset acted on before our confirmed 0x151 was read before the status that confirmed it; one that
        # came after is read now, unless it lands between this and the latch opening (the reader's latency).
        self.link.caught_up(self.config.feedback_timeout_s)
        guard()
        self._mode_mark = mode_sent_at

    def _enable_guard(self, token: int) -> Callable[[], None]:
        """The e-stop guard of the handshake and the mode selection, which also raises ``_Restart`` once
        another host's reset or (where it needs the exit) high-follow request arrives."""
        estop = self._abort_on_estop(token, "enable")

        def guard() -> None:
            estop()
            if self._foreign.reset_since(self._resets_waited) is not None:
                raise _Restart("another host reset the arm (0x150 02)")
            if (
                not self.config.high_follow
                and self._foreign.high_follow_since(self._high_follow_since)
                and high_follow_exit_needs_reset(self.link.state())
            ):
                self._may_be_high_follow = True
                raise _Restart("another host asked for high-follow (0x151 … AD)")

        return guard

    def _enable_failure(self, started: float, requests: int, was_off: list[int], gripper_was_on: bool) -> str:
        """Switch the parts this handshake enabled back off (they were off before it: nothing they hold
        was held before), then say why it timed out, with the remedy."""
        state = self.link.state()
        missing = _disabled_parts(state, started)
        message = (
            f"PiPER on {self.link.where} did not report enabled within {self.config.enable_timeout_s:.1f} s after "
            f"{requests} enable requests (still disabled: {', '.join(missing)}); "
        )
        back_off = [j for j in was_off if state.joints_enabled[j - 1]]
        frames = [encode(MotorEnable(j, False)) for j in back_off]
        if not gripper_was_on and state.gripper_enabled:
            frames.append(self._gripper_hold(GripperStatusCode.DISABLE))
        if frames:
            self.link.send(*frames)
            parts = [f"joint_{j}" for j in back_off] + (["gripper"] if len(frames) > len(back_off) else [])
            message += f"switched {', '.join(parts)} off again, as they were before; "
        held = [f"joint_{j}" for j, on in enumerate(state.joints_enabled, start=1) if on and j not in back_off]
        if held:
            message += f"{', '.join(held)} stay enabled and holding, as they were (disable() drops the arm); "
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

    def _is_our_mode(self, mode: ModeControl) -> bool:
        """Whether ``mode`` moves the arm as ours does (the speed matters only outside high-follow)."""
        ours = self._mode()
        same = (mode.ctrl_mode, mode.move_mode, mode.mit_mode) == (ours.ctrl_mode, ours.move_mode, ours.mit_mode)
        return same and (self.config.high_follow or mode.speed_percent == ours.speed_percent)

    def _leave_high_follow(self, token: int) -> None:
        if (
            self.config.high_follow
            or not self._may_be_high_follow
            or not high_follow_exit_needs_reset(self.link.state())
        ):
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
        foreign = self._foreign.reset_since(self._resets_waited)
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
            motor_off = MotorOff(target)

            def off_or_newer(s: ArmState, at: float = target, off: MotorOff = motor_off) -> bool:
                return self._foreign.reset_since(at) is not None or off.seen(s)

            self._wait(guard, off_or_newer, max(target + settle - self.clock.monotonic(), 0.0))
            newer = self._foreign.reset_since(target)
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
            # Another host's reset that reached the bus before this 0x151 is read first, so the guard sees it;
            # one that lands after this is the residual (the firmware acts on our 0x151 in its countdown).
            self.link.caught_up(self.config.feedback_timeout_s)
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
        """Raise ``FeedbackStaleError`` when joint frames keep arriving with the same angles, and the 0x25x
        motor frames (where heard) with the same values, for ``FROZEN_AFTER_S`` of frame time while every
        command asks for a move (the watchdog only sees frames stop). An arm held still by contact passes: its
        motor currents change. A pause in commanding that long starts the count again."""
        present = state.joint_positions_rad
        if present is None or max(abs(t - p) for t, p in zip(targets, present, strict=True)) < FROZEN_MIN_MOVE_RAD:
            self._unchanged = None
            return
        seen = (*present, *(None if s is None else s.value for s in state.high_speed))
        newest = min(s.timestamp for s in state.joints if s is not None)
        kept = self._unchanged
        if kept is None or kept[0] != seen or newest - kept[2] > FROZEN_AFTER_S:
            self._unchanged = (seen, newest, newest)
            return
        self._unchanged = (seen, kept[1], newest)
        unchanged_for = newest - kept[1]
        if unchanged_for > FROZEN_AFTER_S:
            what = "angles and motor currents" if any(s is not None for s in state.high_speed) else "angles"
            raise FeedbackStaleError(
                f"PiPER on {self.link.where}: joint feedback keeps arriving with the same {what} for "
                f"{unchanged_for * 1e3:.0f} ms while the arm is commanded to move: frozen feedback; command refused "
                "(check the arm and the bus)"
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
        if self._foreign.reset_since(self._resets_waited) is not None:
            return (
                f"another host reset the arm (0x150 02): its motors switch off ~{RESET_MOTOR_OFF_S:.2f} s later; "
                "call enable()"
            )
        modes = self._foreign.modes_since(self._mode_mark)  # every one of them, not only the latest
        if (
            not self.config.high_follow
            and any(mode.mit_mode == MIT_MODE_HIGH_FOLLOW for mode in modes)
            and high_follow_exit_needs_reset(self.link.state())
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


def _all_disabled_since(state: ArmState, since: float) -> bool:
    gripper = state.gripper
    fresh_gripper_off = gripper is not None and gripper.timestamp > since and not gripper.value.enabled
    return joints_disabled_since(state, since) and fresh_gripper_off


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
