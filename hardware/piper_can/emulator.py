"""Runs the simulated PiPER firmware (``piper_can.firmware``) on a python-can bus.

Two ways: ``step(dt)`` handles every queued frame, advances the model ``dt`` and sends one cycle
(deterministic; on a ``SimulatedClock``, register it with ``clock.every(period, emulator.step)``);
``start()`` does the same in real time on a daemon thread. While that thread runs, change the model
inside ``with emulator.locked() as firmware:``. Frames are stamped with the clock's time (kept by
python-can's ``virtual`` bus with ``preserve_timestamps=True``).
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import can

from .clock import SYSTEM_CLOCK, Clock
from .codec import Frame
from .firmware import EmulatorConfig, PiperFirmware, Plant

log = logging.getLogger(__name__)

_MAX_REAL_TIME_STEP_S = 0.1


class PiperEmulator:
    """A ``PiperFirmware`` on ``bus``: received frames go to ``handle``, its frames go on the bus. With a
    ``plant`` (``piper_twin``'s physics) the firmware's motors are that plant's."""

    def __init__(
        self,
        bus: can.BusABC,
        config: EmulatorConfig | None = None,
        clock: Clock = SYSTEM_CLOCK,
        plant: Plant | None = None,
    ) -> None:
        self.bus = bus
        self.clock = clock
        self.firmware = PiperFirmware(config, plant)
        self._rng = random.Random(self.firmware.config.seed)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.RLock()

    @contextmanager
    def locked(self) -> Iterator[PiperFirmware]:
        """The model, with the real-time loop held off while the block runs."""
        with self._lock:
            yield self.firmware

    def step(self, dt: float | None = None) -> None:
        """Handle every queued host frame, advance ``dt`` (default one period) and send one cycle."""
        while (msg := self.bus.recv(timeout=0)) is not None:
            self._receive(msg)
        self._advance(self.firmware.config.period_s if dt is None else dt)

    def start(self) -> None:
        """Run in real time on a daemon thread until ``stop``."""
        if self._thread is not None:
            raise RuntimeError("the emulator is already running")
        if not self.clock.real_time:
            raise RuntimeError("a simulated clock runs the emulator through clock.every(period, emulator.step)")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="piper-emulator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def _run(self) -> None:
        """One cycle per period; the model advances by the wall time that really passed (so a busy
        machine delays frames, as a loaded bus would, but never slows the simulated arm down)."""
        cfg = self.firmware.config
        wall_period = cfg.period_s / cfg.rate_scale
        last = time.monotonic()
        next_tick = last + wall_period
        while not self._stop.is_set():
            # Every frame that has arrived is handled before the next cycle, even when the loop runs late.
            while (msg := self.bus.recv(timeout=max(next_tick - time.monotonic(), 0.0))) is not None:
                self._receive(msg)
            now = time.monotonic()
            self._advance(min((now - last) * cfg.rate_scale, _MAX_REAL_TIME_STEP_S))
            last = now
            next_tick += wall_period + (self._rng.uniform(0, cfg.jitter_s) if cfg.jitter_s else 0.0)
            if now - next_tick > 0.1:  # fell far behind (machine busy): resynchronise
                next_tick = now

    def _receive(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        with self._lock:
            replies = self.firmware.handle(Frame(msg.arbitration_id, bytes(msg.data)), msg.is_extended_id)
        self._send(replies)

    def _advance(self, dt: float) -> None:
        with self._lock:
            frames = self.firmware.tick(dt)
        self._send(frames)

    def _send(self, frames: list[Frame]) -> None:
        for frame in frames:
            msg = can.Message(
                timestamp=self.clock.time(), arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False
            )
            try:
                self.bus.send(msg)
            except can.CanError as exc:  # a full socket buffer must not kill the firmware loop
                log.debug("emulator send failed: %s", exc)
