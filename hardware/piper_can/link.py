"""One python-can bus to a PiPER: a reader thread feeding a ``FeedbackCache``, a stale-feedback
watchdog, and locked sends.

Timestamps are this process's ``time.monotonic()`` at receipt, the same clock for every python-can
interface. The watchdog watches a set of frame IDs (the joint frames) and trips when, for more than
``stale_timeout_s``, no fresh frame of every watched ID arrived:

* the receive queue is empty and the deadline passed (the bus went silent or the watched frames stopped), or
* other frames keep arriving while a watched ID stays missing.

A gap in *all* traffic longer than the timeout, seen while frames are still queued, means this reader
was starved (or the socket dropped frames), not that the arm stopped: it restarts the evidence window
instead of tripping.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping

import can

from .codec import (
    COMMAND_IDS,
    FEEDBACK_IDS,
    ID_EMERGENCY_STOP,
    ID_FIRMWARE,
    ID_LIMIT_QUERY,
    ID_MASTER_SLAVE,
    ID_MOTOR_ENABLE,
    CodecError,
    Frame,
    decode_command,
    decode_feedback,
)
from .errors import FeedbackStaleError, PiperConnectionError
from .state import ArmState, FeedbackCache

log = logging.getLogger(__name__)

# Host -> arm frames worth caching when another host or a linked leader sends them.
OBSERVED_CONTROL_IDS = COMMAND_IDS - {
    ID_EMERGENCY_STOP,
    ID_FIRMWARE,
    ID_LIMIT_QUERY,
    ID_MASTER_SLAVE,
    ID_MOTOR_ENABLE,
}
_IDLE_WAIT_S = 0.05
_POLL_S = 0.002


def open_bus(interface: str, channel: str, bitrate: int, bus_options: Mapping[str, object]) -> can.BusABC:
    """Open a python-can bus, turning every failure into one ``PiperConnectionError`` line."""
    if not interface:
        raise PiperConnectionError("no CAN interface given (e.g. socketcan, slcan, udp_multicast)")
    if not channel:
        raise PiperConnectionError(f"no CAN channel given for interface {interface!r} (e.g. can0)")
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **bus_options)
    except Exception as exc:  # python-can raises OSError, CanError, ValueError, ImportError ...
        hint = (
            f"; bring the adapter up with: sudo ip link set {channel} up type can bitrate {bitrate}"
            if interface == "socketcan"
            else ""
        )
        raise PiperConnectionError(
            f"cannot open CAN bus {interface}:{channel}: {type(exc).__name__}: {exc}{hint}"
        ) from exc


class PiperLink:
    """Reader thread, state cache, watchdog and thread-safe sends on one CAN bus."""

    def __init__(
        self,
        interface: str,
        channel: str,
        bitrate: int = 1_000_000,
        bus_options: Mapping[str, object] | None = None,
        watch_ids: Iterable[int] = (),
        stale_timeout_s: float = 0.015,
        watch_name: str = "joint feedback",
    ) -> None:
        if stale_timeout_s <= 0:
            raise ValueError(f"stale_timeout_s must be positive, got {stale_timeout_s}")
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.bus_options = dict(bus_options or {})
        self.watch_ids = frozenset(watch_ids)
        self.stale_timeout_s = stale_timeout_s
        self.watch_name = watch_name
        self.cache = FeedbackCache()
        self.bad_frames = 0
        self._bus: can.BusABC | None = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._armed = False
        self._last_seen: dict[int, float] = {}
        self._resume_ts = 0.0
        self._stale: FeedbackStaleError | None = None
        self.stale_at: float | None = None

    @property
    def where(self) -> str:
        return f"{self.interface}:{self.channel}"

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def open(self, first_frames: Iterable[int], timeout_s: float) -> None:
        """Open the bus, start the reader and wait until every ID in ``first_frames`` was heard."""
        if self._bus is not None:
            raise PiperConnectionError(f"the CAN bus {self.where} is already open")
        self._bus = open_bus(self.interface, self.channel, self.bitrate, self.bus_options)
        self.cache = FeedbackCache()
        self._last_seen = {}
        self._stop.clear()
        self._thread = threading.Thread(target=self._read_loop, name=f"piper-reader-{self.channel}", daemon=True)
        self._thread.start()
        wanted = frozenset(first_frames)
        if not self._wait(lambda: all(i in self._last_seen for i in wanted), timeout_s):
            self.close()
            missing = ", ".join(f"0x{i:X}" for i in sorted(wanted) if i not in self._last_seen)
            raise PiperConnectionError(
                f"no PiPER heard on {self.where} within {timeout_s:.1f} s (missing frames {missing}); "
                "check the channel, the wiring and that the arm is powered"
            )
        self.arm_watchdog()

    def arm_watchdog(self) -> None:
        """(Re)start watching: clears a previous trip; the window starts now."""
        now = time.monotonic()
        self._resume_ts = now
        self._stale = None
        self.stale_at = None
        self._armed = bool(self.watch_ids)

    def close(self) -> None:
        """Stop the reader and release the bus; safe to call twice."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()
        self._armed = False

    def send(self, *frames: Frame) -> None:
        """Send frames back to back under one lock (no other thread's frame in between)."""
        bus = self._bus
        if bus is None:
            raise PiperConnectionError(f"the CAN bus {self.where} is not open")
        with self._send_lock:
            for frame in frames:
                msg = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
                try:
                    bus.send(msg, timeout=0.05)
                except can.CanError as exc:
                    raise PiperConnectionError(
                        f"sending 0x{frame.arbitration_id:X} on {self.where} failed: {exc}"
                    ) from exc

    def state(self) -> ArmState:
        return self.cache.snapshot()

    @property
    def stale_error(self) -> FeedbackStaleError | None:
        """The watchdog's error once tripped (it stays tripped until ``arm_watchdog``)."""
        return self._stale

    def raise_if_stale(self) -> None:
        if self._stale is not None:
            raise self._stale
        if self._thread is None or not self._thread.is_alive():
            raise FeedbackStaleError(f"the CAN reader for {self.where} is not running; reconnect")

    def wait_for(self, predicate: Callable[[ArmState], bool], timeout_s: float) -> bool:
        """Poll the state until ``predicate`` holds; False on timeout."""
        return self._wait(lambda: predicate(self.cache.snapshot()), timeout_s)

    @staticmethod
    def _wait(condition: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while True:
            if condition():
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(_POLL_S)

    # ---------------------------------------------------------------------------- reader thread
    def _evidence_start(self) -> float:
        """Since when the watched set has been incomplete: the oldest watched ID, or a traffic resume."""
        oldest = min((self._last_seen.get(i, 0.0) for i in self.watch_ids), default=0.0)
        return max(oldest, self._resume_ts)

    def _trip(self, now: float, reason: str) -> None:
        if self._stale is None:
            self.stale_at = now
            self._stale = FeedbackStaleError(reason)
            log.error("%s", reason)

    def _check_age(self, now: float) -> None:
        age = now - self._evidence_start()
        if age > self.stale_timeout_s:
            self._trip(
                now,
                f"stale feedback: no {self.watch_name} from the PiPER on {self.where} for {age * 1e3:.0f} ms "
                f"(limit {self.stale_timeout_s * 1e3:.0f} ms); commands stopped",
            )

    def _read_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        previous = time.monotonic()
        while not self._stop.is_set():
            wait = _IDLE_WAIT_S
            if self._armed and self._stale is None:
                wait = min(max(self._evidence_start() + self.stale_timeout_s - time.monotonic(), 5e-4), wait)
            try:
                msg = bus.recv(timeout=wait)
            except Exception as exc:  # the bus went away under us
                self._trip(time.monotonic(), f"reading the CAN bus {self.where} failed: {exc}")
                return
            now = time.monotonic()
            if msg is None:
                if self._armed:
                    self._check_age(now)
                self.cache.roll_rates(now)
                continue
            if now - previous > self.stale_timeout_s:
                self._resume_ts = now  # this reader was starved; frames were waiting for it
            previous = now
            self._handle(msg, now)
            if self._armed:
                self._check_age(now)
            self.cache.roll_rates(now)

    def _handle(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        frame_id = msg.arbitration_id
        try:
            if frame_id in FEEDBACK_IDS:
                decoded = decode_feedback(frame_id, msg.data)
            elif frame_id in OBSERVED_CONTROL_IDS:
                decoded = decode_command(frame_id, msg.data)
            else:
                return
        except CodecError as exc:
            self.bad_frames += 1
            log.debug("ignoring malformed frame: %s", exc)
            return
        self.cache.update(frame_id, decoded, now)
        self._last_seen[frame_id] = now
