"""MetaWorld v3 dimensions and timing shared by the env, its LeRobot config and the dataset writer."""

ACTION_DIM = 4  # Δxyz of the hand + gripper effort, in [-1, 1]
FPS = 80  # control period: frame_skip 5 × 2.5 ms = 12.5 ms (LeRobot's metaworld env and datasets: 80 too)
HORIZON = 500  # MetaWorld's max_path_length
IMAGE_SIZE = 128
# What ``observation.state`` holds, by name, and its size. "full": the 39-d MetaWorld observation (object and goal
# positions included: privileged); "proprio": QueST's 8-d proprio, hand xyz + gripper of this and the previous
# frame (obs[0:4] ++ obs[18:22]), for policies that must find the objects in a camera image; "hand": LeRobot's
# own MetaWorld format, hand xyz + gripper (obs[0:4]).
STATE_LAYOUTS = {"full": 39, "proprio": 8, "hand": 4}
STATE_DIM = STATE_LAYOUTS["full"]  # hand xyz, gripper, 2 objects × (pos + quat), the previous frame's 18, goal xyz
CAMERAS = ("corner", "corner2", "corner3", "corner4", "topview", "behindGripper", "gripperPOV")
# LeRobot's own MetaWorld format (its ``metaworld`` env, the Hub's lerobot/metaworld_* datasets): this camera as
# ``observation.image``, at this size, and the "hand" state layout as ``observation.state``.
LEROBOT_CAMERA = "corner2"
LEROBOT_IMAGE_SIZE = 480
LEROBOT_STATE = "hand"
