"""``piper-emulator``: run the simulated PiPER firmware as its own process on a python-can bus.

Example (another process then connects as it would to ``can0``)::

    piper-emulator --interface=udp_multicast --channel=239.74.0.1 --port=43113
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import NoReturn

from .emulator import PiperEmulator
from .errors import PiperError
from .firmware import EmulatorConfig
from .link import open_bus

PROG = "piper-emulator"


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad input as one line (no usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _pose(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated angles in radians, got {text!r}") from None
    if len(values) != 6:
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated angles in radians, got {len(values)}")
    return values


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Simulated AgileX PiPER firmware on a python-can bus.")
    p.add_argument("--interface", required=True, help="python-can interface, e.g. udp_multicast or virtual")
    p.add_argument("--channel", required=True, help="python-can channel, e.g. 239.74.0.1 for udp_multicast")
    p.add_argument("--port", type=int, help="UDP port for udp_multicast (python-can default 43113)")
    p.add_argument("--bitrate", type=int, default=1_000_000)
    p.add_argument("--role", choices=("follower", "leader"), default="follower")
    p.add_argument("--profile", choices=("full", "light"), default="full", help="light: joints, status, 0x26x")
    p.add_argument("--rate-scale", type=_positive, default=1.0, help="wall-clock speed-up of the 200 Hz cycle")
    p.add_argument("--enable-latency-ms", type=float, default=20.0)
    p.add_argument("--start-enabled", action="store_true", help="start enabled in CAN mode (hardware link)")
    p.add_argument("--disabled-behaviour", choices=("hold", "drop"), default="hold")
    p.add_argument("--limit-policy", choices=("clamp", "reject"), default="clamp")
    p.add_argument("--initial-pose", type=_pose, help="6 comma-separated joint angles in radians")
    p.add_argument("--duration", type=_positive, help="exit after this many seconds (default: until signalled)")
    p.add_argument("--strict", action="store_true", help="log every ignored or rejected frame")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    config = EmulatorConfig(
        role=args.role,
        profile=args.profile,
        rate_scale=args.rate_scale,
        enable_latency_s=args.enable_latency_ms / 1000,
        start_enabled=args.start_enabled,
        disabled_behaviour=args.disabled_behaviour,
        limit_policy=args.limit_policy,
        initial_pose_rad=args.initial_pose,
        strict=args.strict,
    )
    options = {} if args.port is None else {"port": args.port}
    try:
        bus = open_bus(args.interface, args.channel, args.bitrate, options)
    except PiperError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    emulator = PiperEmulator(bus, config)
    emulator.start()
    port = f" port {args.port}" if args.port is not None else ""
    print(f"{PROG}: {args.role} ready on {args.interface}:{args.channel}{port}", flush=True)
    try:
        done.wait(args.duration)
    finally:
        emulator.stop()
        bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
