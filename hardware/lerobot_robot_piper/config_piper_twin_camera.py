"""Config of the ``piper_twin`` camera: a view rendered from the PiPER twin's published world state."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.cameras import CameraConfig

VIEWS = ("front", "wrist")


@CameraConfig.register_subclass("piper_twin")
@dataclass(kw_only=True)
class PiperTwinCameraConfig(CameraConfig):
    """``--robot.cameras='{front: {type: piper_twin, view: front}, wrist: {type: piper_twin, view: wrist}}'``.

    It renders ``view`` from the state that ``piper-emulator --physics`` publishes on ``group``/``port``
    (its ``--state-group``/``--state-port``). ``max_age_s``: a frame from an older state is refused (the
    emulator stopped publishing)."""

    view: str = "front"
    group: str = "239.74.1.1"
    port: int = 43200
    fps: int | None = 30
    width: int | None = 128
    height: int | None = 96
    connect_timeout_s: float = 2.0
    max_age_s: float = 0.5

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise ValueError(f"piper_twin camera view must be one of {', '.join(VIEWS)}, got {self.view!r}")
        for name in ("fps", "width", "height"):
            value = getattr(self, name)
            if value is None or value <= 0:
                raise ValueError(f"piper_twin camera {name} must be a positive integer, got {value!r}")
        if not (self.max_age_s > 0 and self.connect_timeout_s > 0):
            raise ValueError("piper_twin camera max_age_s and connect_timeout_s must be positive")
