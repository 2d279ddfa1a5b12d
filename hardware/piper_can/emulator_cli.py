"""``piper-emulator``: run the simulated PiPER firmware as its own process on a python-can bus.

Example (another process then connects as it would to ``can0``)::

    piper-emulator --interface=udp_multicast --channel=239.74.0.1 --port=43113

With ``--physics`` (the ``twin`` extra: ``mujoco``, ``piper-control``) the firmware drives ``piper_twin``'s
MuJoCo arm in the scene ``--scene`` placed from ``--scene-seed``, publishes the world state for the
``piper_twin`` cameras on ``--state-group``/``--state-port``, and places the objects anew for the seed a
``piper_twin.state_channel.request_placement`` asks for (on ``--state-port`` + 1).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from collections.abc import Callable
from typing import NoReturn

from .emulator import PiperEmulator
from .errors import PiperError
from .firmware import EmulatorConfig, Plant
from .link import open_bus

PROG = "piper-emulator"


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad input as one line (no usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):  # NaN passes every `value <= 0` check
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _pose(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated angles in radians, got {text!r}") from None
    if len(values) != 6:
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated angles in radians, got {len(values)}")
    if not all(map(math.isfinite, values)):
        raise argparse.ArgumentTypeError(f"the angles must be finite numbers, got {text!r}")
    return values


def _positive(text: str) -> float:
    value = _finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def _non_negative(text: str) -> float:
    value = _finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
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
    p.add_argument("--enable-latency-ms", type=_non_negative, default=20.0)
    p.add_argument("--start-enabled", action="store_true", help="start enabled in CAN mode (hardware link)")
    p.add_argument("--disabled-behaviour", choices=("hold", "drop"), default="hold")
    p.add_argument("--limit-policy", choices=("clamp", "reject"), default="clamp")
    p.add_argument("--initial-pose", type=_pose, help="6 comma-separated joint angles in radians")
    p.add_argument("--duration", type=_positive, help="exit after this many seconds (default: until signalled)")
    p.add_argument("--strict", action="store_true", help="log every ignored or rejected frame")
    p.add_argument("--physics", action="store_true", help="drive the MuJoCo twin (needs the 'twin' extra)")
    p.add_argument("--scene", default="table", help="twin scene: table, press_button, cube_in_bowl")
    p.add_argument("--scene-seed", type=int, default=0, help="seed of the twin scene's object placement")
    p.add_argument("--state-group", default="239.74.1.1", help="multicast group of the twin's world state")
    p.add_argument("--state-port", type=int, default=43200, help="UDP port of the twin's world state")
    return p


def _twin(args: argparse.Namespace) -> tuple[Plant, Callable[[], None]]:
    """The physics plant for ``--physics``, publishing its world state and placing objects on request; and
    how to close it."""
    # Imported here: the twin's dependencies are an optional extra.
    from piper_twin.plant import TwinPlant
    from piper_twin.state_channel import PlacementRequests, StatePublisher

    plant = TwinPlant(args.scene, args.scene_seed, args.initial_pose)
    publisher = StatePublisher(args.state_group, args.state_port)
    requests = PlacementRequests(args.state_group, args.state_port)

    def after_step(twin: TwinPlant) -> None:
        if (seed := requests.poll()) is not None:
            twin.place(seed)
        publisher.publish(twin.snapshot())

    plant.listeners.append(after_step)

    def close() -> None:
        publisher.close()
        requests.close()

    return plant, close


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
    plant: Plant | None = None
    close_plant: Callable[[], None] = lambda: None  # noqa: E731
    if args.physics:
        try:
            plant, close_plant = _twin(args)
        except (ImportError, ValueError) as exc:
            print(f"{PROG}: error: --physics: {exc}", file=sys.stderr)
            return 2
    options = {} if args.port is None else {"port": args.port}
    try:
        bus = open_bus(args.interface, args.channel, args.bitrate, options)
    except PiperError as exc:
        close_plant()
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    emulator = PiperEmulator(bus, config, plant=plant)
    emulator.start()
    port = f" port {args.port}" if args.port is not None else ""
    twin = f" (physics: scene {args.scene}, seed {args.scene_seed})" if args.physics else ""
    print(f"{PROG}: {args.role} ready on {args.interface}:{args.channel}{port}{twin}", flush=True)
    try:
        done.wait(args.duration)
    finally:
        emulator.stop()
        bus.shutdown()
        close_plant()
    return 0


if __name__ == "__main__":
    sys.exit(main())
