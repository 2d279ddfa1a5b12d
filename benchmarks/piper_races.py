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
* ``enable_foreign`` (issue 57): ``enable()`` on an enabled arm while another host's reset lands at a random
  moment up to 30 ms after it began (the handshake and the mode selection take ~20 ms when nothing
  interrupts them), then the commander runs for 0.15 s. Violations, counted by kind: a 0x151 acted on,
  or a joint frame accepted, in the reset's countdown (as ``foreign``); and ``enable()`` returning into a
  motor-off (the arm not enabled in CAN command mode 0.15 s after it returned), judged when the firmware
  handled the reset before the call returned (how often is printed; a later reset is the ``foreign`` race).
* ``resume_foreign`` (issue 57): the same against ``resume()`` from an e-stop, the foreign reset landing up
  to 200 ms after the resume began (our reset, its motor-off, the handshake, the mode).
* ``wall_step`` (issue 57): the wall clock the frames are stamped on steps back (``--wall-step-s``, 2 s; 0 is
  the control) at a random moment of the command stream, then joint 3 cuts out 0-20 ms later. Violation:
  a joint frame for joint 3 (0x156) the firmware handles more than ``CUT_OUT_GRACE_S`` after it first
  reported the cut-out (0x263 enable bit clear): the driver's reader must handle that report, and a
  command that passed its check just before it still goes out; the frames within the grace are reported.

To keep a trial short the firmware switches the motors off 0.1 s after a reset instead of the real
arm's 0.73 s (the driver waits for the enable bits to clear, not for a fixed time). No torch. Run:
    ./run.sh python benchmarks/piper_races.py [--reset 150] [--resume 150] [--estop 100] [--foreign 100]
        [--enable-foreign 0] [--resume-foreign 0] [--wall-step 0] [--wall-step-s -2] [--seed 0] [--out FILE.json]
``--out`` writes every race's counts, the machine's load and the seed as JSON (benchmarks/results/).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import sys
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import can
from piper_can.clock import SystemClock
from piper_can.codec import (
    ID_GRIPPER_COMMAND,
    ID_JOINT_COMMAND,
    ID_LOW_SPEED,
    ID_MODE_CONTROL,
    CtrlMode,
    Frame,
    decode_feedback,
)
from piper_can.driver import PiperDriver
from piper_can.emulator import PiperEmulator
from piper_can.errors import PiperError
from piper_can.firmware import EmulatorConfig
from piper_can.settings import DriverConfig
from piper_can.state import ArmState

MOTION = (ID_MODE_CONTROL, *ID_JOINT_COMMAND, ID_GRIPPER_COMMAND)
POSES = ((0.3, 0.8, -0.6, 0.2, 0.1, -0.2), (0.35, 0.85, -0.65, 0.25, 0.15, -0.15))
COMMAND_PERIOD_S = 0.005
MOTOR_OFF_S = 0.1  # the emulated firmware's delayed motor-off after a reset (a real arm: 0.73 s)
WALL_STEP_S = -2.0
CUT_OUT_JOINT = 3
# A joint frame for the cut-out joint handled this long after the firmware first reported it is a violation:
# the reader must handle the report (one feedback cycle) and a command past its check may still go (one period).
CUT_OUT_GRACE_S = 0.005 + COMMAND_PERIOD_S


@dataclass(frozen=True, slots=True)
class Seen:
    """One frame the firmware handled: its ID, the firmware's state before it (motor-off pending,
    e-stopped), whether it acted on it (no ignore counted) and its control mode afterwards."""

    frame_id: int
    pending: bool
    estopped: bool
    acted: bool
    ctrl_mode_after: int
    at: float  # time.monotonic() when the firmware handled it

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
    """Every frame the firmware handled, with its state around it, and when it first reported joint
    ``CUT_OUT_JOINT`` disabled (0x26x enable bit clear) since the last ``take``."""

    seen: list[Seen] = field(default_factory=list)
    cut_out_reported: float | None = None

    def take(self) -> list[Seen]:
        seen, self.seen = self.seen, []
        self.cut_out_reported = None
        return seen


class SteppingWallClock(SystemClock):
    """The system's clocks, with a wall clock (the one frames are stamped on) that ``step`` moves alone."""

    def __init__(self) -> None:
        self.offset = 0.0

    def time(self) -> float:
        return time.time() + self.offset

    def step(self, seconds: float) -> None:
        self.offset += seconds


@dataclass
class Counts:
    """One trial's (or one race's) violations, and the frames reported beside them."""

    violations: int = 0
    ignored: int = 0  # motion frames the firmware ignored while its motor-off was pending
    gripper: int = 0  # gripper frames it took while its motor-off was pending
    kinds: Counter[str] = field(default_factory=Counter)  # the violations by kind, where a race tells them apart

    def add(self, other: Counts) -> None:
        self.violations += other.violations
        self.ignored += other.ignored
        self.gripper += other.gripper
        self.kinds.update(other.kinds)


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
    landed_during: int = 0  # trials whose foreign reset reached the firmware before the raced call returned
    wall_step_s: float = WALL_STEP_S


@contextmanager
def arm(clock: SteppingWallClock | None = None) -> Iterator[Arm]:
    """A real-time emulated arm (motor-off 0.1 s after a reset) and a connected, enabled driver; with
    ``clock``, both stamp frames on its wall clock (as the kernel stamps them on CLOCK_REALTIME)."""
    channel = f"piper-races-{uuid.uuid4().hex[:12]}"
    options = {} if clock is None else {"preserve_timestamps": True}
    bus = can.Bus(interface="virtual", channel=channel, **options)
    emulator = PiperEmulator(
        bus, EmulatorConfig(profile="light", reset_motor_off_delay_s=MOTOR_OFF_S), clock or SystemClock()
    )
    witness = Witness()
    handle, tick = emulator.firmware.handle, emulator.firmware.tick
    cut_out_report = ID_LOW_SPEED[CUT_OUT_JOINT - 1]

    def witnessed(frame: Frame, extended_id: bool = False) -> list[Frame]:
        firmware = emulator.firmware  # called under the emulator's lock
        pending, estopped, ignored = firmware.motor_off_pending, firmware.estopped, firmware.ignored.total()
        replies = handle(frame, extended_id)
        acted = firmware.ignored.total() == ignored
        seen = Seen(frame.arbitration_id, pending, estopped, acted, firmware.ctrl_mode, time.monotonic())
        witness.seen.append(seen)
        return replies

    def ticked(dt: float) -> list[Frame]:
        frames = tick(dt)
        if witness.cut_out_reported is None:
            for frame in frames:
                if (
                    frame.arbitration_id == cut_out_report
                    and not decode_feedback(frame.arbitration_id, frame.data).enabled
                ):
                    witness.cut_out_reported = time.monotonic()
        return frames

    emulator.firmware.handle = witnessed  # type: ignore[method-assign]
    emulator.firmware.tick = ticked  # type: ignore[method-assign]
    emulator.start()
    other = can.Bus(interface="virtual", channel=channel, **options)  # another host on the same bus
    # A Python emulator on a loaded 2-core machine: 300 ms of feedback jitter, as the CLI tests allow.
    config = DriverConfig(interface="virtual", channel=channel, bus_options=options, feedback_timeout_s=0.3)
    driver = PiperDriver(config, clock or SystemClock())
    try:
        driver.connect()
        driver.enable()
        yield Arm(emulator, driver, witness, other)
    finally:
        driver.close()
        emulator.stop()
        other.shutdown()
        bus.shutdown()


def foreign_reset(rig: Arm) -> None:
    """Another host's reset (0x150 02), on the bus at once for every listener. python-can's ``virtual`` bus
    puts a frame in each listener's queue in turn, so a thread switch between two puts could let the firmware
    act on it, and answer, before our reader's queue has it; a real bus delivers a frame to every node at
    once (holding the emulator off while it is put everywhere models that)."""
    with rig.emulator.locked():
        rig.other.send(can.Message(arbitration_id=0x150, data=bytes([0x02]).ljust(8, b"\0"), is_extended_id=False))


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
    foreign_reset(rig)
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


def foreign_reset_during(rig: Arm, rng: random.Random, operation: Callable[[], None], window_s: float) -> Counts:
    """``operation`` while another host's reset lands ``0..window_s`` after it began, then 0.15 s of commands.
    Violations: motion acted on in the countdown; the operation returning into a motor-off (judged when the
    firmware handled the reset before the operation returned; a later one is the ``foreign`` race)."""
    rig.witness.take()
    began = threading.Event()

    def reset_later() -> None:
        began.wait()
        time.sleep(rng.uniform(0.0, window_s))
        foreign_reset(rig)

    other_host = threading.Thread(target=reset_later)
    other_host.start()
    began.set()
    try:
        operation()
        returned_at = time.monotonic()
    finally:
        other_host.join()
    commander = Commander(rig.driver)
    time.sleep(MOTOR_OFF_S + 0.05)  # past any countdown the operation may have returned into
    commander.stop()
    with rig.emulator.locked() as firmware:
        enabled = all(firmware.enabled) and firmware.ctrl_mode == CtrlMode.CAN
    seen = rig.witness.take()
    foreign_at = max(s.at for s in seen if s.frame_id == 0x150)  # the other host's (ours come before it)
    during = foreign_at < returned_at
    rig.landed_during += during
    if not enabled:
        rig.driver.enable()  # waits the reset out: the next trial starts enabled
    kinds = Counter(
        {
            "0x151 acted on in a countdown": sum(s.moves and s.frame_id == ID_MODE_CONTROL for s in seen),
            "joint frame accepted in a countdown": sum(s.moves and s.frame_id in ID_JOINT_COMMAND for s in seen),
            "returned into a motor-off": int(during and not enabled),
        }
    )
    counts = in_the_countdown(seen, kinds.total())
    counts.kinds = +kinds
    return counts


def race_enable_foreign(rig: Arm, rng: random.Random) -> Counts:
    return foreign_reset_during(rig, rng, rig.driver.enable, 0.03)


def race_resume_foreign(rig: Arm, rng: random.Random) -> Counts:
    rig.driver.emergency_stop()
    time.sleep(0.02)
    return foreign_reset_during(rig, rng, rig.driver.resume, 0.2)


def race_wall_step(rig: Arm, rng: random.Random) -> Counts:
    clock = rig.driver.clock
    assert isinstance(clock, SteppingWallClock)
    commander = Commander(rig.driver)
    time.sleep(rng.uniform(0.01, 0.05))
    rig.witness.take()
    clock.step(rig.wall_step_s)
    time.sleep(rng.uniform(0.0, 0.02))
    with rig.emulator.locked() as firmware:
        firmware.set_enabled(CUT_OUT_JOINT, False)
        cut_at = time.monotonic()
    time.sleep(0.2)
    commander.stop()
    reported = rig.witness.cut_out_reported
    seen = [s for s in rig.witness.take() if s.frame_id == ID_JOINT_COMMAND[(CUT_OUT_JOINT - 1) // 2]]
    with rig.emulator.locked() as firmware:
        firmware.set_enabled(CUT_OUT_JOINT, True)
    if reported is None:
        raise PiperError("the firmware never reported the cut-out (the emulator thread stalled)")
    late = [s.at - reported for s in seen if s.at > reported + CUT_OUT_GRACE_S]
    counts = Counts(len(late), ignored=sum(cut_at < s.at <= reported + CUT_OUT_GRACE_S for s in seen))
    if late:  # how long after the report the last one came: a starved reader, or a feedback cache frozen by the step
        counts.kinds[f"frame {max(late) * 1e3:.0f} ms after the report"] = len(late)
    return counts


RACES = {
    "reset": race_reset,
    "resume": race_resume,
    "estop": race_estop,
    "foreign": race_foreign,
    "enable_foreign": race_enable_foreign,
    "resume_foreign": race_resume_foreign,
    "wall_step": race_wall_step,
}
DEFAULT_TRIALS = {"reset": 150, "resume": 150, "estop": 100, "foreign": 100}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in RACES:
        default = DEFAULT_TRIALS.get(name, 0)
        parser.add_argument(f"--{name.replace('_', '-')}", type=int, default=default, help=f"trials of the {name} race")
    parser.add_argument(
        "--wall-step-s", type=float, default=WALL_STEP_S, help="the wall_step race's step (0: a control)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="write the counts as JSON to this file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(name)s: %(message)s")  # not every reset's warning
    rng = random.Random(args.seed)
    total = 0
    results: dict[str, dict[str, object]] = {}
    for name, race in RACES.items():
        trials = getattr(args, name)
        if trials <= 0:
            continue
        started = time.monotonic()
        load_before = os.getloadavg()[0]
        counts, in_trials = Counts(), Counts()
        failed = 0
        with arm(SteppingWallClock() if name == "wall_step" else None) as rig:
            rig.wall_step_s = args.wall_step_s
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
        seconds = time.monotonic() - started
        reported = ""
        if name in ("reset", "foreign", "enable_foreign", "resume_foreign"):
            reported = (
                f"; during motor-off countdowns: {counts.ignored} motion frames ignored (in {in_trials.ignored} "
                f"trials), {counts.gripper} gripper frames taken (in {in_trials.gripper} trials)"
            )
        if name in ("enable_foreign", "resume_foreign"):
            reported += f"; the reset reached the firmware before the call returned in {rig.landed_during} trials"
        if counts.kinds:
            reported += f"; violations by kind: {dict(counts.kinds)}"
        elif name == "wall_step":
            reported = (
                f"; {counts.ignored} frames to the cut-out joint within the grace (in {in_trials.ignored} trials)"
            )
        print(
            f"{name}: {trials} trials, {counts.violations} violations in {in_trials.violations} trials, {failed} not "
            f"judged, {seconds:.1f} s{reported}",
            flush=True,
        )
        results[name] = {
            "trials": trials,
            "violations": counts.violations,
            "violating_trials": in_trials.violations,
            "violations_by_kind": dict(counts.kinds),
            "not_judged": failed,
            "reported_frames": counts.ignored,
            "reported_trials": in_trials.ignored,
            "gripper_frames_in_countdowns": counts.gripper,
            "landed_during_call": rig.landed_during if name in ("enable_foreign", "resume_foreign") else None,
            "seconds": round(seconds, 1),
            "load_1min_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    print(f"total violations: {total}")
    if args.out:
        meta = {
            "seed": args.seed,
            "cpus": os.cpu_count(),
            "motor_off_s": MOTOR_OFF_S,
            "grace_s": CUT_OUT_GRACE_S,
            "wall_step_s": args.wall_step_s,
        }
        with open(args.out, "w") as out:
            command = " ".join(["benchmarks/piper_races.py", *(argv if argv is not None else sys.argv[1:])])
            stamp = {"command": command, "date": time.strftime("%Y-%m-%d", time.gmtime())}
            json.dump(stamp | {"meta": meta, "races": results, "total_violations": total}, out, indent=1)
            out.write("\n")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
