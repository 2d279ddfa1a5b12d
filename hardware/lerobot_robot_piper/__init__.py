"""LeRobot plugin for the AgileX PiPER: robot ``piper_follower``, teleoperator ``piper_leader``, and for the
physics twin the camera ``piper_twin`` and the teleoperator ``piper_scripted``.

LeRobot imports this package by its distribution name; importing it registers the config types and
changes nothing else in the process (the twin's MuJoCo is imported only when its devices connect).
"""

from .config_piper_follower import PiperFollowerConfig
from .config_piper_leader import PiperLeaderConfig
from .config_piper_scripted import PiperScriptedConfig
from .config_piper_twin_camera import PiperTwinCameraConfig
from .piper_follower import PiperFollower
from .piper_leader import PiperLeader

__all__ = [
    "PiperFollower",
    "PiperFollowerConfig",
    "PiperLeader",
    "PiperLeaderConfig",
    "PiperScriptedConfig",
    "PiperTwinCameraConfig",
]
