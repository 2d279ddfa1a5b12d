"""Everything that must survive ``kill -9``: atomic files and directories, an episode journal, resumable state.

* :func:`write_atomic` / :func:`write_json` / :func:`save_npz`: a reader (or a rerun after a crash) sees the
  old content or the new, never a torn file; data and directory entry are fsynced. :func:`link_atomic` does the
  same for a symbolic link.
* :func:`replace_dir`: swap a finished directory into place; :func:`restore_interrupted_replace` undoes a swap
  killed between its two renames.
* :class:`EpisodeJournal`: one file per finished episode, written the moment it ends, plus small per-group
  records (demos, R-SFT collection, real-arm rollouts). A journal made with other settings is refused.
* :class:`ResumableState`: a directory (checkpoint files plus ``progress.json``) replaced as a whole after
  each unit of work (an SPO iteration, an R-SFT epoch).
* :func:`output_lock`: one writer per output directory, symbolic links resolved, and none inside another's (a second
  run is refused, the first one named); the lock dies with its process, so ``kill -9`` leaves nothing to clean up.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import shutil
import sys
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_cso.errors import UsageError, check_output_dir

PROGRESS_FILE = "progress.json"


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _commit(tmp: Path, path: Path, write: Callable[[Any], None]) -> None:
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _own_tmp(path: Path) -> Path:
    """This process's temporary sibling of ``path``."""
    return path.with_name(f"{path.name}.{os.getpid()}.tmp")


def write_atomic(path: Path, data: bytes, shared: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (temporary sibling, fsync, rename). The next write replaces the
    temporary file a killed one left; ``shared``: processes may write the same file at once, so each writes its own
    temporary file."""
    tmp = _own_tmp(path) if shared else path.with_name(path.name + ".tmp")
    _commit(tmp, path, lambda f: f.write(data))


def link_atomic(link: Path, target: Path) -> None:
    """Make ``link`` a symbolic link to the directory ``target``, atomically (processes may do it at once)."""
    tmp = _own_tmp(link)
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(target, target_is_directory=True)
    os.replace(tmp, link)
    _fsync_dir(link.parent)


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    write_atomic(path, json.dumps(data, indent=2, default=str).encode())


def read_json(path: Path, lines: bool = False) -> Any | None:
    """The JSON in ``path`` (with ``lines``: a list, one value per line, as in ``log.jsonl``), or None when there is
    no such file; ``UsageError`` naming a damaged one."""
    if not path.is_file():
        return None
    try:
        text = path.read_text()
        return [json.loads(line) for line in text.splitlines()] if lines else json.loads(text)
    except ValueError as e:  # not JSON (truncated, overwritten), or not UTF-8
        raise UsageError(
            f"{path} is damaged ({e}); delete it, or the output dir holding it, to redo its work"
        ) from None


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an ``.npz`` atomically."""
    _commit(path.with_name(path.name + ".tmp"), path, lambda f: np.savez(f, **arrays))


def replace_dir(src: Path, dst: Path) -> None:
    """Move directory ``src`` to ``dst``, replacing it; a crash leaves either the old or the new one. A ``dst`` that
    is a symbolic link stays one: the directory it names is replaced (``src`` moved beside that one first)."""
    if dst.is_symlink():
        real = Path(os.path.realpath(dst))
        if src.resolve().parent != real.parent:
            beside = real.with_name(real.name + ".tmp")
            shutil.rmtree(beside, ignore_errors=True)
            shutil.move(src, beside)  # a rename on one file system, else a copy
            src = beside
        dst = real
    old = dst.with_name(dst.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if dst.exists():
        os.replace(dst, old)
    os.replace(src, dst)
    _fsync_dir(dst.parent)
    shutil.rmtree(old, ignore_errors=True)


def restore_interrupted_replace(dst: Path) -> None:
    """Undo a :func:`replace_dir` killed between its two renames."""
    dst = Path(os.path.realpath(dst)) if dst.is_symlink() else dst
    old = dst.with_name(dst.name + ".old")
    if not dst.exists() and old.exists():
        os.replace(old, dst)


class EpisodeJournal:
    """``root/spec.json``, ``root/episodes/<group>/<name>.npz`` and ``root/records/<group>/<name>.json``.

    ``spec`` is what the journal's content depends on; opening a journal that holds a different one raises
    ``UsageError`` (``what`` names the content in that message). A journal that holds nothing yet (left by a run
    that failed before its first episode, e.g. a robot that did not connect) takes the new spec.
    """

    def __init__(self, root: Path, spec: dict[str, Any], what: str = "a collection") -> None:
        self.root = root
        stored = read_json(root / "spec.json")
        if stored is not None and stored != spec and not self._empty():
            raise UsageError(
                f"{root} holds {what} made with other settings ({stored}); delete it or choose another --output_dir"
            )
        (root / "episodes").mkdir(parents=True, exist_ok=True)
        (root / "records").mkdir(parents=True, exist_ok=True)
        if stored != spec:
            write_json(root / "spec.json", spec)

    def _empty(self) -> bool:
        """Whether no episode or record has been written."""
        return not any(p.is_file() for d in ("episodes", "records") for p in (self.root / d).rglob("*"))

    def episode_path(self, group: str, name: str) -> Path:
        return self.root / "episodes" / group / f"{name}.npz"

    def save_episode(self, group: str, name: str, arrays: dict[str, np.ndarray]) -> None:
        path = self.episode_path(group, name)
        path.parent.mkdir(exist_ok=True)
        save_npz(path, arrays)

    def episode_files(self, group: str | None = None) -> list[Path]:
        """Episode files of ``group`` (every group when None), sorted by group then name."""
        return sorted((self.root / "episodes").glob(f"{group or '*'}/*.npz"))

    @staticmethod
    def load(
        path: Path, keys: tuple[str, ...] | None = None, redo: str = "delete it and the run redoes that episode"
    ) -> dict[str, np.ndarray]:
        """The arrays of an episode file (only ``keys`` when given); ``UsageError`` naming a damaged one, ending in
        ``redo``, what to do about it."""
        try:
            with np.load(path) as data:
                return {k: data[k] for k in (data.files if keys is None else keys)}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            raise UsageError(f"{path} is damaged ({e}); {redo}") from None

    def save_record(self, group: str, name: str, record: dict[str, Any]) -> None:
        directory = self.root / "records" / group
        directory.mkdir(exist_ok=True)
        write_json(directory / f"{name}.json", record)

    def records(self, group: str) -> dict[str, dict[str, Any]]:
        """name → record of every record of ``group``."""
        return {p.stem: read_json(p) for p in (self.root / "records" / group).glob("*.json")}


class ResumableState:
    """A state directory holding a unit of work's files and ``progress.json``, replaced as a whole."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        restore_interrupted_replace(directory)

    def progress(self) -> dict[str, Any] | None:
        """The progress saved last, or None before the first save."""
        return read_json(self.directory / PROGRESS_FILE)

    def save(
        self,
        progress: dict[str, Any],
        write: Callable[[Path], None],
        main: bool = True,
        barrier: Callable[[], None] = lambda: None,
    ) -> None:
        """``write(tmp)`` fills a fresh directory, then it replaces the state together with ``progress``.

        When several processes write one state (e.g. accelerate's ``save_state``), all call this: the ``main``
        one prepares and commits the directory, and ``barrier`` keeps the others' ``write`` in between.
        """
        tmp = self.directory.with_name(self.directory.name + ".tmp")
        if main:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
        barrier()
        write(tmp)
        barrier()
        if main:
            write_json(tmp / PROGRESS_FILE, progress)
            replace_dir(tmp, self.directory)
        barrier()


def lock_file(directory: Path) -> Path:
    """The lock file of an output directory: ``.<name>.lock`` beside it."""
    return directory.with_name(f".{directory.name}.lock")


def _holder(fd: int) -> str:
    return os.pread(fd, 4096, 0).decode(errors="replace").strip() or "a process"


def _take_lock(path: Path) -> tuple[int, bool]:
    """An open ``path`` (made if missing) and whether this process now holds its exclusive lock. A lock file is
    removed by its holder at the end, so a file locked after its holder removed it is dropped and made anew."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return fd, False
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd, True
        except FileNotFoundError:
            pass
        os.close(fd)


def _held_around(directory: Path) -> tuple[Path, str] | None:
    """An output directory above or below ``directory`` (resolved) that another run writes, with its holder: the
    lock files beside its parents, and those inside it (a stage run alone inside a pipeline's output)."""
    around = [lock_file(parent) for parent in directory.parents if parent != parent.parent]
    around += sorted(directory.rglob(".*.lock")) if directory.is_dir() else []
    for path in around:
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:  # none there (most parents)
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except BlockingIOError:
            return path.with_name(path.name.removeprefix(".").removesuffix(".lock")), _holder(fd)
        finally:
            os.close(fd)
    return None


@contextmanager
def output_lock(directory: Path) -> Iterator[None]:
    """Hold the lock of ``directory`` (:func:`lock_file` of its real path, symbolic links resolved) while the block
    runs; raises ``UsageError`` naming the holder (pid, command, since when) when another process holds it, or holds
    a directory above or below it. The lock dies with its process (``kill -9`` leaves nothing to clean up); its file
    is removed when the block ends, on a refusal too."""
    check_output_dir(directory)
    real = directory.resolve()
    real.parent.mkdir(parents=True, exist_ok=True)
    path = lock_file(real)
    fd, held = _take_lock(path)
    try:
        if not held:
            raise UsageError(
                f"{directory} is being written by another run ({_holder(fd)}); wait for it to end or choose another "
                "output dir"
            )
        os.ftruncate(fd, 0)
        command = " ".join([os.path.basename(sys.argv[0]), *sys.argv[1:]])
        os.pwrite(fd, f"pid {os.getpid()}: {command}, since {dt.datetime.now():%Y-%m-%d %H:%M:%S}".encode(), 0)
        nearby = _held_around(real)
        if nearby is not None:
            inside = nearby[0] in real.parents
            raise UsageError(
                f"{directory} {'is inside' if inside else 'holds'} {nearby[0]}, which is being written by another run "
                f"({nearby[1]}); wait for it to end or choose another output dir"
            )
        yield
    finally:
        if held:
            path.unlink(missing_ok=True)
        os.close(fd)
