"""LeRobot camera ``piper_twin``: the PiPER twin's front or wrist view, rendered from its published state.

``piper-emulator --physics`` publishes the world state (``piper_twin.state_channel``); this camera receives it
and renders the view in this process (``piper_twin.renderer``) on its own capture thread, ``fps`` times a second,
as a real camera captures: ``read_latest`` (what the follower's control loop calls) returns the newest frame at
once, and the render costs the loop no time. Needs the ``twin`` extra (``mujoco``, ``piper-control``).
"""

from __future__ import annotations

import threading
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
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._new_frame = threading.Condition()
        self._frame: tuple[np.ndarray, float] | None = None  # the newest frame and its state's wall time
        self._error: BaseException | None = None

    def __str__(self) -> str:
        return f"PiperTwinCamera({self.config.view} @ {self.config.group}:{self.config.port})"

    @property
    def is_connected(self) -> bool:
        return self._receiver is not None

    @staticmethod
    def find_cameras() -> list[dict[str, Any]]:
        return [{"type": "piper_twin", "view": view} for view in ("front", "wrist")]

    def connect(self, warmup: bool = True) -> None:
        """Join the state channel, wait for the first state, start the capture thread and wait for its first
        frame (the thread builds the scene's renderer: a GL context belongs to the thread that made it)."""
        if self.is_connected:
            raise RuntimeError(f"{self} is already connected")
        try:
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
        self._receiver, self._frame, self._error = receiver, None, None
        self._stop.clear()
        self._thread = threading.Thread(target=self._capture, args=(snapshot.scene,), name=str(self), daemon=True)
        self._thread.start()
        try:
            self._wait_for_frame(after=None, timeout_s=max(self.config.connect_timeout_s, 10.0))
        except BaseException:
            self.disconnect()
            raise

    def _capture(self, scene: str) -> None:
        """The capture thread: render each new state, at most ``fps`` times a second, until disconnected."""
        try:
            from piper_twin.renderer import TwinRenderer

            renderer = TwinRenderer(scene, self.config.width, self.config.height)
        except BaseException as exc:  # handed to the reader
            with self._new_frame:
                self._error = exc
                self._new_frame.notify_all()
            return
        period, rendered = 1.0 / self.config.fps, None
        try:
            while not self._stop.is_set():
                started = time.monotonic()
                snapshot = self._receiver.latest()
                if snapshot is not None and snapshot is not rendered:
                    frame = renderer.render(snapshot, self.config.view)
                    rendered = snapshot
                    with self._new_frame:
                        self._frame = (frame, snapshot.wall_time_s)
                        self._new_frame.notify_all()
                self._stop.wait(max(0.0, period - (time.monotonic() - started)))
        except BaseException as exc:
            with self._new_frame:
                self._error = exc
                self._new_frame.notify_all()
        finally:
            renderer.close()

    def _wait_for_frame(self, after: tuple[np.ndarray, float] | None, timeout_s: float) -> tuple[np.ndarray, float]:
        """A frame other than ``after``, waiting up to ``timeout_s``; the capture thread's error is raised here."""
        with self._new_frame:
            self._new_frame.wait_for(lambda: self._error is not None or self._frame is not after, timeout_s)
            if self._error is not None:
                raise RuntimeError(f"{self}: the capture thread failed: {self._error!r}") from self._error
            if self._frame is after:
                raise TimeoutError(f"{self}: no new frame within {timeout_s:.2f} s")
            return self._frame

    def _fresh(self, frame: tuple[np.ndarray, float]) -> np.ndarray:
        """``frame``'s image; refuses one from a state older than ``max_age_s`` (the emulator stopped)."""
        age = time.time() - frame[1]
        if age > self.config.max_age_s:
            raise TimeoutError(f"{self}: no twin state for {age:.2f} s (limit {self.config.max_age_s} s)")
        return frame[0]

    def read(self) -> np.ndarray:
        """The next frame the capture thread renders (blocks up to ``max_age_s``)."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        with self._new_frame:
            newest = self._frame
        return self._fresh(self._wait_for_frame(after=newest, timeout_s=self.config.max_age_s))

    def async_read(self, timeout_ms: float = 200) -> np.ndarray:
        """The next frame, waiting up to ``timeout_ms``."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        with self._new_frame:
            newest = self._frame
        return self._fresh(self._wait_for_frame(after=newest, timeout_s=timeout_ms / 1000))

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        """The newest frame at once (the control loop's read), refused when its state is older than ``max_age_s``."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        with self._new_frame:
            if self._error is not None:
                raise RuntimeError(f"{self}: the capture thread failed: {self._error!r}") from self._error
            frame = self._frame
        return self._fresh(frame)  # connect() waited for the first

    def disconnect(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
        if self._receiver is not None:
            self._receiver.close()
        self._receiver = None
