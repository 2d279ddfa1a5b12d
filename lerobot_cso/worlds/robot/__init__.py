"""A LeRobot robot with an operator in the loop: the settings, the operator, the world and its backend."""
