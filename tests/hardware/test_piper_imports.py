"""``piper_can`` stays torch- and LeRobot-free (checked in a fresh interpreter)."""

from __future__ import annotations

import subprocess
import sys

CHECK = """
import importlib, pkgutil, sys
import piper_can
names = [m.name for m in pkgutil.iter_modules(piper_can.__path__, "piper_can.")]
for name in names:
    importlib.import_module(name)
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "lerobot", "numpy"))
print(len(names), heavy)
"""


def test_importing_every_piper_can_module_loads_neither_torch_nor_lerobot():
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=60, check=True)
    count, heavy = out.stdout.split(" ", 1)
    assert int(count) >= 8  # codec, driver, emulator, emulator_cli, errors, link, safety, state
    assert heavy.strip() == "[]"
