"""LeRobot plugin entry point.

LeRobot imports every installed distribution whose name starts with ``lerobot_policy_`` by that exact
name. Importing this module registers the ``cso`` policy type and the ``cso_metaworld`` env type.
"""

from lerobot_cso.envs.config import CSOMetaWorldEnvConfig  # noqa: F401  (registers --env.type=cso_metaworld)
from lerobot_cso.policy import CSOConfig, CSOPolicy  # noqa: F401  (registration on import)
