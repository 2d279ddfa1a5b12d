"""``piper-merge``: LeRobot's ``lerobot-edit-dataset --operation.type=merge``, with the motion mode stamp carried.

LeRobot's merge writes a new ``meta/info.json`` without ``piper-record``'s ``piper_motion`` key, so a policy trained
on the merged batches would deploy in the default mode (position at 50 %) instead of the recorded one. This takes
exactly ``lerobot-edit-dataset``'s arguments for a merge and runs LeRobot's own ``edit_dataset`` in this process.
Before anything is written it reads every part's stamp: parts recorded in different modes, or some stamped and
some not, are refused with one error line and exit code 1. LeRobot merges into a hidden folder beside the
output, which is stamped and then renamed into place, so the output holds a whole, stamped dataset or nothing.
"""

import logging
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from lerobot.configs import parser
from lerobot.scripts.lerobot_edit_dataset import EditDatasetConfig, MergeConfig, edit_dataset
from lerobot.utils.constants import HF_LEROBOT_HOME
from lerobot.utils.utils import init_logging

from .motion_metadata import dataset_root, read_motion_mode, write_motion_mode
from .record_cli import OneLineTorchcodecProbe

PROG = "piper-merge"


@parser.wrap()
def parse_edit_config(cfg: EditDatasetConfig) -> EditDatasetConfig:
    """``lerobot-edit-dataset``'s configuration, parsed from ``sys.argv`` exactly as it parses it."""
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    if argv is not None:
        sys.argv = [PROG, *argv]
    init_logging()
    logging.getLogger("lerobot.utils.import_utils").addFilter(OneLineTorchcodecProbe())
    cfg = parse_edit_config()
    try:
        return _merge(cfg)
    except _Refused as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1


class _Refused(Exception):
    """Nothing was merged, for the reason given."""


def _merge(cfg: EditDatasetConfig) -> int:
    op = cfg.operation
    if not isinstance(op, MergeConfig):
        raise _Refused("it merges datasets (--operation.type=merge); other edits: lerobot-edit-dataset")
    if not op.repo_ids or not cfg.new_repo_id:
        raise _Refused("name the parts (--operation.repo_ids=[...]) and the merged dataset (--new_repo_id)")
    if op.roots and len(op.roots) != len(op.repo_ids):
        raise _Refused(f"{len(op.repo_ids)} --operation.repo_ids but {len(op.roots)} --operation.roots")
    if cfg.push_to_hub:
        raise _Refused("--push_to_hub=true would push before the stamp is written: merge, then push the result")
    given = op.roots or [None] * len(op.repo_ids)
    roots = [dataset_root(root, repo_id) for root, repo_id in zip(given, op.repo_ids, strict=True)]
    missing = [str(root) for root in roots if not (root / "meta" / "info.json").is_file()]
    if missing:
        raise _Refused(f"no dataset at {', '.join(missing)}")
    modes = {root: read_motion_mode(root) for root in roots}
    if len(set(modes.values())) > 1:
        held = "; ".join(f"{root}: {mode or 'no stamp'}" for root, mode in modes.items())
        raise _Refused(f"the parts were recorded in different motion modes ({held}); nothing merged")
    (mode,) = set(modes.values())
    output = Path(cfg.new_root) if cfg.new_root else HF_LEROBOT_HOME / cfg.new_repo_id
    if output.exists():
        raise _Refused(f"{output} already exists; name a new --new_root or remove it")
    partial = output.with_name(f".{output.name}.{os.getpid()}.partial")
    cfg.new_root = str(partial)
    try:
        try:
            edit_dataset(cfg)
        except Exception as exc:  # LeRobot's own refusals (e.g. parts with other features) in one line
            raise _Refused(f"LeRobot's merge failed: {exc}; nothing merged") from exc
        if mode is not None:
            write_motion_mode(partial, mode)
        os.replace(partial, output)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    stamp = f"stamped as recorded in {mode}" if mode else "no part was stamped, nor is the merged dataset"
    logging.info("%s: %s merged from %d parts; %s", PROG, output, len(roots), stamp)
    return 0
