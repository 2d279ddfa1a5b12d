"""Renders the twin's cameras (``front``, ``wrist``) from a published ``TwinSnapshot``.

MuJoCo renders offscreen with ``MUJOCO_GL=egl`` (``piper_twin`` sets it unless told otherwise, if it is
imported before ``mujoco``; ``osmesa`` works too). The GL context belongs to the thread that made the
renderer: render on that thread. Every renderer of a process takes one lock around its GL calls: two
threads rendering at once (the front and the wrist camera of one ``lerobot-record``) crash the process with a
segmentation fault in ``mjr_render``/``mjr_readPixels`` (EGL on Mesa's llvmpipe, mujoco 3.3: 2 crashes in about
7 minutes of two threads rendering 64x64 frames without pause; session 37).
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np

from .scenes import compile_scene, get_scene
from .state_channel import TwinSnapshot

# One GL call sequence at a time in this process (see the module's docstring).
GL_LOCK = threading.Lock()


class TwinRenderer:
    """One scene's model and one offscreen renderer of ``height`` x ``width`` RGB frames."""

    def __init__(self, scene: str, width: int, height: int) -> None:
        self.scene = scene
        self.model = compile_scene(get_scene(scene))
        self.model.vis.global_.offwidth = max(width, self.model.vis.global_.offwidth)
        self.model.vis.global_.offheight = max(height, self.model.vis.global_.offheight)
        self.data = mujoco.MjData(self.model)
        with GL_LOCK:
            self._renderer = mujoco.Renderer(self.model, height, width)

    def render(self, snapshot: TwinSnapshot, view: str) -> np.ndarray:
        """The ``(height, width, 3)`` uint8 image of camera ``view`` in the state ``snapshot``."""
        if snapshot.scene != self.scene:
            raise ValueError(f"the twin now runs scene {snapshot.scene!r}, this renderer was built for {self.scene!r}")
        d = self.data
        d.qpos[:] = snapshot.qpos
        d.mocap_pos[:] = snapshot.mocap_pos
        d.mocap_quat[:] = snapshot.mocap_quat
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)
        with GL_LOCK:
            self._renderer.update_scene(d, camera=view)
            return self._renderer.render()

    def close(self) -> None:
        with GL_LOCK:
            self._renderer.close()
