"""lerobot_cso: CSO (Cascaded Skills Optimization) for QueST skill-token policies on LeRobot."""

import os

# Headless offscreen rendering for MetaWorld cameras. MuJoCo picks its GL backend once, when it is first
# imported, so this must run before any submodule imports metaworld or mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")
