"""A recorder of what is said on a udp_multicast channel: the arm's feedback and the commands sent to it, each frame
with the kernel's receive time."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import can

from . import codec


@dataclass
class Sample:
    """One reading: a complete set of joints (rad) or a gripper opening (m)."""

    time_s: float  # the kernel's receive time of the frame (SO_TIMESTAMPNS), not when we read it
    joints_rad: tuple[float, ...]


@dataclass
class Track:
    """Joint samples (complete sets of three frames) and gripper samples of one kind of frame."""

    joints: list[Sample] = field(default_factory=list)
    gripper: list[Sample] = field(default_factory=list)


class ChannelRecorder:
    """Records, on its own thread, the arm's feedback (0x2A5..0x2A8) and the commands (0x155..0x157, 0x159) some
    host or leader sends on the udp_multicast channel ``group``:``port``, and every mode frame (0x151)."""

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
        """Stop recording and close the bus; what was recorded stays."""
        self._stop.set()
        self._thread.join(timeout=2)
        self._bus.shutdown()
