"""AgileX PiPER over CAN without torch or LeRobot: codec, driver, simulated firmware."""
