"""The PiPER's physics twin: a MuJoCo arm (``model``), table-top scenes (``scenes``), the plant the simulated
firmware drives (``plant``), its world state between processes (``state_channel``) and its cameras
(``renderer``). Needs the ``twin`` extra (``mujoco``, ``piper-control``); no torch.
"""

import os

# Offscreen rendering without a display; read when mujoco is first imported (set MUJOCO_GL to override).
os.environ.setdefault("MUJOCO_GL", "egl")
