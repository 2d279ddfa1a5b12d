"""lerobot_cso.durable: what survives kill -9 (atomic files, directory swaps, resumable state, the journal)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lerobot_cso.durable import (
    EpisodeJournal,
    ResumableState,
    read_json,
    replace_dir,
    restore_interrupted_replace,
    write_json,
)
from lerobot_cso.errors import UsageError

# Starts an atomic write of 64 MiB, then hangs inside it (after half the bytes) until killed.
HANGING_WRITER = """
import sys, time
from pathlib import Path
from lerobot_cso import durable
def write(f):
    f.write(b"n" * (32 << 20))
    f.flush()
    print("writing", flush=True)
    time.sleep(60)
durable._commit(Path(sys.argv[1] + ".tmp"), Path(sys.argv[1]), write)
"""


def test_kill_9_during_an_atomic_write_leaves_the_old_file(tmp_path):
    path = tmp_path / "state.json"
    write_json(path, {"version": 1})
    proc = subprocess.Popen([sys.executable, "-c", HANGING_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    assert (tmp_path / "state.json.tmp").stat().st_size == 32 << 20  # the new bytes are on disk, not in place
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert read_json(path) == {"version": 1}
    write_json(path, {"version": 2})  # the next write replaces the leftover temporary file
    assert read_json(path) == {"version": 2} and not (tmp_path / "state.json.tmp").exists()


def test_a_swap_killed_between_its_renames_is_undone(tmp_path):
    dst, src = tmp_path / "buffer", tmp_path / "buffer.new"
    dst.mkdir()
    (dst / "old").write_text("old")
    os.replace(dst, tmp_path / "buffer.old")  # the first rename of replace_dir, then the crash
    restore_interrupted_replace(dst)
    assert (dst / "old").read_text() == "old"
    src.mkdir()
    (src / "new").write_text("new")
    replace_dir(src, dst)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["buffer"] and (dst / "new").read_text() == "new"


def test_resumable_state_keeps_the_last_finished_unit(tmp_path):
    state = ResumableState(tmp_path / "state")
    assert state.progress() is None
    state.save({"iteration": 1}, lambda d: (d / "weights").write_text("w1"))
    state.save({"iteration": 2}, lambda d: (d / "weights").write_text("w2"))

    def crash(directory: Path) -> None:
        (directory / "weights").write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        state.save({"iteration": 3}, crash)
    again = ResumableState(tmp_path / "state")
    assert again.progress() == {"iteration": 2} and (again.directory / "weights").read_text() == "w2"


def test_the_episode_journal_round_trips_and_refuses_other_settings(tmp_path):
    journal = EpisodeJournal(tmp_path / "j", {"n": 1})
    journal.save_episode("reach-v3", "0000007_001", {"actions": np.arange(6, dtype=np.float32).reshape(3, 2)})
    journal.save_record("reach-v3", "0000007", {"attempts": 4, "successes": 1})
    reopened = EpisodeJournal(tmp_path / "j", {"n": 1})
    [path] = reopened.episode_files("reach-v3")
    np.testing.assert_array_equal(reopened.load(path)["actions"], np.arange(6).reshape(3, 2))
    assert reopened.records("reach-v3") == {"0000007": {"attempts": 4, "successes": 1}}
    assert reopened.episode_files() == [path] and reopened.episode_files("other") == []
    with pytest.raises(UsageError, match="holds a collection made with other settings"):
        EpisodeJournal(tmp_path / "j", {"n": 2})
    # nothing left half-written: only the two files and the spec
    assert sorted(p.name for p in (tmp_path / "j").rglob("*") if p.is_file()) == [
        "0000007.json",
        "0000007_001.npz",
        "spec.json",
    ]
