"""LeRobot camera ``piper_twin``: the PiPER twin's front or wrist view, rendered from its published state.

``piper-emulator --physics`` publishes the world state (``piper_twin.state_channel``); this camera
receives it and renders the view in this process (``piper_twin.renderer``), on the thread that reads it.
Needs the ``twin`` extra (``mujoco``, ``piper-control``).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from lerobot.cameras import Camera
from lerobot.utils.errors import DeviceNotConnectedError

from .config_piper_twin_camera import PiperTwinCameraConfig


class PiperTwinCamera(Camera):
    """Frames ``(height, width, 3)`` RGB uint8 of ``config.view``, each from the newest twin state."""

    def __init__(self, config: PiperTwinCameraConfig) -> None:
        super().__init__(config)
        self.config = config
        self._receiver: Any = None
        self._renderer: Any = None

    def __str__(self) -> str:
        return f"PiperTwinCamera({self.config.view} @ {self.config.group}:{self.config.port})"

    @property
    def is_connected(self) -> bool:
        return self._receiver is not None

    @staticmethod
    def find_cameras() -> list[dict[str, Any]]:
        return [{"type": "piper_twin", "view": view} for view in ("front", "wrist")]

    def connect(self, warmup: bool = True) -> None:
        """Join the state channel, wait for the first state, build the scene's renderer."""
        if self.is_connected:
            raise RuntimeError(f"{self} is already connected")
        try:
            from piper_twin.renderer import TwinRenderer
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
        self._renderer = TwinRenderer(snapshot.scene, self.config.width, self.config.height)
        self._receiver = receiver
        if warmup:
            self.read()

    def read(self) -> np.ndarray:
        """Render the newest state; refuses one older than ``max_age_s`` (the emulator stopped)."""
        if self._receiver is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        snapshot = self._receiver.latest()
        age = time.time() - snapshot.wall_time_s
        if age > self.config.max_age_s:
            raise TimeoutError(f"{self}: no twin state for {age:.2f} s (limit {self.config.max_age_s} s)")
        return self._renderer.render(snapshot, self.config.view)

    def async_read(self, timeout_ms: float = 200) -> np.ndarray:
        return self.read()

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        return self.read()

    def disconnect(self) -> None:
        if self._receiver is not None:
            self._receiver.close()
            self._renderer.close()
        self._receiver = self._renderer = None
