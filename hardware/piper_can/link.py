"""One python-can bus to a PiPER: a reader thread feeding a ``FeedbackCache``, a stale-feedback
watchdog, and locked sends.

Every frame is stamped with its arrival time: python-can's ``msg.timestamp`` (the kernel's receive time
on socketcan and udp_multicast, the send time on virtual), or this process's clock where an interface
stamps frames on another clock. The watchdog watches a set of frame IDs (the joint frames) and counts
as stale when some watched ID last *arrived* more than ``stale_timeout_s`` ago. The reader drains
every queued frame before it judges, and trips (latched) when the bus went silent or the watched
frames stopped; ``raise_if_stale`` applies the same test when asked, so a reader that fell behind
(starved of CPU) cannot pass old positions off as fresh.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping

import can

from .codec import (
    COMMAND_IDS,
    DLC,
    FEEDBACK_IDS,
    ID_EMERGENCY_STOP,
    ID_FIRMWARE,
    ID_LIMIT_QUERY,
    ID_MASTER_SLAVE,
    ID_MOTOR_ENABLE,
    Frame,
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
_KEPT_IDS = FEEDBACK_IDS | OBSERVED_CONTROL_IDS
_IDLE_WAIT_S = 0.05
_POLL_S = 0.002
# python-can timestamps on the time.time() clock for socketcan, udp_multicast and virtual; an interface
# whose stamps are further off than this uses another clock (e.g. the adapter's), so use our own.
_PLAUSIBLE_CLOCK_SKEW_S = 5.0


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
        self._armed_at = 0.0
        self._last_seen: dict[int, float] = {}
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
        self._armed_at = time.time()
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
        """Raise ``FeedbackStaleError`` if the watchdog tripped, trips now, or the reader died."""
        if self._thread is None or not self._thread.is_alive():
            raise FeedbackStaleError(f"the CAN reader for {self.where} is not running; reconnect")
        if self._armed and self._stale is None:
            # Frames may be queued for a reader that merely waits for the GIL: give it up to one
            # timeout to drain them before judging.
            deadline = time.monotonic() + self.stale_timeout_s
            while time.time() - self._evidence_start() > self.stale_timeout_s and time.monotonic() < deadline:
                time.sleep(_POLL_S / 4)
            self._check_age(time.time())
        if self._stale is not None:
            raise self._stale

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
        """When the watched set was last complete: the oldest watched arrival (or the arming time)."""
        oldest = min((self._last_seen.get(i, 0.0) for i in self.watch_ids), default=0.0)
        return max(oldest, self._armed_at)

    def _check_age(self, now: float) -> None:
        age = now - self._evidence_start()
        if age > self.stale_timeout_s and self._stale is None:
            self.stale_at = now
            self._stale = FeedbackStaleError(
                f"stale feedback: no {self.watch_name} from the PiPER on {self.where} for {age * 1e3:.0f} ms "
                f"(limit {self.stale_timeout_s * 1e3:.0f} ms); commands stopped"
            )
            log.error("%s", self._stale)

    def _read_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        while not self._stop.is_set():
            wait = _IDLE_WAIT_S
            if self._armed and self._stale is None:
                wait = min(max(self._evidence_start() + self.stale_timeout_s - time.time(), 5e-4), wait)
            try:
                msg = bus.recv(timeout=wait)
                while True:  # drain everything queued before judging the age
                    if msg is not None:
                        self._handle(msg)
                    now = time.time()
                    msg = bus.recv(timeout=0)
                    if msg is None:
                        break
            except Exception as exc:  # the bus went away under us
                if self._stale is None:
                    self.stale_at = time.time()
                    self._stale = FeedbackStaleError(f"reading the CAN bus {self.where} failed: {exc}")
                    log.error("%s", self._stale)
                return
            # The queue was empty at ``now``: nothing that arrived before ``now`` is still unread.
            if self._armed:
                self._check_age(now)
            self.cache.roll_rates(now)

    def _handle(self, msg: can.Message) -> None:
        frame_id = msg.arbitration_id
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or frame_id not in _KEPT_IDS:
            return
        if len(msg.data) != DLC:
            self.bad_frames += 1
            return
        now = time.time()
        arrived = msg.timestamp if abs(now - msg.timestamp) < _PLAUSIBLE_CLOCK_SKEW_S else now
        self.cache.update(frame_id, bytes(msg.data), arrived)
        self._last_seen[frame_id] = arrived
