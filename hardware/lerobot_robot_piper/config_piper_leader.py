"""Configuration of the ``piper_leader`` teleoperator."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.teleoperators.config import TeleoperatorConfig

SOURCES = ("control", "feedback")


@TeleoperatorConfig.register_subclass("piper_leader")
@dataclass
class PiperLeaderConfig(TeleoperatorConfig):
    """A PiPER leader arm, read without ever sending a frame.

    ``source="control"``: an arm configured as leader (0x470 0xFA) that emits 0x151/0x155..0x157/0x159,
    either on its own channel or linked in hardware on the follower's bus (then set the follower's
    ``hardware_linked_leader=true``). ``source="feedback"``: an ordinary PiPER moved by hand (disabled or
    in teach mode) on its own channel, read from its 0x2A5..0x2A8 feedback.
    """

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    port: int | None = None
    source: str = "control"
    # No leader joint or gripper frame for longer than this: get_action raises (its rate is unverified).
    timeout_s: float = 0.1
    connect_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {self.timeout_s}")
