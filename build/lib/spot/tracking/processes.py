"""Which process owns a RUNNING run, and closing the runs whose process is gone.

Every run spot opens is tagged with the host, pid and pid start time of the process that opened it
(:func:`process_tags`). A run left RUNNING by a process that died without closing it (``kill -9``,
out of memory, a node crash) is found by the next ``spot run``, ``spot sweep`` or ``spot tables``
on that store from the same host and marked KILLED with a ``failure_reason``
(:func:`close_dead_runs`). Runs of other hosts (or of another pid namespace, e.g. a container
with the same host name) are left alone: their processes cannot be checked from here.
"""

from __future__ import annotations

import os
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spot import runtime

HOST_TAG = "spot.host"
PID_TAG = "spot.pid"
STARTED_TAG = "spot.pid_started"
PIDNS_TAG = "spot.pid_ns"


def _pid_namespace() -> str:
    """This process's pid namespace (containers sharing a host name have their own), "" if unknown."""
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return ""


def _start_ticks(pid: int) -> str:
    """The process's start time in clock ticks since boot (``/proc/<pid>/stat`` field 22), "" if
    unknown; with the pid it names a process even after the pid is reused."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def process_tags() -> dict[str, str]:
    """``spot.host``, ``spot.pid``, ``spot.pid_started`` and ``spot.pid_ns`` of this process."""
    pid = os.getpid()
    return {
        HOST_TAG: socket.gethostname(),
        PID_TAG: str(pid),
        STARTED_TAG: _start_ticks(pid),
        PIDNS_TAG: _pid_namespace(),
    }


def alive(pid: int, started: str = "") -> bool:
    """Whether process ``pid`` of this host still runs (and, if ``started`` is given, is the same
    process, not a later one that got the pid)."""
    if not runtime.pid_alive(pid):
        return False
    now = _start_ticks(pid)
    return not (started and now and now != started)


def close_dead_runs(client: Any, experiment_ids: Sequence[str], *, report: bool = True) -> list[str]:
    """Mark KILLED the RUNNING runs of the experiments that a process of this host opened and that
    process is gone; return their ids (and print one line about them on stderr if ``report``)."""
    from spot.tracking.queries import search_runs, tag_filter

    host, namespace = socket.gethostname(), _pid_namespace()
    closed = []
    for run in search_runs(client, list(experiment_ids), tag_filter({HOST_TAG: host}, "RUNNING")):
        pid = run.data.tags.get(PID_TAG, "")
        if run.data.tags.get(PIDNS_TAG, namespace) != namespace:  # another container: cannot tell
            continue
        if not pid.isdigit() or alive(int(pid), run.data.tags.get(STARTED_TAG, "")):
            continue
        client.set_tag(
            run.info.run_id,
            "failure_reason",
            f"process {pid} on {host} ended without closing the run (closed by a later command)",
        )
        client.set_terminated(run.info.run_id, "KILLED")
        closed.append(run.info.run_id)
    if closed and report:
        print(
            f"note: {len(closed)} run(s) left RUNNING by dead processes on {host} marked KILLED: {', '.join(closed)}",
            file=sys.stderr,
            flush=True,
        )
    return closed


def close_dead_runs_in(tracking_uri: str | None, experiment_names: Sequence[str] | None = None) -> list[str]:
    """:func:`close_dead_runs` on the named experiments (all if none) of the store a reading
    command uses (``spot tables``); a store or experiment that does not exist is left to the
    command's own error."""
    from spot import SpotError
    from spot.tracking.store import experiments, reader

    try:
        client = reader(tracking_uri)
        ids = list(experiments(client, experiment_names))
    except SpotError:
        return []
    return close_dead_runs(client, ids)
