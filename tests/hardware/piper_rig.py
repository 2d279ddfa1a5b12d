"""Helpers for the PiPER tests: unique virtual channels, an emulated arm + driver rig, a bus monitor.

By default the rig runs on a ``SimulatedClock``: the emulated firmware steps every 5 ms of simulated
time, the driver reads the bus when it asks for the state, and every frame carries its simulated
send time; one thread, exact times, no sleeps. ``real_time=True`` runs the emulator on its thread
and the driver's reader thread on the wall clock (for the tests about threads and starvation).
"""

from __future__ import annotations

import gc
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field

import can
import pytest
from piper_can import codec
from piper_can.clock import SYSTEM_CLOCK, Clock, SimulatedClock
from piper_can.driver import PiperDriver
from piper_can.emulator import PiperEmulator
from piper_can.errors import FeedbackStaleError
from piper_can.firmware import EmulatorConfig, PiperFirmware, Plant
from piper_can.settings import DriverConfig


def unique_virtual_channel() -> str:
    return f"piper-test-{uuid.uuid4().hex[:12]}"


@dataclass
class Rig:
    """An emulated arm and a driver on one virtual channel, plus a passive monitor of every frame."""

    channel: str
    emulator: PiperEmulator
    driver: PiperDriver
    monitor: can.BusABC
    clock: Clock
    buses: list[can.BusABC] = field(default_factory=list)

    @property
    def arm(self) -> PiperFirmware:
        """The emulated firmware (its ground truth); change it inside ``emulator.locked()`` while it runs."""
        return self.emulator.firmware

    def drain(self, timeout: float = 0.0) -> list[can.Message]:
        """Every frame the monitor has seen since the last drain."""
        frames = []
        while (msg := self.monitor.recv(timeout=timeout)) is not None:
            frames.append(msg)
        return frames

    def now(self) -> float:
        return self.clock.time()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass (simulated: the arm steps; the driver reads what arrived)."""
        self.clock.sleep(seconds)
        if self.driver.is_connected:
            self.driver.link.poll()

    def until(self, condition, timeout: float = 2.0, period: float = 0.001) -> bool:
        """Let time pass in ``period`` steps until ``condition()`` holds; False after ``timeout``."""
        deadline = self.clock.monotonic() + timeout
        while self.clock.monotonic() < deadline:
            if condition():
                return True
            self.sleep(period)
        return condition()


@contextmanager
def make_rig(
    emulator_config: EmulatorConfig | None = None,
    connect: bool = True,
    enable: bool = True,
    real_time: bool = False,
    plant: Plant | None = None,
    **driver_options,
) -> Iterator[Rig]:
    channel = unique_virtual_channel()
    clock: Clock = SYSTEM_CLOCK if real_time else SimulatedClock()
    bus_options = {} if real_time else {"preserve_timestamps": True}  # frames keep their simulated times
    emulator_bus = can.Bus(interface="virtual", channel=channel, **bus_options)
    monitor = can.Bus(interface="virtual", channel=channel, **bus_options)
    emulator = PiperEmulator(emulator_bus, emulator_config, clock, plant)
    if real_time:
        emulator.start()
        # The emulator shares this process (and the GIL) with the driver and the test, so a busy machine
        # can delay its 200 Hz loop: the real-time tests allow 100 ms instead of the 15 ms default.
        driver_options.setdefault("feedback_timeout_s", 0.1)
    else:
        clock.every(emulator.firmware.config.period_s, emulator.step)
    config = DriverConfig(interface="virtual", channel=channel, bus_options=bus_options, **driver_options)
    driver = PiperDriver(config, clock)
    rig = Rig(channel, emulator, driver, monitor, clock, [emulator_bus, monitor])
    with gc_paused() if real_time else nullcontext():
        try:
            if connect:
                driver.connect()
                if enable:
                    driver.enable()
            yield rig
        finally:
            driver.close()
            emulator.stop()
            for bus in rig.buses:
                bus.shutdown()


@contextmanager
def gc_paused() -> Iterator[None]:
    """No garbage collection in the block. A full collection stops every thread of this (torch-sized) test
    process for up to a few hundred ms, an emulated arm's real-time loop included, which the watchdog would
    rightly call stale feedback; a real arm keeps talking through our GC pauses."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def wait_until(condition, timeout: float = 2.0, period: float = 0.002) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(period)
    return condition()


MOTION_IDS = (0x151, *codec.ID_JOINT_COMMAND, 0x159)  # frames that select a mode or move the arm


def stale_after(rig: Rig, target, message: str, period_s: float = 0.01) -> float:
    """Freeze the feedback (frames keep coming, nothing in them changes), command ``target`` every ``period_s``;
    the time until the driver refuses with ``message`` in its error, having sent no motion frame since."""
    with rig.emulator.locked() as arm:
        arm.freeze_feedback()
    frozen_at = rig.now()
    for _ in range(int(1.0 / period_s)):
        try:
            rig.driver.command(target)
        except FeedbackStaleError as exc:
            assert message in str(exc)
            refused_at = rig.now()
            break
        rig.sleep(period_s)
    else:
        raise AssertionError("a frozen feed was commanded through for 1 s")
    rig.drain()
    with pytest.raises(FeedbackStaleError):
        rig.driver.command(target)
    assert [m for m in rig.drain() if m.arbitration_id in MOTION_IDS] == []
    return refused_at - frozen_at
