"""Configuration of the ``piper_scripted`` teleoperator: scripted demonstrations on the PiPER twin."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.teleoperators.config import TeleoperatorConfig


@TeleoperatorConfig.register_subclass("piper_scripted")
@dataclass
class PiperScriptedConfig(TeleoperatorConfig):
    """Demonstrates the twin's task (``piper-emulator --physics``) the way a person teleoperates it: it
    watches the scene (the twin's world state on ``group``/``port``), moves the grasp point through the
    task's waypoints at ``speed_m_s`` (each jittered by ``noise_m``, from ``seed``) and gives joint targets
    by inverse kinematics, which the follower executes through its usual safety checks. ``detour_m`` > 0: it
    first arrives beside the object, off by up to that much, and corrects; ``regrasp_m`` > 0: half of the
    demonstrations first close the gripper on nothing, up to that far beside the object, then reopen and grasp;
    ``close_s``: how long every close stays closed before the arm moves on (``piper_twin.demo``).

    ``cycle=true``: once a demonstration is done it waits ``pause_s``, asks the twin to place the objects
    for the next seed (as a person puts the cube back) and demonstrates again; otherwise it holds.

    ``max_age_s``: a state older than this is waited on for up to as long again (a twin stalled by a loaded
    machine); then the teleoperator raises (the twin stopped)."""

    group: str = "239.74.1.1"
    port: int = 43200
    speed_m_s: float = 0.12
    noise_m: float = 0.003
    detour_m: float = 0.0
    regrasp_m: float = 0.0
    close_s: float = 0.8
    seed: int = 0
    cycle: bool = True
    pause_s: float = 1.0
    connect_timeout_s: float = 2.0
    max_age_s: float = 0.5

    def __post_init__(self) -> None:
        for name in ("speed_m_s", "close_s", "connect_timeout_s", "max_age_s"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ValueError(f"piper_scripted {name} must be a finite number > 0, got {getattr(self, name)!r}")
        for name in ("noise_m", "detour_m", "regrasp_m", "pause_s"):
            if not 0 <= getattr(self, name) < float("inf"):
                raise ValueError(f"piper_scripted {name} must be a finite number >= 0, got {getattr(self, name)!r}")
