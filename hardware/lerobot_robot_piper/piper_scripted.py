"""LeRobot teleoperator ``piper_scripted``: scripted demonstrations of the twin's task (``piper_twin.demo``).

It reads the twin's world state (``piper_twin.state_channel``), never the arm's bus: its actions reach the
arm only through the follower (``send_action``), with every check of the driver. Needs the ``twin`` extra.
"""

from __future__ import annotations

import time
from functools import cached_property
from typing import Any

import numpy as np
from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected

from .config_piper_scripted import PiperScriptedConfig
from .features import motor_features, to_action

_MAX_DT_S = 0.2


class PiperScripted(Teleoperator):
    """Actions ``joint_1.pos … joint_6.pos`` (rad) and ``gripper.pos`` (m) of a scripted demonstrator."""

    config_class = PiperScriptedConfig
    name = "piper_scripted"

    def __init__(self, config: PiperScriptedConfig) -> None:
        super().__init__(config)
        self.config = config
        self.demos_started = 0
        self._receiver: Any = None
        self._demo: Any = None
        self._data: Any = None
        self._rng = np.random.default_rng(config.seed)
        self._planned: int | None = None  # the placement the current demonstration is for
        self._last_time_s = 0.0
        self._done_since: float | None = None

    @cached_property
    def action_features(self) -> dict[str, type]:
        return motor_features()

    @cached_property
    def feedback_features(self) -> dict[str, type]:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._receiver is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate."""

    def configure(self) -> None:
        """Nothing to configure."""

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        """Join the twin's state channel and build the scene's model for the IK."""
        try:
            import mujoco
            from piper_twin.demo import ScriptedDemo
            from piper_twin.scenes import compile_scene, get_scene
            from piper_twin.state_channel import StateReceiver
        except ImportError as exc:
            raise ImportError(f"{self} needs the twin extra: pip install -e './hardware[twin]' ({exc})") from exc
        receiver = StateReceiver(self.config.group, self.config.port)
        snapshot = receiver.wait(self.config.connect_timeout_s)
        if snapshot is None:
            receiver.close()
            raise ConnectionError(
                f"{self}: no twin state within {self.config.connect_timeout_s:.1f} s; start "
                f"piper-emulator --physics --state-group={self.config.group} --state-port={self.config.port}"
            )
        scene = get_scene(snapshot.scene)
        model = compile_scene(scene)
        self._demo = ScriptedDemo(
            scene,
            model,
            self.config.speed_m_s,
            self.config.noise_m,
            self.config.detour_m,
            self.config.regrasp_m,
            self.config.close_s,
        )
        self._data = mujoco.MjData(model)
        self._receiver = receiver
        self._last_time_s = snapshot.time_s

    @check_if_not_connected
    def get_action(self) -> dict[str, float]:
        import mujoco

        snapshot = self._fresh_state()
        # The twin's own clock (it runs in real time): a slow caller does not slow the demonstration down.
        dt = min(max(snapshot.time_s - self._last_time_s, 0.0), _MAX_DT_S)
        self._last_time_s = snapshot.time_s
        now = time.monotonic()
        data = self._data
        data.qpos[:], data.mocap_pos[:], data.mocap_quat[:] = snapshot.qpos, snapshot.mocap_pos, snapshot.mocap_quat
        mujoco.mj_kinematics(self._demo.model, data)
        joints = self._demo.ik.joints(snapshot.qpos)
        if self._planned != snapshot.placement:  # objects placed anew: demonstrate from where the arm is
            self._demo.start(data, joints, self._rng)
            self._planned, self._done_since = snapshot.placement, None
            self.demos_started += 1
        targets, gripper = self._demo.step(dt, joints)
        if self._demo.done and self.config.cycle:
            self._done_since = self._done_since if self._done_since is not None else now
            if now - self._done_since >= self.config.pause_s:
                self._request_next(snapshot.seed)
        return to_action(tuple(float(t) for t in targets), gripper)

    def _fresh_state(self) -> Any:
        """The twin's newest state. One older than ``max_age_s`` (a twin stalled on a loaded machine) is
        waited on for up to ``max_age_s`` more; ``TimeoutError`` when no newer one comes (the twin stopped)."""
        deadline = time.monotonic() + self.config.max_age_s
        while True:
            snapshot = self._receiver.latest()
            age = time.time() - snapshot.wall_time_s
            if age <= self.config.max_age_s:
                return snapshot
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self}: no twin state for {age:.2f} s (limit {self.config.max_age_s} s)")
            time.sleep(0.005)

    def _request_next(self, seed: int) -> None:
        from piper_twin.state_channel import request_placement

        request_placement(seed + 1, self.config.group, self.config.port)
        self._done_since = time.monotonic()  # asked again after another pause if the twin did not hear it

    def send_feedback(self, feedback: dict) -> None:
        """Nothing to feed back."""

    def disconnect(self) -> None:
        if self._receiver is not None:
            self._receiver.close()
        self._receiver = None
