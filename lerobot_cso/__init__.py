"""lerobot_cso: CSO (Cascaded Skills Optimization) for QueST skill-token policies on LeRobot."""
