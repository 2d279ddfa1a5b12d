"""MetaWorld v3 dimensions and timing shared by the env, its LeRobot config and the dataset writer."""

STATE_DIM = 39  # hand xyz, gripper, 2 objects × (pos + quat), the previous frame's 18 values, goal xyz
ACTION_DIM = 4  # Δxyz of the hand + gripper effort, in [-1, 1]
FPS = 80  # control period: frame_skip 5 × 2.5 ms = 12.5 ms
HORIZON = 500  # MetaWorld's max_path_length
IMAGE_SIZE = 128
CAMERAS = ("corner", "corner2", "corner3", "corner4", "topview", "behindGripper", "gripperPOV")
