"""MetaWorld as the embedded default world: tasks, initial-state seeds, the gymnasium env, its LeRobot config.

Submodules are imported explicitly; only ``metaworld_env`` imports metaworld/mujoco.
"""
