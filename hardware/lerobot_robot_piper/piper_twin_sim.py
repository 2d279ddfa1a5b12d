"""LeRobot robot ``piper_twin_sim``: ``piper_follower`` on the PiPER's physics twin in this process, faster than
real time (:class:`~lerobot_robot_piper.config_piper_twin_sim.PiperTwinSimConfig`).

The firmware (``piper_can.emulator``), the MuJoCo plant (``piper_twin.plant``) and the real driver run in one
thread on one ``SimulatedClock``, as the hardware tests run them: the emulator steps every 5 ms of simulated time
while ``send_action`` lets one control period pass, the driver reads the bus when asked for the state and judges
its watchdog on the simulated clock. The cameras render the plant's state directly. ``plant`` is the twin, for an
operator that places the scene and reads its success in process (``lerobot-cso --operator.type=twin``). Needs the
``twin`` extra; imported only when this robot is made.
"""

from __future__ import annotations

from typing import Any

import can
from lerobot.utils.decorators import check_if_already_connected
from piper_can.clock import SimulatedClock
from piper_can.emulator import PiperEmulator

from .config_piper_twin_sim import PiperTwinSimConfig
from .piper_follower import PiperFollower


class PiperTwinSim(PiperFollower):
    """The follower's observations and actions, on the twin in this process (see the module doc)."""

    config_class = PiperTwinSimConfig
    name = "piper_twin_sim"
    recovery_hint = "the twin in this process: rerun with --robot.recovery=reset"

    def __init__(self, config: PiperTwinSimConfig) -> None:
        try:
            from piper_twin.plant import TwinPlant
        except ImportError as exc:
            extra = "pip install -e './hardware[twin]'"
            raise ImportError(f"piper_twin_sim needs the twin extra ({extra}): {exc}") from None
        super().__init__(config, SimulatedClock())
        self.config: PiperTwinSimConfig = config
        self.cameras = {}  # rendered from the plant, not received (the twin publishes nothing)
        self.plant = TwinPlant(config.scene, config.scene_seed, config.initial_pose)
        self._renderers: dict[str, Any] = {}
        self._emulator: PiperEmulator | None = None
        self._bus: can.BusABC | None = None

    @property
    def simulated_fps(self) -> int:
        """The control frequency whose period each ``send_action`` lets pass (the caller need not wait)."""
        return self.config.fps

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        """Power the twin on (its firmware on the in-process bus), connect the driver, make the renderers."""
        from piper_twin.renderer import TwinRenderer

        self._bus = can.Bus(interface="virtual", channel=self.config.channel, preserve_timestamps=True)
        self._emulator = PiperEmulator(self._bus, clock=self.driver.clock, plant=self.plant)
        self.driver.clock.every(self._emulator.firmware.config.period_s, self._emulator.step)
        try:
            super().connect(calibrate)
            for name, camera in self.config.cameras.items():
                self._renderers[name] = TwinRenderer(self.plant.scene.name, camera.width, camera.height)
        except BaseException:
            self._power_off()
            raise

    def get_observation(self) -> dict:
        obs = super().get_observation()
        if self._renderers:
            snapshot = self.plant.snapshot()
            for name, renderer in self._renderers.items():
                obs[name] = renderer.render(snapshot, self.config.cameras[name].view)
        return obs

    def send_action(self, action: dict) -> dict:
        """Send as the follower does, then let one control period (``1 / fps``) of simulated time pass."""
        sent = super().send_action(action)
        self.driver.clock.sleep(1 / self.config.fps)
        return sent

    def pass_time(self, seconds: float) -> None:
        """Let ``seconds`` of simulated time pass, the arm holding its last command (e.g. while objects settle)."""
        self.driver.clock.sleep(seconds)

    def disconnect(self) -> None:
        """The follower's disconnect (its policy runs on simulated time), then the twin is powered off."""
        try:
            super().disconnect()
        finally:
            self._power_off()

    def _power_off(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers = {}
        if self._emulator is not None:
            self._emulator.stop()
        if self._bus is not None:
            self._bus.shutdown()
        self._emulator = self._bus = None
