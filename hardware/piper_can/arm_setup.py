"""What the driver reads and writes of the arm's own settings on connect, and the firmware quirk it works
around: collision-protection levels (0x477 -> 0x47B), the joint speed and acceleration caps (0x474, 0x475),
the flash joint limits (0x473), and which firmware leaves high-follow only after a reset.
"""

from __future__ import annotations

import logging
import math

from .codec import (
    NUM_JOINTS,
    PARAM_QUERY_COLLISION,
    JointConfig,
    MotorLimitsSet,
    ParamQuery,
    encode,
    firmware_release,
)
from .errors import CollisionProtectionOffError, PiperError
from .link import PiperLink
from .safety import JointLimits
from .settings import CollisionOff, DriverConfig
from .state import ArmState

log = logging.getLogger(__name__)

# Firmware from this release on leaves high-follow on a plain 0x151; older firmware needs a reset.
LEAVES_HIGH_FOLLOW_WITHOUT_RESET = (1, 8, 5)
# A firmware limit counts as different from a soft limit beyond half its 0.1° resolution.
LIMIT_MISMATCH_RAD = math.radians(0.05)


def high_follow_exit_needs_reset(state: ArmState) -> bool:
    """Whether this firmware (older than S-V1.8-5, or of unknown version) leaves high-follow only by a reset."""
    release = firmware_release(state.firmware_version)
    return release is None or release < LEAVES_HIGH_FOLLOW_WITHOUT_RESET


def check_collision_protection(link: PiperLink, config: DriverConfig) -> None:
    """Ask for the collision-protection levels (0x477 02 -> 0x47B); level 0 (off) warns or refuses."""
    asked_at = link.clock.monotonic()
    link.send(encode(ParamQuery(PARAM_QUERY_COLLISION)))

    def answered(s: ArmState) -> bool:
        return s.collision_levels is not None and s.collision_levels.timestamp > asked_at

    if not link.wait_for(answered, config.connect_timeout_s):
        log.warning(
            "PiPER on %s did not report its collision-protection levels (0x47B): whether it stops on a "
            "collision is unknown",
            link.where,
        )
        return
    levels = link.state().collision_levels.value.levels  # type: ignore[union-attr]
    off = [f"joint_{j}" for j, level in enumerate(levels, start=1) if level == 0]
    if not off:
        return
    message = (
        f"PiPER on {link.where} reports collision protection OFF (level 0) on {', '.join(off)}: the arm "
        "will not stop when it hits something; set a level 1..8 (0x47A, vendor tools)"
    )
    if config.collision_off == CollisionOff.REFUSE:
        raise CollisionProtectionOffError(message + ", or set collision_off=warn")
    log.error("%s", message)


def write_joint_caps(link: PiperLink, config: DriverConfig) -> None:
    """Write the firmware's own joint speed / acceleration caps, if configured (they persist in the arm).

    The speed unit of 0x474 is disputed (0.01 or 0.001 rad/s): it is sent in 0.01 rad/s, so if the
    firmware reads 0.001 the arm moves ten times slower than asked, never faster."""
    cfg = config
    if cfg.max_joint_speed_rad_s is not None:
        raw = round(cfg.max_joint_speed_rad_s * 100)
        link.send(*(encode(MotorLimitsSet(m, max_speed_raw=raw)) for m in range(1, NUM_JOINTS + 1)))
        log.warning("PiPER on %s: joint speed capped at %.2f rad/s (0x474)", link.where, raw / 100)
    if cfg.max_joint_accel_rad_s2 is not None:
        raw = round(cfg.max_joint_accel_rad_s2 * 100)
        link.send(encode(JointConfig(NUM_JOINTS + 1, accel_valid=True, max_accel_raw=raw)))
        log.warning("PiPER on %s: joint acceleration capped at %.2f rad/s^2 (0x475)", link.where, raw / 100)


def confirm_speed_cap(link: PiperLink, config: DriverConfig) -> None:
    """Log an error for every motor whose 0x473 reply does not show the speed cap we wrote."""
    if config.max_joint_speed_rad_s is None:
        return
    raw = round(config.max_joint_speed_rad_s * 100)
    limits = link.state().motor_limits
    ignored = [f"joint_{m}" for m in range(1, NUM_JOINTS + 1) if m in limits and limits[m].max_speed_raw != raw]
    if ignored:
        log.error("PiPER on %s did not take the joint speed cap (0x474) on %s", link.where, ", ".join(ignored))


def firmware_limits(link: PiperLink, config: DriverConfig) -> JointLimits:
    """Read the firmware's joint limits (0x473 replies, asked for by the caller): the soft limits narrowed to
    them (warned about where they differ), or the soft limits where a reply is missing."""
    got_all = link.wait_for(lambda s: len(s.motor_limits) >= NUM_JOINTS, config.connect_timeout_s)
    firmware = link.state().motor_limits
    if not got_all:
        missing = [f"joint_{m}" for m in range(1, NUM_JOINTS + 1) if m not in firmware]
        log.warning(
            "PiPER on %s sent no firmware limits (0x473) for %s; using the soft limits only",
            link.where,
            ", ".join(missing),
        )
    joints = []
    for j, (lower, upper) in enumerate(config.limits.joints_rad, start=1):
        if j not in firmware:
            joints.append((lower, upper))
            continue
        fw_lower, fw_upper = firmware[j].min_angle_rad, firmware[j].max_angle_rad
        narrowed = (max(lower, fw_lower), min(upper, fw_upper))
        if narrowed[0] > narrowed[1]:
            raise PiperError(
                f"PiPER on {link.where}: joint_{j} soft limits [{lower:.4f}, {upper:.4f}] rad and firmware "
                f"limits [{fw_lower:.4f}, {fw_upper:.4f}] rad do not overlap; fix joint_limits"
            )
        if abs(fw_lower - lower) > LIMIT_MISMATCH_RAD or abs(fw_upper - upper) > LIMIT_MISMATCH_RAD:
            log.warning(
                "PiPER on %s: joint_%d firmware limits [%.4f, %.4f] rad differ from the soft limits "
                "[%.4f, %.4f] rad; using [%.4f, %.4f]",
                link.where,
                j,
                fw_lower,
                fw_upper,
                lower,
                upper,
                *narrowed,
            )
        joints.append(narrowed)
    return JointLimits(tuple(joints), config.limits.gripper_m)
