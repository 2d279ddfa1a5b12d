"""LeRobot plugin for the AgileX PiPER: robot ``piper_follower`` and teleoperator ``piper_leader``.

LeRobot imports this package by its distribution name; importing it registers both config types and
changes nothing else in the process.
"""

from .config_piper_follower import PiperFollowerConfig
from .config_piper_leader import PiperLeaderConfig
from .piper_follower import PiperFollower
from .piper_leader import PiperLeader

__all__ = ["PiperFollower", "PiperFollowerConfig", "PiperLeader", "PiperLeaderConfig"]
