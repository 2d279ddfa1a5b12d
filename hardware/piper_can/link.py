"""One python-can bus to a PiPER: a reader thread feeding a ``FeedbackCache``, a stale-feedback
watchdog, CAN error frames, and locked sends.

Every frame is stamped with its arrival time on the clock's *monotonic* time: python-can's
``msg.timestamp`` (the kernel's CLOCK_REALTIME receive time on socketcan and udp_multicast, the send time on
virtual) re-based by the wall-to-monotonic offset read when the frame is handled, so a wall-clock step (an
NTP step, a VM resync) neither freezes the cache nor blinds the watchdog; a stamp that lands in the future
or far in the past (a frame in flight across a step, an interface stamping on another clock) is replaced by
the handling time. The ``Watchdog`` gives each watched frame ID its own timeout and counts
as stale when some watched ID last *arrived* longer ago than that. The reader drains every queued
frame before it judges, and trips (latched) when the bus went silent or a watched frame stopped;
``raise_if_unhealthy`` applies the same test when asked, so a reader that fell behind (starved of CPU)
cannot pass old positions off as fresh. A trip is re-armed only explicitly, and only once every
watched frame has arrived again (``rearm``). CAN error frames are counted and logged; bus-off is
latched like a trip.

On a simulated clock (``piper_can.clock``) there is no reader thread: every ``state``,
``raise_if_unhealthy`` and wait first reads what is queued (``poll``), then judges at the clock's time.
"""

from __future__ import annotations

import errno
import logging
import threading
from collections import Counter, deque
from collections.abc import Callable, Mapping

import can

from .clock import SYSTEM_CLOCK, Clock
from .codec import (
    COMMAND_IDS,
    DLC,
    FEEDBACK_IDS,
    ID_COLLISION_CONFIG,
    ID_FIRMWARE,
    ID_JOINT_CONFIG,
    ID_LIMIT_QUERY,
    ID_MASTER_SLAVE,
    ID_MOTOR_ENABLE,
    ID_MOTOR_LIMITS_SET,
    ID_PARAM_QUERY,
    Frame,
)
from .errors import CanBusError, FeedbackStaleError, PartialCommandError, PiperConnectionError
from .state import ArmState, FeedbackCache

log = logging.getLogger(__name__)

# Host -> arm frames worth caching when another host or a linked leader sends them: its targets, its
# mode changes, and its e-stops and resets. Interfaces that deliver our own frames back (udp_multicast
# loops them to every local listener; ``receive_own_messages``) are filtered: see ``EchoFilter``.
OBSERVED_CONTROL_IDS = COMMAND_IDS - {
    ID_FIRMWARE,
    ID_JOINT_CONFIG,
    ID_LIMIT_QUERY,
    ID_MASTER_SLAVE,
    ID_MOTOR_ENABLE,
    ID_MOTOR_LIMITS_SET,
    ID_PARAM_QUERY,
    ID_COLLISION_CONFIG,
}
_KEPT_IDS = FEEDBACK_IDS | OBSERVED_CONTROL_IDS
# Our own frame coming back this soon, with the same ID and bytes, is an echo (not another host).
ECHO_WINDOW_S = 0.5
_ECHOES_KEPT = 64
_IDLE_WAIT_S = 0.05
_POLL_S = 0.002
# python-can timestamps on the time.time() clock for socketcan, udp_multicast and virtual; an interface
# whose stamps are further off than this uses another clock (e.g. the adapter's), so use the handling time.
_PLAUSIBLE_CLOCK_SKEW_S = 5.0
# SocketCAN error classes (linux/can/error.h), carried in an error frame's ID.
CAN_ERR_BUSOFF = 0x040
CAN_ERR_CLASSES = {
    0x001: "TX timeout",
    0x002: "lost arbitration",
    0x004: "controller problem",
    0x008: "protocol violation",
    0x010: "transceiver problem",
    0x020: "no acknowledgement (nobody else on the bus?)",
    CAN_ERR_BUSOFF: "bus-off",
    0x080: "bus error",
    0x100: "controller restarted",
}
_SERIOUS_ERRORS = {0x020, CAN_ERR_BUSOFF}


def quiet_frame_log() -> None:
    """Stop python-can's per-frame log record unless someone asked for it.

    ``BusABC.recv`` logs every received frame at level 9. LeRobot's ``init_logging`` leaves the root logger at
    NOTSET, so the reader would build a record for each of the arm's 3 040 frames/s that no handler prints: ≈ 15 µs
    each with the GIL held, ≈ 4.5 % of a core taken from the control loop's process. ``can.bus`` is set to DEBUG
    only while its own level is unset; set it to 9 before connecting to see the frames.
    """
    frames = logging.getLogger("can.bus")
    if frames.level == logging.NOTSET:
        frames.setLevel(logging.DEBUG)


def open_bus(interface: str, channel: str, bitrate: int, bus_options: Mapping[str, object]) -> can.BusABC:
    """Open a python-can bus, turning every failure into one ``PiperConnectionError`` line."""
    if not interface:
        raise PiperConnectionError("no CAN interface given (e.g. socketcan, slcan, udp_multicast)")
    if not channel:
        raise PiperConnectionError(f"no CAN channel given for interface {interface!r} (e.g. can0)")
    quiet_frame_log()
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **bus_options)
    except Exception as exc:  # python-can raises OSError, CanError, ValueError, ImportError ...
        hint = ""
        if interface == "socketcan":
            hint = f"; bring the adapter up with: sudo ip link set {channel} up type can bitrate {bitrate}"
            if isinstance(exc, OSError) and exc.errno == errno.EAFNOSUPPORT:  # no SocketCAN in this kernel (yet)
                hint = (
                    "; this kernel has no SocketCAN support loaded: load it with sudo modprobe can can_raw (and your "
                    f"adapter's driver, e.g. gs_usb), then{hint.removeprefix(';')}"
                )
        raise PiperConnectionError(
            f"cannot open CAN bus {interface}:{channel}: {type(exc).__name__}: {exc}{hint}"
        ) from exc


class Watchdog:
    """Pure stale-feedback judgement on given times: every watched ID must arrive within its timeout."""

    def __init__(self, timeouts: Mapping[int, float]) -> None:
        for frame_id, limit in timeouts.items():
            if limit <= 0:
                raise ValueError(f"the timeout of 0x{frame_id:X} must be positive, got {limit}")
        self.timeouts = dict(timeouts)
        self.last_seen: dict[int, float] = {}
        self.armed_at: float | None = None

    @property
    def armed(self) -> bool:
        return self.armed_at is not None and bool(self.timeouts)

    def _start(self, frame_id: int) -> float:
        """When ``frame_id``'s window began: its last arrival, but not before arming."""
        return max(self.last_seen.get(frame_id, 0.0), self.armed_at or 0.0)

    def arm(self, now: float) -> None:
        """Start watching; the window of every ID starts no earlier than ``now``."""
        self.armed_at = now

    def disarm(self) -> None:
        self.armed_at = None

    def seen(self, frame_id: int, arrived: float) -> None:
        if frame_id in self.timeouts:
            self.last_seen[frame_id] = max(arrived, self.last_seen.get(frame_id, arrived))

    def overdue(self, now: float) -> list[tuple[int, float]]:
        """``(id, age)`` of every watched ID older than its timeout at ``now`` (none when disarmed)."""
        if not self.armed:
            return []
        found = []
        for frame_id, limit in self.timeouts.items():
            age = now - self._start(frame_id)
            if age > limit:
                found.append((frame_id, age))
        return found

    def next_deadline(self) -> float | None:
        """The earliest time some watched ID becomes stale if nothing more arrives."""
        if not self.armed:
            return None
        return min(self._start(i) + limit for i, limit in self.timeouts.items())

    def missing_since(self, since: float, now: float) -> list[int]:
        """Watched IDs not heard after ``since`` or older than their timeout at ``now``."""
        return [
            i
            for i, limit in self.timeouts.items()
            if self.last_seen.get(i, 0.0) <= since or now - self.last_seen[i] > limit
        ]


def bus_echoes(interface: str, bus_options: Mapping[str, object]) -> bool:
    """Whether python-can delivers our own sent frames back to us on this bus (udp_multicast always loops
    them to local listeners; any interface with ``receive_own_messages``)."""
    return interface == "udp_multicast" or bool(bus_options.get("receive_own_messages", False))


class EchoFilter:
    """Recognises our own control frames delivered back to us, so they do not pass for another host's. On a
    bus that does not echo (``echoes`` False) nothing is an echo: a frame with our bytes is another host's."""

    def __init__(self, echoes: bool) -> None:
        self.echoes = echoes
        self._lock = threading.Lock()
        self._sent: deque[tuple[int, bytes, float]] = deque(maxlen=_ECHOES_KEPT)

    def sent(self, frame_id: int, data: bytes, at: float) -> None:
        if not self.echoes:
            return
        with self._lock:
            self._sent.append((frame_id, data, at))

    def is_echo(self, frame_id: int, data: bytes, at: float) -> bool:
        """Whether this received frame is one we sent within ``ECHO_WINDOW_S`` (each echo counts once)."""
        if not self.echoes:
            return False
        with self._lock:
            for entry in self._sent:
                sent_id, sent_data, sent_at = entry
                if sent_id == frame_id and sent_data == data and abs(at - sent_at) <= ECHO_WINDOW_S:
                    self._sent.remove(entry)
                    return True
        return False


class PiperLink:
    """Reader thread, state cache, watchdog, error frames and thread-safe sends on one CAN bus."""

    def __init__(
        self,
        interface: str,
        channel: str,
        bitrate: int = 1_000_000,
        bus_options: Mapping[str, object] | None = None,
        watch: Mapping[int, float] | None = None,
        watch_name: str = "feedback",
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.bus_options = dict(bus_options or {})
        self.watchdog = Watchdog(watch or {})
        self.watch_name = watch_name
        self.clock = clock
        self.cache = FeedbackCache()
        self.bad_frames = 0
        self.error_frames: Counter[str] = Counter()
        self._bus: can.BusABC | None = None
        self._send_lock = threading.Lock()
        self._poll_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._heard: set[int] = set()
        self._echoes = EchoFilter(bus_echoes(interface, self.bus_options))
        self._stale: FeedbackStaleError | None = None
        self._bus_error: CanBusError | None = None
        self.stale_at: float | None = None
        self._drains = 0  # how often the reader found its queue empty: see ``caught_up``

    @property
    def where(self) -> str:
        return f"{self.interface}:{self.channel}"

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def open(self, first_frames: tuple[int, ...], timeout_s: float) -> None:
        """Open the bus, start the reader and wait until every ID in ``first_frames`` was heard."""
        if self._bus is not None:
            raise PiperConnectionError(f"the CAN bus {self.where} is already open")
        self._bus = open_bus(self.interface, self.channel, self.bitrate, self.bus_options)
        self.cache = FeedbackCache()
        self._heard = set()
        self.watchdog.last_seen.clear()
        self.error_frames.clear()
        self._bus_error = None
        self._stop.clear()
        if self.clock.real_time:
            self._thread = threading.Thread(target=self._read_loop, name=f"piper-reader-{self.channel}", daemon=True)
            self._thread.start()
        wanted = frozenset(first_frames)
        if not self._wait(lambda: wanted <= self._heard, timeout_s):
            self.close()
            missing = ", ".join(f"0x{i:X}" for i in sorted(wanted - self._heard))
            raise PiperConnectionError(
                f"no PiPER heard on {self.where} within {timeout_s:.1f} s (missing frames {missing}); "
                "check the channel, the wiring and that the arm is powered"
            )
        self._arm(self.clock.monotonic())

    def _arm(self, now: float) -> None:
        self._stale = None
        self.stale_at = None
        self.watchdog.arm(now)

    def rearm(self) -> None:
        """Re-arm a tripped watchdog (and clear a bus-off) once every watched frame arrived again after
        the trip; otherwise raise ``FeedbackStaleError`` naming what is still missing."""
        self.poll()
        now = self.clock.monotonic()
        since = self.stale_at if self.stale_at is not None else (self.watchdog.armed_at or 0.0)
        missing = self.watchdog.missing_since(since, now)
        if not self._reading() or missing:
            what = ", ".join(f"0x{i:X}" for i in missing) or "the reader"
            raise FeedbackStaleError(f"cannot re-arm the watchdog on {self.where}: still no fresh {what}")
        log.warning("PiPER on %s: watchdog re-armed after fresh feedback (was: %s)", self.where, self._stale)
        self._bus_error = None
        self._arm(now)

    def close(self) -> None:
        """Stop the reader and release the bus; safe to call twice."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()
        self.watchdog.disarm()

    def send(self, *frames: Frame, guard: Callable[[], None] | None = None) -> None:
        """Send frames back to back under one lock (no other thread's frame in between).

        ``guard`` runs under the lock before each frame and may raise to stop the rest. A failure after
        the first frame raises ``PartialCommandError`` naming the frames sent and not sent.
        """
        bus = self._bus
        if bus is None:
            raise PiperConnectionError(f"the CAN bus {self.where} is not open")
        with self._send_lock:
            for i, frame in enumerate(frames):
                try:
                    if guard is not None:
                        guard()
                    self._send_one(bus, frame)
                except Exception as exc:
                    if i == 0:
                        raise
                    ids = tuple(f.arbitration_id for f in frames)
                    raise PartialCommandError(self.where, ids[:i], ids[i:], exc) from exc

    def _send_one(self, bus: can.BusABC, frame: Frame) -> None:
        msg = can.Message(
            timestamp=self.clock.time(), arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False
        )
        if frame.arbitration_id in OBSERVED_CONTROL_IDS:
            self._echoes.sent(frame.arbitration_id, bytes(frame.data), self.clock.monotonic())
        try:
            bus.send(msg, timeout=0.05)
        except can.CanError as exc:
            raise PiperConnectionError(f"sending 0x{frame.arbitration_id:X} on {self.where} failed: {exc}") from exc

    def state(self) -> ArmState:
        self.poll()
        return self.cache.snapshot()

    def poll(self) -> None:
        """On a simulated clock: read every queued frame and judge the watchdog now (no-op otherwise:
        the reader thread does it)."""
        bus = self._bus
        if self.clock.real_time or bus is None:
            return
        with self._poll_lock:
            while (msg := bus.recv(timeout=0)) is not None:
                self._handle(msg)
            now = self.clock.monotonic()
            self._check_age(now)
            self.cache.roll_rates(now)

    def _reading(self) -> bool:
        if not self.clock.real_time:
            return self._bus is not None
        return self._thread is not None and self._thread.is_alive()

    @property
    def stale_error(self) -> FeedbackStaleError | None:
        """The watchdog's error once tripped (it stays tripped until ``rearm``)."""
        self.poll()
        return self._stale

    @property
    def bus_error(self) -> CanBusError | None:
        """Bus-off, once the controller reported it (it stays until ``rearm``)."""
        self.poll()
        return self._bus_error

    def raise_if_unhealthy(self) -> None:
        """Raise if the reader died, the bus went off, or the watchdog tripped (or trips now)."""
        if not self._reading():
            raise FeedbackStaleError(f"the CAN reader for {self.where} is not running; reconnect")
        self.poll()
        if self._bus_error is not None:
            raise self._bus_error
        if self.clock.real_time and self.watchdog.armed and self._stale is None:
            # Frames may be queued for a reader that merely waits for the GIL: give it up to one
            # timeout to drain them before judging.
            clock = self.clock
            deadline = clock.monotonic() + min(self.watchdog.timeouts.values())
            while self.watchdog.overdue(clock.monotonic()) and clock.monotonic() < deadline:
                clock.sleep(_POLL_S / 4)
            self._check_age(clock.monotonic())
        if self._stale is not None:
            raise self._stale

    def caught_up(self, timeout_s: float) -> bool:
        """Wait until every frame received before this call has been handled (the reader found its queue empty
        after the call began), at most ``timeout_s``; on a simulated clock, read them now. A reader waiting
        for the GIL (a busy caller holds it for up to the 5 ms switch interval) is given it here."""
        if not self.clock.real_time:
            self.poll()
            return True
        start = self._drains
        deadline = self.clock.monotonic() + timeout_s
        while self._drains == start:
            if self.clock.monotonic() >= deadline or not self._reading():
                return False
            self.clock.sleep(_POLL_S / 8)
        return True

    def wait_for(self, predicate: Callable[[ArmState], bool], timeout_s: float) -> bool:
        """Poll the state until ``predicate`` holds; False on timeout."""
        return self._wait(lambda: predicate(self.state()), timeout_s)

    def sleep(self, seconds: float) -> None:
        """Wait on the link's clock, then read what arrived meanwhile."""
        self.clock.sleep(seconds)
        self.poll()

    def _wait(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        deadline = self.clock.monotonic() + timeout_s
        while True:
            self.poll()
            if condition():
                return True
            if self.clock.monotonic() >= deadline:
                return False
            self.clock.sleep(_POLL_S)

    # ---------------------------------------------------------------------------- reader thread
    def _check_age(self, now: float) -> None:
        overdue = self.watchdog.overdue(now)
        if overdue and self._stale is None:
            frame_id, age = max(overdue, key=lambda item: item[1] - self.watchdog.timeouts[item[0]])
            self.stale_at = now
            self._stale = FeedbackStaleError(
                f"stale feedback: no {self.watch_name} 0x{frame_id:X} from the PiPER on {self.where} for "
                f"{age * 1e3:.0f} ms (limit {self.watchdog.timeouts[frame_id] * 1e3:.0f} ms); commands stopped"
            )
            log.error("%s", self._stale)

    def _read_loop(self) -> None:
        bus = self._bus
        if bus is None:
            return
        while not self._stop.is_set():
            wait = _IDLE_WAIT_S
            deadline = self.watchdog.next_deadline()
            if deadline is not None and self._stale is None:
                wait = min(max(deadline - self.clock.monotonic(), 5e-4), wait)
            try:
                msg = bus.recv(timeout=wait)
                while True:  # drain everything queued before judging the age
                    if msg is not None:
                        self._handle(msg)
                    now = self.clock.monotonic()
                    msg = bus.recv(timeout=0)
                    if msg is None:
                        break
            except Exception as exc:  # the bus went away under us
                if self._stale is None:
                    self.stale_at = self.clock.monotonic()
                    self._stale = FeedbackStaleError(f"reading the CAN bus {self.where} failed: {exc}")
                    log.error("%s", self._stale)
                return
            # The queue was empty at ``now``: nothing that arrived before ``now`` is still unread.
            self._drains += 1
            self._check_age(now)
            self.cache.roll_rates(now)

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        frame_id = msg.arbitration_id
        if msg.is_remote_frame or msg.is_extended_id or frame_id not in _KEPT_IDS:
            return
        if len(msg.data) != DLC:
            self.bad_frames += 1
            return
        arrived = self.arrival(msg.timestamp)
        data = bytes(msg.data)
        if frame_id in OBSERVED_CONTROL_IDS and self._echoes.is_echo(frame_id, data, arrived):
            return
        self.cache.update(frame_id, data, arrived)
        self._heard.add(frame_id)
        self.watchdog.seen(frame_id, arrived)

    def arrival(self, wall_stamp: float) -> float:
        """A frame's wall-clock receive stamp on the monotonic clock: re-based by the offset between the two
        clocks now, or now itself when that lands in the future or ``_PLAUSIBLE_CLOCK_SKEW_S`` in the past."""
        now = self.clock.monotonic()
        arrived = wall_stamp + (now - self.clock.time())
        return arrived if now - _PLAUSIBLE_CLOCK_SKEW_S < arrived <= now else now

    def _on_error_frame(self, msg: can.Message) -> None:
        classes = [name for bit, name in CAN_ERR_CLASSES.items() if msg.arbitration_id & bit] or ["unknown"]
        for bit, name in CAN_ERR_CLASSES.items():
            if msg.arbitration_id & bit and not self.error_frames[name]:
                (log.error if bit in _SERIOUS_ERRORS else log.warning)(
                    "PiPER on %s: CAN error frame: %s (data %s)", self.where, name, bytes(msg.data).hex(" ")
                )
        self.error_frames.update(classes)
        if msg.arbitration_id & CAN_ERR_BUSOFF and self._bus_error is None:
            self._bus_error = CanBusError(
                f"CAN bus-off on {self.where}: the adapter stopped talking to the arm; check the wiring, the "
                f"120 ohm termination and the bitrate ({self.bitrate}), restart the interface "
                f"(e.g. sudo ip link set {self.channel} down; sudo ip link set {self.channel} up type can "
                f"bitrate {self.bitrate} restart-ms 100), then re-arm or reconnect"
            )
            log.error("%s", self._bus_error)
