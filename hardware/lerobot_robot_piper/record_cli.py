"""``piper-record``: LeRobot's ``lerobot-record``, then the dataset stamped with the motion mode it was
recorded in (``meta/info.json`` key ``piper_motion``), so that deployment uses the same mode.

It takes exactly ``lerobot-record``'s arguments and runs LeRobot's own ``record`` in this process
(a robot plugin cannot do this from inside ``lerobot-record``: it is never told the dataset, whose
directory and repo id ``lerobot-record`` settles only after making the robot). The mode is what the
``piper_follower`` observed while recording: a hardware-linked leader's 0x151 frames, else its own
setting. Nothing is stamped, with one error line and exit code 1, when the mode is unknown, changed
during the recording, or differs from the one the resumed dataset already holds.
"""

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from lerobot.configs import parser
from lerobot.scripts.lerobot_record import RecordConfig, record
from lerobot.utils.import_utils import register_third_party_plugins

from .config_piper_follower import PiperFollowerConfig
from .motion_metadata import MotionMode, dataset_root, read_motion_mode, write_motion_mode
from .piper_follower import PiperFollower, followers_made

PROG = "piper-record"


class StampError(Exception):
    """The dataset was recorded but cannot be stamped with one motion mode."""


@parser.wrap()
def parse_record_config(cfg: RecordConfig) -> RecordConfig:
    """``lerobot-record``'s configuration, parsed from ``sys.argv`` exactly as ``lerobot-record`` does."""
    return cfg


class OneLineTorchcodecProbe(logging.Filter):
    """LeRobot's warning that torchcodec cannot load (where FFmpeg is missing) is a page of tracebacks at every
    probe and looks like a crash: one line, said once. (The cso plugin, where installed, shortens it the same way
    for every LeRobot command; this package must not need it.)"""

    def __init__(self) -> None:
        super().__init__()
        self.said = False

    def filter(self, record: logging.LogRecord) -> bool:
        if "'torchcodec' is installed but cannot be loaded" not in record.getMessage():
            return True
        record.msg, record.args = "torchcodec cannot load here (no FFmpeg it supports): videos decode with pyav", ()
        said, self.said = self.said, True
        return not said


def main(argv: Sequence[str] | None = None) -> int:
    if argv is not None:
        sys.argv = [PROG, *argv]
    logging.getLogger("lerobot.utils.import_utils").addFilter(OneLineTorchcodecProbe())
    register_third_party_plugins()
    cfg = parse_record_config()
    if not isinstance(cfg.robot, PiperFollowerConfig):
        print(f"{PROG}: error: it records a piper_follower (--robot.type=piper_follower)", file=sys.stderr)
        return 2
    root = dataset_root(cfg.dataset.root, cfg.dataset.repo_id)
    before = _episodes(root) if cfg.resume else 0
    previous = read_motion_mode(root) if before else None
    with followers_made() as followers:
        try:
            record(cfg)
        finally:
            # lerobot-record settled the repo id (a timestamp suffix) while it ran: find the dataset again.
            root = dataset_root(cfg.dataset.root, cfg.dataset.repo_id)
            try:
                _stamp(root, followers, before, previous)
                stamped = True
            except StampError as exc:
                stamped = False
                print(f"{PROG}: error: {exc}", file=sys.stderr)
    return 0 if stamped else 1


def _episodes(root: Path) -> int:
    info = root / "meta" / "info.json"
    return int(json.loads(info.read_text()).get("total_episodes", 0)) if info.is_file() else 0


def _stamp(root: Path, followers: list[PiperFollower], before: int, previous: MotionMode | None) -> None:
    """Stamp the one mode the follower moved in (nothing when no episode was added)."""
    if _episodes(root) == before:
        return
    modes = {mode for follower in followers for mode in follower.modes_seen}
    if not modes:
        raise StampError(
            f"{root} recorded, but no linked leader's 0x151 mode frame was heard, so the motion mode is "
            "unknown; not stamped (stamp it with write_motion_mode, hardware/README.md section 4)"
        )
    if len(modes) > 1:
        seen = ", ".join(sorted(map(str, modes)))
        raise StampError(f"{root}: the motion mode changed while recording ({seen}); not stamped")
    (mode,) = modes
    if before and previous != mode:
        held = previous or "an unrecorded mode"
        raise StampError(f"{root} already holds {before} episodes recorded in {held}, now {mode}; not stamped")
    write_motion_mode(root, mode)
    logging.info("%s: %s stamped as recorded in %s", PROG, root, mode)
