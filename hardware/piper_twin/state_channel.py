"""The twin's world state between processes: the emulator publishes it, cameras (and scene operators) read it.

Back the other way, on ``port + 1``: a request to place the scene's objects for another seed (what a person
does between demonstrations: put the cube back). It moves objects only, never the arm.

One UDP multicast datagram per publication on the loopback (as python-can's ``udp_multicast`` carries CAN):
the scene's name and seed, the simulated time, the host's wall-clock time it was taken at (the group never
leaves this host), whether the task has succeeded, and the MuJoCo state a renderer needs (``qpos``, mocap
poses). Every receiver on the group gets every datagram; a receiver keeps
only the newest. The CAN bus stays the arm's only control path: nothing here can move the arm.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass

import numpy as np

DEFAULT_GROUP = "239.74.1.1"
DEFAULT_PORT = 43200
_MAGIC = b"PTW1"
_HEADER = struct.Struct("<4s32sqqddBHH")  # magic, scene, seed, placement, time, wall time, success, nq, nmocap
_MAX_DATAGRAM = 65_000
_PLACE = struct.Struct("<4sq")  # magic, seed
_PLACE_MAGIC = b"PTP1"


@dataclass(frozen=True)
class TwinSnapshot:
    """The twin's state at ``time_s`` (simulated seconds since the emulator started), taken at
    ``wall_time_s`` (``time.time()``); ``placement`` counts the placements of the objects so far."""

    scene: str
    seed: int
    placement: int
    time_s: float
    wall_time_s: float
    success: bool
    qpos: np.ndarray
    mocap_pos: np.ndarray  # (nmocap, 3)
    mocap_quat: np.ndarray  # (nmocap, 4)

    def encode(self) -> bytes:
        name = self.scene.encode("ascii")
        if len(name) > 32:
            raise ValueError(f"scene name longer than 32 bytes: {self.scene!r}")
        nq, nmocap = len(self.qpos), len(self.mocap_pos)
        header = _HEADER.pack(
            _MAGIC, name, self.seed, self.placement, self.time_s, self.wall_time_s, self.success, nq, nmocap
        )
        arrays = np.concatenate([self.qpos, self.mocap_pos.ravel(), self.mocap_quat.ravel()]).astype("<f8")
        return header + arrays.tobytes()

    @classmethod
    def decode(cls, datagram: bytes) -> TwinSnapshot:
        magic, name, seed, placement, time_s, wall_time_s, success, nq, nmocap = _HEADER.unpack_from(datagram)
        if magic != _MAGIC:
            raise ValueError("not a PiPER twin state datagram")
        values = np.frombuffer(datagram, "<f8", offset=_HEADER.size)
        if len(values) != nq + 7 * nmocap:
            raise ValueError(f"truncated twin state datagram ({len(datagram)} bytes)")
        return cls(
            name.rstrip(b"\x00").decode("ascii"),
            seed,
            placement,
            time_s,
            wall_time_s,
            bool(success),
            values[:nq].copy(),
            values[nq : nq + 3 * nmocap].reshape(nmocap, 3).copy(),
            values[nq + 3 * nmocap :].reshape(nmocap, 4).copy(),
        )


def _sender() -> socket.socket:
    """A multicast sender that stays on this host (TTL 0, loopback)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    return sock


def _receiver(group: str, port: int) -> socket.socket:
    """A non-blocking member of ``group`` on ``port`` (every member gets every datagram)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((group, port))
    membership = socket.inet_aton(group) + socket.inet_aton("127.0.0.1")
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
    sock.setblocking(False)
    return sock


class StatePublisher:
    """Sends snapshots to the multicast group."""

    def __init__(self, group: str = DEFAULT_GROUP, port: int = DEFAULT_PORT) -> None:
        self.address = (group, port)
        self._sock = _sender()

    def publish(self, snapshot: TwinSnapshot) -> None:
        try:
            self._sock.sendto(snapshot.encode(), self.address)
        except OSError:
            pass  # a full socket buffer drops one snapshot; the next one carries the newer state

    def close(self) -> None:
        self._sock.close()


def request_placement(seed: int, group: str = DEFAULT_GROUP, port: int = DEFAULT_PORT) -> None:
    """Ask the twin on ``group``/``port`` to place its scene's objects for ``seed``."""
    sock = _sender()
    try:
        sock.sendto(_PLACE.pack(_PLACE_MAGIC, seed), (group, port + 1))
    finally:
        sock.close()


class PlacementRequests:
    """The twin's side of ``request_placement``: ``poll()`` returns the newest requested seed, if any."""

    def __init__(self, group: str = DEFAULT_GROUP, port: int = DEFAULT_PORT) -> None:
        self._sock = _receiver(group, port + 1)

    def poll(self) -> int | None:
        seed = None
        while True:
            try:
                datagram = self._sock.recv(_MAX_DATAGRAM)
            except BlockingIOError:
                return seed
            if len(datagram) == _PLACE.size and datagram[:4] == _PLACE_MAGIC:
                seed = _PLACE.unpack(datagram)[1]

    def close(self) -> None:
        self._sock.close()


class StateReceiver:
    """Joins the group; ``latest()`` drains what arrived and returns the newest snapshot seen so far."""

    def __init__(self, group: str = DEFAULT_GROUP, port: int = DEFAULT_PORT) -> None:
        self.address = (group, port)
        self._sock = _receiver(group, port)
        self._latest: TwinSnapshot | None = None

    def latest(self) -> TwinSnapshot | None:
        while True:
            try:
                datagram = self._sock.recv(_MAX_DATAGRAM)
            except BlockingIOError:
                return self._latest
            self._latest = TwinSnapshot.decode(datagram)

    def wait(self, timeout_s: float) -> TwinSnapshot | None:
        """The newest snapshot, waiting up to ``timeout_s`` for a first one."""
        deadline = time.monotonic() + timeout_s
        while (snapshot := self.latest()) is None and time.monotonic() < deadline:
            time.sleep(0.005)
        return snapshot

    def place(self, seed: int, timeout_s: float = 2.0) -> TwinSnapshot:
        """Have the twin place its objects for ``seed`` (an episode's initial state) and return its first
        state after it did; the request is repeated every 0.1 s until seen (a datagram can be lost), so
        the objects may be placed twice. ``TimeoutError`` when the twin does not answer."""
        deadline = time.monotonic() + timeout_s
        before = self.wait(timeout_s)
        while before is not None and time.monotonic() < deadline:
            request_placement(seed, *self.address)
            retry = min(time.monotonic() + 0.1, deadline)
            while time.monotonic() < retry:
                snapshot = self.latest()
                if snapshot is not None and snapshot.placement > before.placement and snapshot.seed == seed:
                    return snapshot
                time.sleep(0.005)
        raise TimeoutError(
            f"the twin on {self.address[0]}:{self.address[1]} did not place seed {seed} in {timeout_s} s"
        )

    def close(self) -> None:
        self._sock.close()
