"""LeRobot teleoperator ``piper_leader``: a PiPER leader arm, listened to on CAN (it never sends)."""

from __future__ import annotations

import logging
from functools import cached_property

from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected
from piper_can.clock import SYSTEM_CLOCK, Clock
from piper_can.codec import ID_GRIPPER_COMMAND, ID_GRIPPER_FEEDBACK, ID_JOINT_COMMAND, ID_JOINT_FEEDBACK
from piper_can.errors import FeedbackStaleError
from piper_can.link import PiperLink

from .config_piper_leader import PiperLeaderConfig
from .features import motor_features, to_action

log = logging.getLogger(__name__)


class PiperLeader(Teleoperator):
    """Actions ``joint_1.pos … joint_6.pos`` (rad) and ``gripper.pos`` (m) from a leader arm."""

    config_class = PiperLeaderConfig
    name = "piper_leader"

    def __init__(self, config: PiperLeaderConfig, clock: Clock = SYSTEM_CLOCK):
        """``clock``: the system's (LeRobot's CLIs), or a ``SimulatedClock`` in tests."""
        super().__init__(config)
        self.config = config
        control = config.source == "control"
        self._joint_ids = ID_JOINT_COMMAND if control else ID_JOINT_FEEDBACK
        self._gripper_id = ID_GRIPPER_COMMAND if control else ID_GRIPPER_FEEDBACK
        self.link = PiperLink(
            config.interface,
            config.channel,
            config.bitrate,
            {} if config.port is None else {"port": config.port},
            watch=dict.fromkeys((*self._joint_ids, self._gripper_id), config.timeout_s),
            watch_name="leader frame" if control else "leader feedback",
            clock=clock,
        )

    @cached_property
    def action_features(self) -> dict[str, type]:
        return motor_features()

    @cached_property
    def feedback_features(self) -> dict[str, type]:
        return {}  # passive: nothing is ever sent to the leader

    @property
    def is_connected(self) -> bool:
        return self.link.is_open

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to do: the leader reports absolute angles."""

    def configure(self) -> None:
        """Nothing to configure: the leader is only listened to."""

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        self.link.open((*self._joint_ids, self._gripper_id), self.config.connect_timeout_s)
        log.info("%s listening on %s (%s frames)", self, self.link.where, self.config.source)

    @check_if_not_connected
    def get_action(self) -> dict[str, float]:
        self.link.raise_if_unhealthy()
        state = self.link.state()
        if self.config.source == "control":
            joints, gripper = state.leader_joint_targets_rad, state.leader_gripper
        else:
            joints, gripper = state.joint_positions_rad, state.gripper
        if joints is None or gripper is None:  # not after connect(), which waited for every frame
            raise FeedbackStaleError(f"no leader frames heard on {self.link.where} yet")
        return to_action(joints, gripper.value.opening_m)

    def send_feedback(self, feedback: dict) -> None:
        """Passive leader: feedback is not supported and ignored."""

    def disconnect(self) -> None:
        self.link.close()
