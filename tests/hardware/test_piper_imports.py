"""``piper_can`` and ``piper_twin`` stay torch- and LeRobot-free (checked in a fresh interpreter)."""

from __future__ import annotations

import subprocess
import sys

import pytest

CHECK = """
import importlib, pkgutil, sys
import {package}
names = [m.name for m in pkgutil.iter_modules({package}.__path__, "{package}.")]
for name in names:
    importlib.import_module(name)
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "lerobot", {forbidden}))
print(len(names), heavy)
"""


@pytest.mark.parametrize(
    ("package", "forbidden", "modules"),
    [
        ("piper_can", '"numpy"', 8),  # codec, driver, emulator, emulator_cli, errors, link, safety, state
        ("piper_twin", '"torch"', 5),  # model, plant, renderer, scenes, state_channel (MuJoCo and NumPy only)
    ],
)
def test_importing_every_module_loads_neither_torch_nor_lerobot(package, forbidden, modules):
    code = CHECK.format(package=package, forbidden=forbidden)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    count, heavy = out.stdout.split(" ", 1)
    assert int(count) >= modules
    assert heavy.strip() == "[]"
