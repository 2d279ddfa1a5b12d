"""LeRobot robot ``piper_follower``: a PiPER arm through the safe ``piper_can`` driver."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cached_property
from pathlib import Path

from lerobot.cameras import make_cameras_from_configs
from lerobot.robots.robot import Robot
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected
from piper_can.clock import SYSTEM_CLOCK, Clock
from piper_can.codec import MIT_MODE_HIGH_FOLLOW
from piper_can.driver import PiperDriver
from piper_can.errors import ArmNotReadyError
from piper_can.state import ArmState

from .config_piper_follower import PiperFollowerConfig
from .features import TORQUE_KEYS, VELOCITY_KEYS, from_action, motor_features, to_action
from .motion_metadata import MotionMode, deployment_source, read_motion_mode

log = logging.getLogger(__name__)

# Lists that collect every PiperFollower made while ``followers_made()`` blocks run (piper-record).
_collectors: list[list[PiperFollower]] = []


@contextmanager
def followers_made() -> Iterator[list[PiperFollower]]:
    """Every ``PiperFollower`` constructed in this process while the block runs."""
    made: list[PiperFollower] = []
    _collectors.append(made)
    try:
        yield made
    finally:
        _collectors.remove(made)


class PiperFollower(Robot):
    """Observations and actions are ``joint_1.pos … joint_6.pos`` (rad) and ``gripper.pos`` (m), plus
    one ``(h, w, 3)`` image per camera, and with ``use_velocity_and_torque`` also ``joint_N.vel``
    (rad/s) and ``joint_N.torque`` (N·m). Targets are clamped to the limits and to
    ``max_relative_target`` before they reach the bus; ``send_action`` returns what was sent."""

    config_class = PiperFollowerConfig
    name = "piper_follower"
    # How to bring the arm back after a fault, for the one line a caller prints (lerobot-cso's robot rollouts).
    recovery_hint = "PiPER: release the e-stop if pressed, then piper-recover, or rerun with --robot.recovery=reset"

    def __init__(self, config: PiperFollowerConfig, clock: Clock = SYSTEM_CLOCK):
        """``clock``: the system's (LeRobot's CLIs), or a ``SimulatedClock`` in tests."""
        super().__init__(config)
        self.config = config
        self.motion = self._deployment_motion()
        self.driver = PiperDriver(config.driver_config(self.motion), clock)
        self.cameras = make_cameras_from_configs(config.cameras)
        self._modes_seen: dict[MotionMode, None] = {}  # in the order first seen
        for made in _collectors:
            made.append(self)

    def _deployment_motion(self) -> MotionMode:
        """Our motion mode: given, else recorded with what is deployed (logged), else position at 50 %."""
        config = self.config
        if config.hardware_linked_leader:  # never sends: the leader's mode applies
            return config.resolve_motion()
        source = Path(config.motion_mode_from) if config.motion_mode_from else deployment_source()
        recorded = None if source is None else read_motion_mode(source)
        if config.motion_mode_from is not None and recorded is None:
            raise ValueError(f"no PiPER motion mode recorded for {config.motion_mode_from} (meta/info.json)")
        motion = config.resolve_motion(recorded)
        if recorded is None:
            if config.motion_mode is None and source is not None and source.exists():
                log.warning(
                    "%s: no PiPER motion mode recorded for %s (record with piper-record); moving in %s",
                    self,
                    source,
                    motion,
                )
        elif config.motion_mode is None:
            log.info("%s: moving in the motion mode recorded for %s: %s", self, source, motion)
        elif motion.motion_mode != recorded.motion_mode:
            log.warning("%s: moving in %s, not in the recorded %s (--robot.motion_mode)", self, motion, recorded)
        return motion

    @cached_property
    def observation_features(self) -> dict[str, type | tuple]:
        cameras = {name: (cfg.height, cfg.width, 3) for name, cfg in self.config.cameras.items()}
        extra = dict.fromkeys((*VELOCITY_KEYS, *TORQUE_KEYS), float) if self.config.use_velocity_and_torque else {}
        return {**motor_features(), **extra, **cameras}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return motor_features()

    @property
    def is_connected(self) -> bool:
        return self.driver.is_connected

    @property
    def motion_mode(self) -> MotionMode | None:
        """The mode the arm moves in: ours, or with a hardware-linked leader the leader's (from its
        0x151 frames; None until one was heard)."""
        return self._mode_in(self.driver.state())

    @property
    def modes_seen(self) -> tuple[MotionMode, ...]:
        """Every mode the arm moved in at an observation since it was made (what ``piper-record`` stamps)."""
        return tuple(self._modes_seen)

    def _mode_in(self, state: ArmState) -> MotionMode | None:
        if not self.config.hardware_linked_leader:
            return self.motion
        leader = state.leader_mode
        if leader is None:
            return None
        high_follow = leader.value.mit_mode == MIT_MODE_HIGH_FOLLOW
        return MotionMode("high_follow" if high_follow else "position", leader.value.speed_percent)

    @property
    def is_calibrated(self) -> bool:
        return True  # the PiPER reports absolute joint angles; nothing to calibrate

    def calibrate(self) -> None:
        """Nothing to do: no interactive zeroing."""

    def configure(self) -> None:
        """Nothing beyond ``connect``: the enable handshake already selected the motion mode."""

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        self.driver.connect(listen_only=self.config.hardware_linked_leader)
        try:
            if self.config.hardware_linked_leader:
                self.driver.checked_state()
                log.info("%s: hardware-linked leader on %s; observing only", self, self.driver.link.where)
            else:
                self.driver.enable()  # recovers faults as ``recovery`` says, or raises
            for cam in self.cameras.values():
                cam.connect()
        except BaseException:
            self.driver.close()
            raise
        self.configure()
        log.info("%s connected on %s", self, self.driver.link.where)

    @check_if_not_connected
    def get_observation(self) -> dict:
        state = self.driver.checked_state()
        joints, gripper = state.joint_positions_rad, state.gripper
        if joints is None or gripper is None:  # not after connect(), which waited for both
            raise ArmNotReadyError(f"{self}: no joint or gripper feedback yet")
        obs: dict = to_action(joints, gripper.value.opening_m)
        mode = self._mode_in(state)
        if mode is not None:
            self._modes_seen.setdefault(mode)
        if self.config.use_velocity_and_torque:
            velocities, torques = state.joint_velocities_rad_s, state.joint_torques_nm
            if velocities is None or torques is None:  # not after connect(), which waited for them
                raise ArmNotReadyError(f"{self}: no 0x251..0x256 motor feedback yet")
            obs |= dict(zip(VELOCITY_KEYS, velocities, strict=True)) | dict(zip(TORQUE_KEYS, torques, strict=True))
        for name, cam in self.cameras.items():
            obs[name] = cam.read_latest()
        return obs

    @check_if_not_connected
    def send_action(self, action: dict) -> dict:
        joints, gripper = from_action(action)
        if self.config.hardware_linked_leader:
            # The leader drives this arm through the hardware link; sending would fight it.
            return to_action(joints, gripper)
        sent = self.driver.command(joints, gripper)
        return to_action(sent.joints_rad, gripper if sent.gripper_m is None else sent.gripper_m)

    def disconnect(self) -> None:
        """Best effort and never decorated: the disconnect policy runs even if a camera died."""
        try:
            if self.config.hardware_linked_leader:
                self.driver.close()
            else:
                self.driver.disconnect()
        finally:
            for cam in self.cameras.values():
                try:
                    if cam.is_connected:
                        cam.disconnect()
                except Exception as exc:
                    log.warning("camera disconnect failed: %s", exc)
