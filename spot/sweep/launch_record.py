"""The record of a sweep's last launch, ``<storage>/<experiment>.json`` (sweep id, spec hash, parent
run id), and the lock beside it that a running launch holds.

``--resume`` reads the record to continue the same launch; ``spot sweep FILE --status`` reads it to
find the launch's runs (:mod:`spot.sweep.status`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.sweep.spec import Sweep


def record_file(sweep: Sweep, storage: str | Path) -> Path:
    """``<storage>/<experiment>.json``: the record of the sweep's last launch with that storage."""
    return Path(storage).resolve() / f"{sweep.experiment}.json"


def lock_file(state_file: Path) -> Path:
    """The lock beside a launch record, ``<storage>/<experiment>.lock``: held while a launch runs."""
    return state_file.with_suffix(".lock")


def read_record(state_file: Path) -> dict[str, str]:
    """A launch record: sweep id, spec hash and parent run id; ValueError if it is damaged."""
    try:
        state = json.loads(state_file.read_text())
    except UnicodeDecodeError as e:
        raise ValueError(str(e)) from None
    if not (
        isinstance(state, dict)
        and all(isinstance(state.get(k), str) and state[k] for k in ("sweep_id", "spec_hash", "parent_run_id"))
    ):
        raise ValueError("expected an object with sweep_id, spec_hash and parent_run_id")
    return state


def write_record(state_file: Path, state: dict[str, Any]) -> None:
    """Write the launch record whole or not at all (a temporary file beside it, then renamed)."""
    tmp = state_file.with_name(f"{state_file.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(state, indent=2))
    tmp.replace(state_file)  # whole or not at all


def launch_state(sweep: Sweep, path: str | Path, state_file: Path, *, resume: bool) -> dict[str, Any]:
    """The launch record: a new sweep id, or the one being resumed (checked to expand the same)."""
    if not resume:
        return {
            "sweep_id": f"{sweep.experiment}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(2)}",
            "spec_hash": sweep.spec_hash(),
            "file": str(Path(path).resolve()),
        }
    if not state_file.is_file():
        raise SpotError(
            f"nothing to resume: no launch of sweep '{sweep.experiment}' under {state_file.parent}; "
            "start it without --resume"
        )
    try:
        state = read_record(state_file)
    except ValueError as e:
        raise SpotError(
            f"launch record {state_file} is damaged ({e}); it cannot be resumed: start a new launch without --resume"
        ) from None
    if state["spec_hash"] != sweep.spec_hash():
        raise SpotError(
            f"sweep file '{path}' expands to other trials than the launch {state['sweep_id']} "
            "being resumed; Ray cannot change a sweep's trials: start a new launch without --resume"
        )
    return state


@contextlib.contextmanager
def launch_lock(state_file: Path, experiment: str) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``<storage>/<experiment>.lock`` for the launch: a second
    launch (or ``--resume``) of the same sweep with the same storage refuses while one runs, so
    no launch overwrites another's record. The lock dies with the process, however it ends."""
    lock_path = lock_file(state_file)
    try:
        state_file.parent.mkdir(parents=True, exist_ok=True)
        f = open(lock_path, "a+")
    except OSError as e:
        raise SpotError(f"--storage {state_file.parent}: cannot keep the launch record there ({e.strerror})") from None
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise SpotError(
                f"sweep '{experiment}' is already running with storage {state_file.parent} "
                f"({holder}); wait for it to end, or give this launch another --storage"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        f.flush()
        yield
