"""Creating and migrating a SQLite store under a file lock.

Opening a SQLite store for the first time creates MLflow's tables and runs its alembic migrations;
two processes doing that at once on a new file race ("duplicate column name", "table ... already
exists", "expected to match one row"). :func:`prepare_store` opens the store with an exclusive
``flock`` on ``<db>.lock`` held, so the second process waits and then finds the schema current.
Later opens of a current schema need no lock (SQLite's own locking covers the writes).
:func:`sqlite_path` (the database file of a ``sqlite:///`` URI) lives here, below
:mod:`spot.tracking.store`, which imports this module and re-exports it.
"""

from __future__ import annotations

import contextlib
import fcntl
from collections.abc import Iterator
from pathlib import Path

_prepared: set[str] = set()


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (relative or absolute); None for other URIs."""
    return Path(uri[len("sqlite:///") :]) if uri.startswith("sqlite:///") else None


@contextlib.contextmanager
def store_lock(db: Path) -> Iterator[None]:
    """An exclusive lock on ``<db>.lock`` (the file is created if missing; it is never removed, so
    that every process locks the same inode)."""
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def prepare_store(uri: str) -> None:
    """Create or migrate the SQLite store of ``uri`` under :func:`store_lock` (once per process);
    other URIs are left alone."""
    db = sqlite_path(uri)
    if db is None or uri in _prepared:
        return
    from mlflow.tracking import MlflowClient

    with store_lock(db):
        MlflowClient(uri).search_experiments(max_results=1)  # opens the store: tables and migrations
    _prepared.add(uri)
