"""The worlds this package ships, registered by importing them: ``--world.type=metaworld|libero|robot``.

A world of this package is one folder of :mod:`lerobot_cso.worlds` plus its line here; a third party's registers
itself from its own distribution (:mod:`lerobot_cso.worlds.base`).
"""

from lerobot_cso.worlds.base import WorldConfig
from lerobot_cso.worlds.libero.world import LiberoConfig  # noqa: F401  (--world.type=libero)
from lerobot_cso.worlds.metaworld.world import MetaWorldConfig
from lerobot_cso.worlds.robot.config import RobotWorldConfig  # noqa: F401  (--world.type=robot)


def default_world(tasks: str) -> WorldConfig:
    """The world a ``--tasks`` spec names when no ``--world.type`` is given: the registered world that claims
    those tasks, MetaWorld otherwise."""
    for cls in WorldConfig.get_known_choices().values():
        if cls.claims(tasks):
            return cls()
    return MetaWorldConfig()
