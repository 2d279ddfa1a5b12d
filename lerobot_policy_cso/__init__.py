"""LeRobot plugin entry point.

LeRobot imports every installed distribution whose name starts with ``lerobot_policy_`` by that exact
name. Importing this module registers the ``cso`` policy type and the ``cso_metaworld`` env type, and configures
LIBERO for offline use where it is installed, so that LeRobot's own ``lerobot-eval --env.type=libero`` does not
stop at LIBERO's interactive set-up questions.
"""

from lerobot_cso.policy import CSOConfig, CSOPolicy  # noqa: F401  (registration on import)
from lerobot_cso.worlds.libero.setup import configure_if_installed
from lerobot_cso.worlds.metaworld.env_config import CSOMetaWorldEnvConfig  # noqa: F401  (--env.type=cso_metaworld)

configure_if_installed()
