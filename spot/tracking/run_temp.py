"""Run temp folders: where a run stages its artifact files before they are logged.

Each run gets a ``$SPOT_CACHE_DIR/tmp/spot-run-<pid>-*`` folder (:func:`run_temp_dir`) that it
removes when it ends (:func:`remove_run_temp`); a killed run's folder is removed by the next run
(:func:`clean_run_temp`).
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

from spot import runtime

RUN_TEMP_PREFIX = "spot-run-"


def run_temp_root() -> Path:
    """Where runs stage their artifact files before logging them: ``$SPOT_CACHE_DIR/tmp``."""
    from spot import cache

    return cache.cache_dir() / "tmp"


def clean_run_temp(root: Path | None = None) -> list[Path]:
    """Remove ``spot-run-<pid>-*`` folders under ``root`` whose process no longer runs (killed runs);
    returns them. Folders of another host's processes (a shared cache dir) are kept while younger
    than a day."""
    import re
    import shutil

    root = run_temp_root() if root is None else root
    removed = []
    if not root.is_dir():
        return removed
    for folder in root.iterdir():
        m = re.fullmatch(rf"{RUN_TEMP_PREFIX}(\d+)-.*", folder.name)
        if m is None or not folder.is_dir() or int(m[1]) == os.getpid():
            continue
        if runtime.pid_alive(int(m[1])):
            continue
        try:
            if time.time() - folder.stat().st_mtime < 86400 and not _local_pid_folder(folder):
                continue
        except FileNotFoundError:
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def _local_pid_folder(folder: Path) -> bool:
    """Whether ``folder`` was made on this host (its ``.host`` file names it)."""
    try:
        return (folder / ".host").read_text().strip() == platform.node()
    except OSError:
        return False


def run_temp_dir() -> Path:
    """A new ``$SPOT_CACHE_DIR/tmp/spot-run-<pid>-*`` folder for one run's artifact files (the run
    removes it when it ends, :func:`remove_run_temp`; a killed run's is removed by the next run)."""
    import tempfile

    from spot import store

    root = store.writable_dir(run_temp_root(), "$SPOT_CACHE_DIR")  # a file or read-only: one clear error
    clean_run_temp(root)
    folder = Path(tempfile.mkdtemp(prefix=f"{RUN_TEMP_PREFIX}{os.getpid()}-", dir=root))
    (folder / ".host").write_text(platform.node())
    return folder


def remove_run_temp(folder: Path) -> None:
    """Remove a folder made by :func:`run_temp_dir` (its files were logged to the run)."""
    import shutil

    if folder.name.startswith(RUN_TEMP_PREFIX):
        shutil.rmtree(folder, ignore_errors=True)
