"""LeRobot plugin for the AgileX PiPER: robot ``piper_follower``, teleoperator ``piper_leader``, and for the
physics twin the camera ``piper_twin``, the teleoperator ``piper_scripted`` and the robot ``piper_twin_sim`` (the
twin in process, faster than real time).

LeRobot imports this package by its distribution name; importing it registers the config types and
changes nothing else in the process (the twin's MuJoCo is imported only when its devices connect, or when a
piper_twin_sim is made).
"""

from .config_piper_follower import PiperFollowerConfig
from .config_piper_leader import PiperLeaderConfig
from .config_piper_scripted import PiperScriptedConfig
from .config_piper_twin_camera import PiperTwinCameraConfig
from .config_piper_twin_sim import PiperTwinSimConfig
from .piper_follower import PiperFollower
from .piper_leader import PiperLeader

__all__ = [
    "PiperFollower",
    "PiperFollowerConfig",
    "PiperLeader",
    "PiperLeaderConfig",
    "PiperScriptedConfig",
    "PiperTwinCameraConfig",
    "PiperTwinSimConfig",
]
