"""Helpers to run the emulator and LeRobot's CLIs as real processes over udp_multicast (loopback)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import can
from piper_can import codec

BIN = Path(sys.executable).parent
CLI_TIMEOUT_S = 240


def cli_env(home: Path) -> dict[str, str]:
    """Offline, with LeRobot's caches (calibration dirs) under ``home``."""
    env = dict(os.environ)
    env.update(
        HF_HOME=str(home / "hf"),
        HF_LEROBOT_HOME=str(home / "lerobot"),
        HF_HUB_OFFLINE="1",
        HF_DATASETS_OFFLINE="1",
        TOKENIZERS_PARALLELISM="false",
    )
    return env


@dataclass
class EmulatorProcess:
    """A ``piper-emulator`` process; ``stop`` ends it (SIGTERM, then SIGKILL)."""

    group: str
    port: int
    process: subprocess.Popen

    def args(self, prefix: str) -> list[str]:
        """``--robot.…`` / ``--teleop.…`` arguments that reach this arm."""
        return [
            f"--{prefix}.interface=udp_multicast",
            f"--{prefix}.channel={self.group}",
            f"--{prefix}.port={self.port}",
        ]

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)
        return self.process.returncode


EMULATOR_LIFETIME_S = 900  # bound: an emulator left behind by a killed test run ends by itself


def start_emulator(group: str, port: int, *extra: str, timeout: float = 30.0) -> EmulatorProcess:
    """Start ``piper-emulator`` and wait for its ready line."""
    cmd = [
        str(BIN / "piper-emulator"),
        "--interface=udp_multicast",
        f"--channel={group}",
        f"--port={port}",
        f"--duration={EMULATOR_LIFETIME_S}",
        *extra,
    ]
    process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    emulator = EmulatorProcess(group, port, process)
    ready: list[str] = []
    reader = threading.Thread(target=lambda: ready.append(process.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    if not ready or "ready" not in ready[0]:
        emulator.stop()
        raise RuntimeError(f"piper-emulator did not start: {ready} {process.stderr.read()}")
    return emulator


def run_cli(name: str, args: list[str], home: Path, timeout: float = CLI_TIMEOUT_S) -> subprocess.CompletedProcess:
    """Run a LeRobot console script from this venv to completion (killed after ``timeout``)."""
    return subprocess.run(
        [str(BIN / name), *args], capture_output=True, text=True, timeout=timeout, env=cli_env(home), cwd=home
    )


def explain(out: subprocess.CompletedProcess) -> str:
    """The informative tail of a CLI's stderr (without LeRobot's torchcodec fallback noise)."""
    lines = [line for line in out.stderr.splitlines() if "torchcodec" not in line and "libav" not in line]
    return "\n".join(lines[-40:])


@dataclass
class Sample:
    time_s: float  # the kernel's receive time of the frame (SO_TIMESTAMPNS), not when we read it
    joints_rad: tuple[float, ...]


@dataclass
class Track:
    """Joint samples (complete sets of three frames) and gripper samples of one kind of frame."""

    joints: list[Sample] = field(default_factory=list)
    gripper: list[Sample] = field(default_factory=list)


class ChannelRecorder:
    """Records what is said on a udp channel: the arm's feedback (0x2A5..0x2A8) and the commands
    (0x155..0x157, 0x159) some host or leader sends, each with the kernel's receive time."""

    def __init__(self, group: str, port: int) -> None:
        self.feedback = Track()
        self.commands = Track()
        self.modes: list[bytes] = []  # the data of every 0x151 (mode) frame
        self._bus = can.Bus(interface="udp_multicast", channel=group, port=port)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        kinds = (
            (self.feedback, codec.ID_JOINT_FEEDBACK, codec.ID_GRIPPER_FEEDBACK, codec.decode_feedback, {}),
            (self.commands, codec.ID_JOINT_COMMAND, codec.ID_GRIPPER_COMMAND, codec.decode_command, {}),
        )
        while not self._stop.is_set():
            msg = self._bus.recv(timeout=0.05)
            if msg is None:
                continue
            if msg.arbitration_id == codec.ID_MODE_CONTROL:
                self.modes.append(bytes(msg.data))
            for track, joint_ids, gripper_id, decode, latest in kinds:
                if msg.arbitration_id == gripper_id:
                    track.gripper.append(Sample(msg.timestamp, (decode(gripper_id, msg.data).opening_m,)))
                elif msg.arbitration_id in joint_ids:
                    latest[msg.arbitration_id] = decode(msg.arbitration_id, msg.data).positions_rad
                    if msg.arbitration_id == joint_ids[-1] and len(latest) == 3:
                        joints = tuple(p for i in joint_ids for p in latest[i])
                        track.joints.append(Sample(msg.timestamp, joints))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._bus.shutdown()
