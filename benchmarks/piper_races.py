"""The PiPER driver's races in real time (issue 34): count the frames that reach an arm that must not move.

Each trial runs the real ``PiperDriver`` (its reader thread, the wall clock) against the simulated firmware
on its real-time thread, on a python-can ``virtual`` bus, with a commander thread sending a pose at
~200 Hz. The firmware's true state is recorded before every frame it acts on. Races:

* ``reset``: ``reset()`` lands at a random moment of the command stream. Violation: any motion frame
  (0x151, 0x155..0x157, 0x159) reaching the firmware while its delayed motor-off is pending, acted on or
  not (our reset is latched under the send lock: nothing of ours may follow it).
* ``resume``: the driver is e-stopped; ``resume()`` runs while another thread calls ``emergency_stop()``
  at a random moment after the resume began (during or after it; a gate on the resume's first look at
  the state marks its start). Violations: a motion frame (0x151, 0x155..0x157, 0x159) acted on while
  the firmware is e-stopped; the trial ending with the driver or the firmware not e-stopped (the
  e-stop was requested last, so it must win).
* ``estop``: ``emergency_stop()`` lands at a random moment of the command stream. Violation: a motion
  frame acted on while the firmware is e-stopped.
* ``foreign``: another host's reset (0x150 02) lands at a random moment of the command stream; the
  driver's reader must see it before the next command's frames. Frames of ours sent before our reader
  had handled the foreign frame still reach the firmware with its motor-off pending: that cannot be
  helped, so the violation is what moves the arm then: a 0x151 acted on (it puts the firmware back into
  CAN command mode) or a joint frame the firmware accepts (only in CAN command mode). Joint frames it
  ignores in standby, and gripper frames it takes in standby (the gripper accepts targets there, as the
  vendor's gripper demo relies on), are counted and reported, not hidden.

To keep a trial short the firmware switches the motors off 0.1 s after a reset instead of the real
arm's 0.73 s (the driver waits for the enable bits to clear, not for a fixed time). No torch. Run:
    ./run.sh python benchmarks/piper_races.py [--reset 150] [--resume 150] [--estop 100] [--foreign 100]
        [--seed 0]
"""

from __future__ import annotations

import argparse
import logging
import random
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import can
from piper_can.codec import ID_GRIPPER_COMMAND, ID_JOINT_COMMAND, ID_MODE_CONTROL, CtrlMode, Frame
from piper_can.driver import DriverConfig, PiperDriver
from piper_can.emulator import PiperEmulator
from piper_can.errors import PiperError
from piper_can.firmware import EmulatorConfig
from piper_can.state import ArmState

MOTION = (ID_MODE_CONTROL, *ID_JOINT_COMMAND, ID_GRIPPER_COMMAND)
POSES = ((0.3, 0.8, -0.6, 0.2, 0.1, -0.2), (0.35, 0.85, -0.65, 0.25, 0.15, -0.15))
COMMAND_PERIOD_S = 0.005


@dataclass(frozen=True, slots=True)
class Seen:
    """One frame the firmware handled: its ID, the firmware's state before it (motor-off pending,
    e-stopped), whether it acted on it (no ignore counted) and its control mode afterwards."""

    frame_id: int
    pending: bool
    estopped: bool
    acted: bool
    ctrl_mode_after: int

    @property
    def moves(self) -> bool:
        """Acted on as motion by a firmware whose motor-off is pending: a 0x151 that put it back into CAN
        command mode, or a joint frame accepted (which it does only in CAN command mode)."""
        if not (self.pending and self.acted):
            return False
        if self.frame_id == ID_MODE_CONTROL:
            return self.ctrl_mode_after == CtrlMode.CAN
        return self.frame_id in ID_JOINT_COMMAND


@dataclass
class Witness:
    """Every frame the firmware handled, with its state around it."""

    seen: list[Seen] = field(default_factory=list)

    def take(self) -> list[Seen]:
        seen, self.seen = self.seen, []
        return seen


@dataclass
class Counts:
    """One trial's (or one race's) violations, and the frames reported beside them."""

    violations: int = 0
    ignored: int = 0  # motion frames the firmware ignored while its motor-off was pending
    gripper: int = 0  # gripper frames it took while its motor-off was pending

    def add(self, other: Counts) -> None:
        self.violations += other.violations
        self.ignored += other.ignored
        self.gripper += other.gripper


def in_the_countdown(seen: list[Seen], violations: int) -> Counts:
    """``violations``, plus what else reached the firmware while its motor-off was pending."""
    pending = [s for s in seen if s.pending and s.frame_id in MOTION]
    ignored = sum(not s.acted for s in pending)
    gripper = sum(s.acted and s.frame_id == ID_GRIPPER_COMMAND for s in pending)
    return Counts(violations, ignored, gripper)


@dataclass
class Arm:
    emulator: PiperEmulator
    driver: PiperDriver
    witness: Witness
    other: can.BusABC


@contextmanager
def arm() -> Iterator[Arm]:
    """A real-time emulated arm (motor-off 0.1 s after a reset) and a connected, enabled driver."""
    channel = f"piper-races-{uuid.uuid4().hex[:12]}"
    bus = can.Bus(interface="virtual", channel=channel)
    emulator = PiperEmulator(bus, EmulatorConfig(profile="light", reset_motor_off_delay_s=0.1))
    witness = Witness()
    handle = emulator.firmware.handle

    def witnessed(frame: Frame, extended_id: bool = False) -> list[Frame]:
        firmware = emulator.firmware  # called under the emulator's lock
        pending, estopped, ignored = firmware.motor_off_pending, firmware.estopped, firmware.ignored.total()
        replies = handle(frame, extended_id)
        acted = firmware.ignored.total() == ignored
        witness.seen.append(Seen(frame.arbitration_id, pending, estopped, acted, firmware.ctrl_mode))
        return replies

    emulator.firmware.handle = witnessed  # type: ignore[method-assign]
    emulator.start()
    other = can.Bus(interface="virtual", channel=channel)  # another host on the same bus
    # A Python emulator on a loaded 2-core machine: 300 ms of feedback jitter, as the CLI tests allow.
    driver = PiperDriver(DriverConfig(interface="virtual", channel=channel, feedback_timeout_s=0.3))
    try:
        driver.connect()
        driver.enable()
        yield Arm(emulator, driver, witness, other)
    finally:
        driver.close()
        emulator.stop()
        other.shutdown()
        bus.shutdown()


class Commander:
    """A thread that commands a pose every ~5 ms until stopped, ignoring refusals."""

    def __init__(self, driver: PiperDriver) -> None:
        self.driver = driver
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        i = 0
        while not self._stop.is_set():
            i += 1
            try:
                self.driver.command(POSES[i % 2 if i % 40 < 20 else 0], 0.02)
                self.sent += 1
            except PiperError:
                pass
            time.sleep(COMMAND_PERIOD_S)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def race_reset(rig: Arm, rng: random.Random) -> Counts:
    commander = Commander(rig.driver)
    time.sleep(rng.uniform(0.01, 0.05))
    rig.driver.reset()
    time.sleep(0.15)  # past the motor-off, the commander still trying
    commander.stop()
    seen = rig.witness.take()
    rig.driver.enable()
    return in_the_countdown(seen, sum(s.pending and s.frame_id in MOTION for s in seen))


def race_resume(rig: Arm, rng: random.Random) -> Counts:
    driver = rig.driver
    if not driver.estopped:
        driver.emergency_stop()
    time.sleep(0.02)
    rig.witness.take()
    commander = Commander(driver)
    began = threading.Event()
    resumer, state = threading.current_thread(), driver.link.state

    def noting_state() -> ArmState:  # resume()'s first look at the state: it has begun
        if threading.current_thread() is resumer:
            began.set()
        return state()

    def stop_later() -> None:
        began.wait()
        time.sleep(rng.uniform(0.0, 0.3))
        driver.emergency_stop()

    stopper = threading.Thread(target=stop_later)
    driver.link.state = noting_state  # type: ignore[method-assign]
    stopper.start()
    try:
        driver.resume()
    except PiperError:
        pass  # aborted by the e-stop (or a refusal it caused): what must happen
    finally:
        began.set()
        stopper.join()
        driver.link.state = state  # type: ignore[method-assign]
    # The e-stop frame is on the bus: give a stalled emulator thread time to act on it before judging.
    deadline = time.monotonic() + 2.0
    while not rig.emulator.firmware.estopped and time.monotonic() < deadline:
        time.sleep(0.01)
    commander.stop()
    seen = rig.witness.take()
    violations = sum(s.estopped and s.frame_id in MOTION for s in seen)
    return Counts(violations + (not driver.estopped) + (not rig.emulator.firmware.estopped))


def race_estop(rig: Arm, rng: random.Random) -> Counts:
    driver = rig.driver
    commander = Commander(driver)
    time.sleep(rng.uniform(0.01, 0.05))
    driver.emergency_stop()
    time.sleep(0.05)
    commander.stop()
    seen = rig.witness.take()
    driver.resume()
    return Counts(sum(s.estopped and s.frame_id in MOTION for s in seen))


def race_foreign(rig: Arm, rng: random.Random) -> Counts:
    commander = Commander(rig.driver)
    time.sleep(rng.uniform(0.01, 0.05))
    rig.other.send(can.Message(arbitration_id=0x150, data=bytes([0x02]).ljust(8, b"\0"), is_extended_id=False))
    time.sleep(0.15)
    commander.stop()
    seen = rig.witness.take()
    rig.driver.enable()
    return in_the_countdown(seen, sum(s.moves for s in seen))


def restart(rig: Arm, attempts: int = 10) -> None:
    """Reconnect and recover the driver after a trial the machine's load broke."""
    for attempt in range(attempts):
        rig.driver.close()
        try:
            rig.driver.connect()
            rig.driver.recover("reset")
            break
        except PiperError:
            if attempt == attempts - 1:
                raise
            time.sleep(0.2)
    rig.witness.take()


RACES = {"reset": race_reset, "resume": race_resume, "estop": race_estop, "foreign": race_foreign}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name, default in (("reset", 150), ("resume", 150), ("estop", 100), ("foreign", 100)):
        parser.add_argument(f"--{name}", type=int, default=default, help=f"trials of the {name} race")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(name)s: %(message)s")  # not every reset's warning
    rng = random.Random(args.seed)
    total = 0
    for name, race in RACES.items():
        trials = getattr(args, name)
        if trials <= 0:
            continue
        started = time.monotonic()
        counts, in_trials = Counts(), Counts()
        failed = 0
        with arm() as rig:
            for _ in range(trials):
                try:
                    found = race(rig, rng)
                except PiperError as exc:  # a trial the loaded machine broke (e.g. a stale-feedback trip)
                    failed += 1
                    print(f"  {name}: trial not judged: {exc}", file=sys.stderr)
                    restart(rig)
                    continue
                counts.add(found)
                in_trials.add(Counts(found.violations > 0, found.ignored > 0, found.gripper > 0))
        total += counts.violations
        reported = ""
        if name in ("reset", "foreign"):
            reported = (
                f"; during motor-off countdowns: {counts.ignored} motion frames ignored (in {in_trials.ignored} "
                f"trials), {counts.gripper} gripper frames taken (in {in_trials.gripper} trials)"
            )
        print(
            f"{name}: {trials} trials, {counts.violations} violations in {in_trials.violations} trials, {failed} not "
            f"judged, {time.monotonic() - started:.1f} s{reported}",
            flush=True,
        )
    print(f"total violations: {total}")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
