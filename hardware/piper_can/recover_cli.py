"""``piper-recover``: report a PiPER's faults and bring it back, as explicit, logged operations.

    piper-recover --channel=can0                  # report: faults, modes, enable bits (sends only queries)
    piper-recover --channel=can0 --clear-errors   # 0x475 / 0x159 clear-error codes; motors untouched
    piper-recover --channel=can0 --reset          # 0x150 reset, wait out the motor-off, re-enable (position mode)

After ``--reset`` the arm is enabled and holds where it is. Support a raised arm first: between the
firmware's motor-off and the re-enable it drops a little.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import NoReturn

from .codec import CtrlMode, MoveMode
from .driver import PiperDriver
from .errors import PiperError
from .settings import DriverConfig
from .state import ArmState

PROG = "piper-recover"


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad input as one line (no usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Report and recover faults of an AgileX PiPER over CAN.")
    p.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    p.add_argument("--channel", default="can0", help="python-can channel (default can0)")
    p.add_argument("--port", type=int, help="UDP port for udp_multicast")
    p.add_argument("--bitrate", type=int, default=1_000_000)
    action = p.add_mutually_exclusive_group()
    action.add_argument("--clear-errors", action="store_true", help="clear the joints' and gripper's error codes")
    action.add_argument("--reset", action="store_true", help="reset the firmware, then re-enable (arm drops briefly)")
    p.add_argument("--feedback-timeout-s", type=float, default=DriverConfig.feedback_timeout_s)
    return p


def describe(state: ArmState) -> str:
    """One line: faults, control and move mode, and which motors are enabled."""
    faults = "; ".join(map(str, state.faults())) or "none"
    mode = "unknown"
    if state.status is not None:
        status = state.status.value
        mode = f"{_name(CtrlMode, status.ctrl_mode)}/{_name(MoveMode, status.mode_feed)}"
    enabled = "".join("1" if on else "0" for on in state.joints_enabled) + ("1" if state.gripper_enabled else "0")
    return f"faults: {faults}; mode {mode}; enabled joints 1-6 + gripper: {enabled}"


def _name(kind: type[CtrlMode] | type[MoveMode], value: int) -> str:
    try:
        return kind(value).name
    except ValueError:
        return f"0x{value:02X}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format=f"{PROG}: %(message)s")
    try:
        config = DriverConfig(
            interface=args.interface,
            channel=args.channel,
            bitrate=args.bitrate,
            bus_options={} if args.port is None else {"port": args.port},
            feedback_timeout_s=args.feedback_timeout_s,
        )
    except ValueError as exc:  # a setting out of range, as the driver checks it
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    driver = PiperDriver(config)
    try:
        driver.connect()
        print(f"{PROG}: {driver.link.where} before: {describe(driver.state())}", flush=True)
        if args.clear_errors:
            driver.clear_errors()
        elif args.reset:
            driver.recover("reset")
        if args.clear_errors or args.reset:
            print(f"{PROG}: {driver.link.where} after: {describe(driver.state())}", flush=True)
            driver.checked_state()  # raises if a fault is left
    except PiperError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    finally:
        driver.close()  # hold: the arm is left as it is now
    return 0


if __name__ == "__main__":
    sys.exit(main())
