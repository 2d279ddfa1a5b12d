"""``piper-emulator`` as its own process, reached over udp_multicast like a real arm on can0."""

from __future__ import annotations

import subprocess

import pytest
from piper_can.driver import PiperDriver
from piper_can.emulator_process import BIN, start_emulator, unique_udp_channel
from piper_can.settings import DriverConfig
from piper_rig import wait_until


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--interface=udp_multicast"], 2, "piper-emulator: error: the following arguments are required: --channel"),
        (
            ["--interface=virtual", "--channel=x", "--rate-scale=-1"],
            2,
            "piper-emulator: error: argument --rate-scale: must be positive, got -1.0",
        ),
        (
            ["--interface=virtual", "--channel=x", "--initial-pose=1,2"],
            2,
            "piper-emulator: error: argument --initial-pose: expected 6 comma-separated angles in radians, got 2",
        ),
        (
            ["--interface=nosuch", "--channel=x"],
            1,
            "piper-emulator: error: cannot open CAN bus nosuch:x: "
            'CanInterfaceNotImplementedError: Unknown interface type "nosuch"',
        ),
    ],
)
def test_bad_input_is_one_error_line_and_a_non_zero_exit(args, code, message):
    out = subprocess.run([str(BIN / "piper-emulator"), *args], capture_output=True, text=True, timeout=60)
    assert out.returncode == code
    assert out.stderr.splitlines() == [message]
    assert out.stdout == ""


def test_driver_in_this_process_drives_the_emulator_process():
    group, port = unique_udp_channel()
    emulator = start_emulator(group, port, "--enable-latency-ms=30")
    # The emulator is another process: on a loaded 2-core machine either can wait its turn, as in the CLI tests.
    config = DriverConfig(interface="udp_multicast", channel=group, bus_options={"port": port}, feedback_timeout_s=0.3)
    driver = PiperDriver(config)
    try:
        driver.connect()
        driver.enable()
        target = (0.1, 0.3, -0.3, 0.0, 0.1, 0.0)
        assert wait_until(lambda: driver.command(target, 0.02).joints_rad == target, timeout=5.0)

        def reached() -> bool:
            """The target, streamed at 100 Hz as a control loop does, has been reached. Over udp_multicast a
            datagram can be lost: once, under the parallel suite on a slow 2-core VM, a target sent only until
            the driver reported it sent was not reached in 5 s."""
            driver.command(target, 0.02)
            return driver.state().joint_positions_rad == pytest.approx(target, abs=1e-4)

        assert wait_until(reached, timeout=5.0, period=0.01)
        assert wait_until(lambda: driver.state().firmware_version == "S-V1.8-2")
        assert wait_until(lambda: driver.state().rates_hz.get(0x2A5, 0) == pytest.approx(200, rel=0.25))
    finally:
        driver.close()
        assert emulator.stop() == 0  # SIGTERM ends it cleanly
