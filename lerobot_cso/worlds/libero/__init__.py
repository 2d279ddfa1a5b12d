"""LIBERO on LeRobot's ``LiberoEnv``: its offline set-up, the env, the world."""
