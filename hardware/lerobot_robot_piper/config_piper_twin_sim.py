"""Configuration of the ``piper_twin_sim`` robot: the PiPER's physics twin inside this process, on simulated time."""

from __future__ import annotations

from dataclasses import dataclass, replace

from lerobot.robots.config import RobotConfig
from piper_can.settings import DriverConfig

from .config_piper_follower import PiperFollowerConfig
from .config_piper_twin_camera import PiperTwinCameraConfig
from .motion_metadata import MotionMode


@RobotConfig.register_subclass("piper_twin_sim")
@dataclass
class PiperTwinSimConfig(PiperFollowerConfig):
    """``piper_follower`` on the twin in this process, faster than real time: the simulated firmware, its MuJoCo
    arm in ``scene`` (placed from ``scene_seed``) and the real driver share one simulated clock, and every
    ``send_action`` advances it by one control period, ``1 / fps``. Nothing waits for the wall clock, so a loop
    runs as fast as the physics, the cameras and the policy allow; their time costs no simulated time.

    Every follower setting applies; ``channel`` names the in-process CAN bus (python-can ``virtual``),
    ``interface`` is ignored. ``cameras`` are ``piper_twin`` cameras (``view``, ``width``, ``height``), rendered
    here from the twin's state."""

    scene: str = "press_button"
    scene_seed: int = 0
    # The arm's pose at power-on (6 angles in rad); null: all zero.
    initial_pose: list[float] | None = None
    # The control frequency the caller runs at: each send_action advances the twin by 1 / fps seconds.
    fps: int = 30

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (isinstance(self.fps, int) and self.fps >= 1):
            raise ValueError(f"piper_twin_sim fps must be an integer >= 1, got {self.fps!r}")
        if self.initial_pose is not None and len(self.initial_pose) != 6:
            raise ValueError(f"piper_twin_sim initial_pose needs 6 angles in rad, got {len(self.initial_pose)}")
        for name, camera in self.cameras.items():
            if not isinstance(camera, PiperTwinCameraConfig):
                raise ValueError(f"piper_twin_sim renders piper_twin cameras only; camera {name!r} is {camera.type}")

    def driver_config(self, motion: MotionMode | None = None) -> DriverConfig:
        """The follower's driver settings on the in-process ``virtual`` bus, each frame keeping its simulated
        send time."""
        return replace(super().driver_config(motion), interface="virtual", bus_options={"preserve_timestamps": True})
