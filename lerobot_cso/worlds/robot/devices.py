"""The robot and its optional teleoperator as one pair of devices: connected, let go of after a fault, and
connected again once the operator has recovered them (fault recovery).

A fault names its device in one line (:class:`ArmFault`); the robot plugin may add how to recover it: a robot
with a ``recovery_hint`` attribute (e.g. the PiPER's) has it appended to the message.
"""

from __future__ import annotations

import logging
from typing import Any

from lerobot.robots import Robot, make_robot_from_config
from lerobot.teleoperators import Teleoperator, make_teleoperator_from_config

from lerobot_cso.worlds.robot.operator import EpisodeInfo, Operator

log = logging.getLogger(__name__)


class ArmFault(SystemExit):
    """The robot did not connect or failed during an episode; the command ends with this one-line message
    (exit code 1)."""


class TeleopFault(RuntimeError):
    """The teleoperator failed while the arm followed it (the scene-arranging phase)."""


def reason(exc: BaseException) -> str:
    """``exc`` as one line: its type and message."""
    return f"{type(exc).__name__}: {exc}".replace("\n", " ")


class Devices:
    """The robot (``robot``) and the teleoperator (``teleop``, or None), built from their configs."""

    def __init__(self, robot_config: Any, teleop_config: Any | None) -> None:
        self.robot_config, self.teleop_config = robot_config, teleop_config
        self.robot: Robot = make_robot_from_config(robot_config)
        self.teleop: Teleoperator | None = None

    def hint(self, device: str) -> str:
        """`` (<how to recover>)`` for the robot when its plugin says how, else nothing."""
        hint = getattr(self.robot, "recovery_hint", None) if device == "robot" else None
        return f" ({hint})" if hint else ""

    def connect(self) -> dict[str, Any]:
        """Connect both; returns the robot's first observation. A device that does not connect is an
        :class:`ArmFault` naming it (both are disconnected)."""
        device = f"robot {self.robot_config.type}"
        try:
            self.robot.connect()
            observation = self.robot.get_observation()
            if self.teleop_config is not None:
                device = f"teleoperator {self.teleop_config.type}"
                self.teleop = make_teleoperator_from_config(self.teleop_config)
                self.teleop.connect()
        except Exception as exc:  # not on the bus, a camera that does not open, ...: one line, not a traceback
            self.close()
            raise ArmFault(f"error: {device} did not connect: {reason(exc)}") from exc
        except BaseException:
            self.close()
            raise
        return observation

    def recover(self, operator: Operator, info: EpisodeInfo, fault: str, device: str) -> None:
        """``--operator.on_fault=wait``: let go of the devices, wait for the operator, connect them again as a
        rerun would (their own ``connect``: for the PiPER the enable handshake with ``--robot.recovery``), until
        they do."""
        self.let_go()
        print(
            f"{device} fault in state {info.state}, attempt {info.attempt}: {fault}. The episode was discarded and "
            f"the devices disconnected; recover the {device}{self.hint(device)}",
            flush=True,
        )
        while True:
            operator.wait_for_recovery(info)
            self.robot = make_robot_from_config(self.robot_config)
            try:
                self.robot.connect()
                self.robot.get_observation()
                if self.teleop_config is not None:
                    self.teleop = make_teleoperator_from_config(self.teleop_config)
                    self.teleop.connect()
            except Exception as exc:  # still faulted: nothing was commanded
                self.let_go()
                print(f"the devices did not reconnect: {reason(exc)}; recover them and confirm again", flush=True)
                continue
            print(f"reconnected; state {info.state}, attempt {info.attempt} again", flush=True)
            return

    def let_go(self) -> None:
        """Disconnect the teleoperator and the robot (its own disconnect policy) where still connected; a failure
        is only logged."""
        for device in (self.teleop, self.robot):
            try:
                if device is not None and device.is_connected:
                    device.disconnect()
            except Exception as exc:
                log.warning("%s did not disconnect cleanly: %s", type(device).__name__, reason(exc))

    def close(self) -> None:
        """Disconnect (the robot's own disconnect policy applies); never sends anything else."""
        for device in (self.teleop, self.robot):
            if device is not None and device.is_connected:
                device.disconnect()
