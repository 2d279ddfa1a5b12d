"""Issue 35, item 8: the PiPER commands refuse what they cannot honour with one ``error:`` line and exit code 2,
before they start (in this process: each case fails in argument checks, well under a second)."""

from __future__ import annotations

import errno

import can
import pytest
from piper_can import emulator_cli, recover_cli
from piper_can.errors import PiperConnectionError
from piper_can.link import open_bus


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ("--rate-scale=nan", "argument --rate-scale: must be a finite number, got 'nan'"),
        ("--rate-scale=inf", "argument --rate-scale: must be a finite number, got 'inf'"),
        (
            "--initial-pose=nan,0,0,0,0,0",
            "argument --initial-pose: the angles must be finite numbers, got 'nan,0,0,0,0,0'",
        ),
        ("--enable-latency-ms=nan", "argument --enable-latency-ms: must be a finite number, got 'nan'"),
        ("--enable-latency-ms=-5", "argument --enable-latency-ms: must be >= 0, got -5.0"),
        ("--duration=nan", "argument --duration: must be a finite number, got 'nan'"),
    ],
)
def test_the_emulator_refuses_a_non_finite_setting_before_it_says_ready(bad, message, capsys):
    """``--initial-pose=nan,...`` or ``--rate-scale=nan`` printed "ready", then the firmware thread died on the first
    frame (or sent nothing) while the process stayed up."""
    with pytest.raises(SystemExit) as exit_:
        emulator_cli.main(["--interface=virtual", "--channel=h35-emulator", "--duration=0.2", bad])
    out, err = capsys.readouterr()
    assert exit_.value.code == 2
    assert err.splitlines() == [f"piper-emulator: error: {message}"]
    assert "ready" not in out


@pytest.mark.parametrize("bad", ["-1", "nan", "5"])
def test_recover_refuses_an_out_of_range_setting_in_one_line(bad, capsys):
    """``piper-recover --feedback-timeout-s=-1`` raised the driver config's ValueError as a traceback."""
    assert recover_cli.main(["--interface=virtual", "--channel=h35-recover", f"--feedback-timeout-s={bad}"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"piper-recover: error: feedback_timeout_s must be a finite number in (0.0, 1.0], got {float(bad)!r}"
    ]


def test_a_kernel_without_socketcan_is_told_to_load_the_can_modules(monkeypatch):
    """Errno 97 (no CAN address family) got an ``ip link`` hint, which cannot help before the modules are loaded."""

    def no_can(**options: object) -> can.BusABC:
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")

    monkeypatch.setattr(can, "Bus", no_can)
    with pytest.raises(
        PiperConnectionError, match="no SocketCAN support loaded: load it with sudo modprobe can can_raw"
    ):
        open_bus("socketcan", "can0", 1_000_000, {})


def test_piper_record_says_lerobots_torchcodec_probe_page_in_one_line_without_the_cso_plugin(monkeypatch, caplog):
    """Issue 35, item 9: with the hardware package alone (no cso plugin to shorten it), ``piper-record`` opened with
    LeRobot's page of libtorchcodec tracebacks, once per probe, where FFmpeg is missing."""
    import importlib
    import logging

    from lerobot.utils.import_utils import get_safe_default_video_backend
    from lerobot_robot_piper import record_cli

    probe_log = logging.getLogger("lerobot.utils.import_utils")
    monkeypatch.setattr(probe_log, "filters", [])  # no other plugin's filter in this process

    def no_plugins() -> None:
        raise SystemExit(0)  # stop after piper-record's own set-up

    monkeypatch.setattr(record_cli, "register_third_party_plugins", no_plugins)
    with pytest.raises(SystemExit):
        record_cli.main([])
    load = importlib.import_module

    def no_ffmpeg(name: str, *args):
        if name == "torchcodec":
            raise RuntimeError("Could not load libtorchcodec.\n" + "Traceback (most recent call last):\n" * 30)
        return load(name, *args)

    monkeypatch.setattr(importlib, "import_module", no_ffmpeg)
    with caplog.at_level(logging.WARNING, logger="lerobot.utils.import_utils"):
        assert get_safe_default_video_backend() == get_safe_default_video_backend() == "pyav"
    assert [r.getMessage() for r in caplog.records] == [
        "torchcodec cannot load here (no FFmpeg it supports): videos decode with pyav"
    ]
