"""LeRobot plugin entry point.

LeRobot imports every installed distribution whose name starts with ``lerobot_policy_`` by that exact
name. Importing this module registers the ``cso`` policy type and the ``cso_metaworld`` env type, configures
LIBERO for offline use where it is installed, so that LeRobot's own ``lerobot-eval --env.type=libero`` does not
stop at LIBERO's interactive set-up questions, shortens LeRobot's torchcodec probe warning to one line, and makes a
cso policy setting that the policy refuses one ``error:`` line, exit code 2
(:func:`~lerobot_cso.errors.one_line_policy_refusals`).
"""

import logging
import sys

import draccus

from lerobot_cso.errors import one_line_policy_refusals
from lerobot_cso.policy import CSOConfig, CSOPolicy  # noqa: F401  (registration on import)
from lerobot_cso.worlds.libero.setup import configure_if_installed
from lerobot_cso.worlds.metaworld.env_config import CSOMetaWorldEnvConfig  # noqa: F401  (--env.type=cso_metaworld)


class OneLineTorchcodecProbe(logging.Filter):
    """LeRobot's warning that torchcodec cannot load (where FFmpeg is missing) carries a page of tracebacks, one per
    FFmpeg version tried, at every probe, and looks like a crash at the start of ``lerobot-train`` or
    ``lerobot-record``: it becomes one line, said once, or nothing when the command chose
    ``--dataset.video_backend=pyav`` (LeRobot computes that flag's default, probing torchcodec, before reading it)."""

    def __init__(self) -> None:
        super().__init__()
        self.said = False

    def filter(self, record: logging.LogRecord) -> bool:
        if "'torchcodec' is installed but cannot be loaded" not in record.getMessage():
            return True
        record.msg, record.args = "torchcodec cannot load here (no FFmpeg it supports): videos decode with pyav", ()
        said, self.said = self.said, True
        return not said and "--dataset.video_backend=pyav" not in sys.argv


configure_if_installed()
draccus.parse = one_line_policy_refusals(draccus.parse)
TORCHCODEC_PROBE = OneLineTorchcodecProbe()
logging.getLogger("lerobot.utils.import_utils").addFilter(TORCHCODEC_PROBE)
