"""The QueST skill-token policy, registered with LeRobot as ``--policy.type=cso``."""

from lerobot_cso.policy.configuration_cso import CSOConfig
from lerobot_cso.policy.modeling_cso import CSOPolicy
from lerobot_cso.policy.processor_cso import make_cso_pre_post_processors

__all__ = ["CSOConfig", "CSOPolicy", "make_cso_pre_post_processors"]
