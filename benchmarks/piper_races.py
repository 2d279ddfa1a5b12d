"""The PiPER driver's races in real time (issue 34): count the frames that reach an arm that must not move.

Each trial runs the real ``PiperDriver`` (its reader thread, the wall clock) against the simulated firmware
on its real-time thread, on a python-can ``virtual`` bus, with a commander thread sending a pose at
~200 Hz. The firmware's true state is recorded before every frame it acts on. Races:

* ``reset``: ``reset()`` lands at a random moment of the command stream. Violation: a mode or joint
  frame (0x151, 0x155..0x157) acted on while the firmware's delayed motor-off is pending.
* ``resume``: the driver is e-stopped; ``resume()`` runs while another thread calls ``emergency_stop()``
  at a random moment after the resume began (during or after it; a gate on the resume's first look at
  the state marks its start). Violations: a motion frame (0x151, 0x155..0x157, 0x159) acted on while
  the firmware is e-stopped; the trial ending with the driver or the firmware not e-stopped (the
  e-stop was requested last, so it must win).
* ``estop``: ``emergency_stop()`` lands at a random moment of the command stream. Violation: a motion
  frame acted on while the firmware is e-stopped.
* ``foreign``: another host's reset (0x150 02) lands at a random moment of the command stream; the
  driver's reader must see it before the next command's frames. Counted like ``reset``; frames sent
  before our reader had handled the foreign frame are the documented residual window (reported, not
  hidden).

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
from piper_can.codec import ID_JOINT_COMMAND, ID_MODE_CONTROL, Frame
from piper_can.driver import DriverConfig, PiperDriver
from piper_can.emulator import PiperEmulator
from piper_can.errors import PiperError
from piper_can.firmware import EmulatorConfig
from piper_can.state import ArmState

MODE_AND_JOINTS = (ID_MODE_CONTROL, *ID_JOINT_COMMAND)
MOTION = (*MODE_AND_JOINTS, 0x159)
POSES = ((0.3, 0.8, -0.6, 0.2, 0.1, -0.2), (0.35, 0.85, -0.65, 0.25, 0.15, -0.15))
COMMAND_PERIOD_S = 0.005


@dataclass
class Witness:
    """The firmware's state before each frame it acted on: (frame id, motor-off pending, e-stopped)."""

    seen: list[tuple[int, bool, bool]] = field(default_factory=list)

    def take(self) -> list[tuple[int, bool, bool]]:
        seen, self.seen = self.seen, []
        return seen


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
        witness.seen.append((frame.arbitration_id, firmware.motor_off_pending, firmware.estopped))
        return handle(frame, extended_id)

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


def race_reset(rig: Arm, rng: random.Random) -> int:
    commander = Commander(rig.driver)
    time.sleep(rng.uniform(0.01, 0.05))
    rig.driver.reset()
    time.sleep(0.15)  # past the motor-off, the commander still trying
    commander.stop()
    seen = rig.witness.take()
    rig.driver.enable()
    return sum(1 for frame_id, pending, _ in seen if pending and frame_id in MODE_AND_JOINTS)


def race_resume(rig: Arm, rng: random.Random) -> int:
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
    violations = sum(1 for frame_id, _, estopped in seen if estopped and frame_id in MOTION)
    return violations + (not driver.estopped) + (not rig.emulator.firmware.estopped)


def race_estop(rig: Arm, rng: random.Random) -> int:
    driver = rig.driver
    commander = Commander(driver)
    time.sleep(rng.uniform(0.01, 0.05))
    driver.emergency_stop()
    time.sleep(0.05)
    commander.stop()
    seen = rig.witness.take()
    driver.resume()
    return sum(1 for frame_id, _, estopped in seen if estopped and frame_id in MOTION)


def race_foreign(rig: Arm, rng: random.Random) -> int:
    commander = Commander(rig.driver)
    time.sleep(rng.uniform(0.01, 0.05))
    rig.other.send(can.Message(arbitration_id=0x150, data=bytes([0x02]).ljust(8, b"\0"), is_extended_id=False))
    time.sleep(0.15)
    commander.stop()
    seen = rig.witness.take()
    rig.driver.enable()
    return sum(1 for frame_id, pending, _ in seen if pending and frame_id in MODE_AND_JOINTS)


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
        violations = bad_trials = failed = 0
        with arm() as rig:
            for _ in range(trials):
                try:
                    found = race(rig, rng)
                    violations += found
                    bad_trials += found > 0
                except PiperError as exc:  # a trial the loaded machine broke (e.g. a stale-feedback trip)
                    failed += 1
                    print(f"  {name}: trial not judged: {exc}", file=sys.stderr)
                    restart(rig)
        total += violations
        print(
            f"{name}: {trials} trials, {violations} violations in {bad_trials} trials, {failed} not judged, "
            f"{time.monotonic() - started:.1f} s",
            flush=True,
        )
    print(f"total violations: {total}")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
