"""A ``piper-emulator`` process on a private udp_multicast channel: the simulated arm as another program on the bus."""

from __future__ import annotations

import random
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent  # this environment's console scripts (piper-emulator, LeRobot's CLIs)
LIFETIME_S = 900  # bound: an emulator left behind by a killed run ends by itself


def unique_udp_channel() -> tuple[str, int]:
    """A random IPv4 multicast group and UDP port (Linux delivers by port, so both must be unique)."""
    rng = random.SystemRandom()
    group = f"239.{rng.randint(1, 254)}.{rng.randint(1, 254)}.{rng.randint(1, 254)}"
    return group, rng.randint(20_000, 60_000)


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
        """End the process; its exit code."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)
        return self.process.returncode


def start_emulator(group: str, port: int, *extra: str, timeout: float = 30.0) -> EmulatorProcess:
    """Start ``piper-emulator`` on ``group``:``port`` with the ``extra`` arguments and wait for its ready line."""
    cmd = [
        str(BIN / "piper-emulator"),
        "--interface=udp_multicast",
        f"--channel={group}",
        f"--port={port}",
        f"--duration={LIFETIME_S}",
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
