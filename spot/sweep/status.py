"""Where a sweep stands (``spot sweep FILE --status``): one line per (config, seed) of its last
launch, read from MLflow while the launch runs or after it ended; launches nothing.

A running (config, seed) shows its latest evaluation and how far its IQL has got; a finished one its
final score; a failed one its reason. Runs left RUNNING by a process of this host that is gone are
marked KILLED first, as every reading command does (:mod:`spot.tracking.processes`). Whether a
launch is running is read from its lock (``<storage>/<experiment>.lock``, held by the launching
process for as long as it lives).
"""

from __future__ import annotations

import fcntl
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.sweep.launch_record import lock_file, read_record, record_file
from spot.sweep.spec import Sweep
from spot.sweep.summary import Row, first_line, summarize, tag_value, text_table


@dataclass(frozen=True)
class Status:
    """A launch's rows, with the progress of each running (config, seed)."""

    sweep_id: str
    rows: list[Row]
    progress: dict[str, str]  # run key -> "eval 20.5 at 20000 / 300000 (3 min ago)"
    launcher: str = ""  # the lock holder's line ("pid 123 on host, since ...") while a launch runs
    previous: bool = False  # a new launch is starting: the rows are the previous launch's

    @property
    def exit_code(self) -> int:
        """0: every run finished; 3: still in progress (a launch runs, or a run is RUNNING); 1: the
        launch ended with runs not finished (failed, killed, never run)."""
        if self.launcher or any(r.status == "RUNNING" for r in self.rows):
            return 3
        return 0 if all(r.status == "FINISHED" for r in self.rows) else 1


def launcher(sweep: Sweep, storage: str | Path) -> str:
    """The holder line of the launch lock if a launch of this sweep runs with ``storage``, else ""."""
    lock = lock_file(record_file(sweep, storage))
    try:
        f = open(lock)
    except FileNotFoundError:
        return ""
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return f.read().strip() or "another process"
        fcntl.flock(f, fcntl.LOCK_UN)
        return ""


def launch_record(sweep: Sweep, storage: str | Path) -> dict[str, str]:
    """The record of the last launch under ``storage`` (``spot sweep --storage``), checked to be of
    this file as it is now."""
    state_file = record_file(sweep, storage)
    if not state_file.is_file():
        raise SpotError(f"sweep '{sweep.experiment}' was never launched with storage {state_file.parent}")
    try:
        state = read_record(state_file)
    except ValueError as e:
        raise SpotError(f"launch record {state_file} is damaged ({e})") from None
    if state["spec_hash"] != sweep.spec_hash():
        raise SpotError(
            f"sweep file '{sweep.path}' expands to other trials than its last launch {state['sweep_id']} "
            "(the file changed since): its status would list other (config, seed) than the launch ran"
        )
    return state


def _progress(client: Any, run_id: str, now_ms: int) -> str:
    run = client.get_run(run_id)
    total = run.data.params.get("iql.steps", "?")
    history = client.get_metric_history(run_id, "eval/score")
    if not history:
        return f"no evaluation yet (IQL steps {total})"
    last = max(history, key=lambda m: (m.step, m.timestamp))
    ago = max(0, now_ms - last.timestamp) // 60_000
    host = run.data.tags.get("spot.host", "")
    return f"eval {last.value:.1f} at {last.step} / {total} ({ago} min ago{', on ' + host if host else ''})"


def sweep_status(sweep: Sweep, tracking_uri: str, storage: str | Path) -> Status:
    """The last launch's rows from the store at ``tracking_uri`` (which must exist)."""
    from spot import tracking
    from spot.tracking.processes import close_dead_runs

    running = launcher(sweep, storage)
    if running and not record_file(sweep, storage).is_file():
        return Status("", [], {}, running)  # the first launch is starting: no record yet
    state = launch_record(sweep, storage)
    client = tracking.reader(tracking_uri)
    exp = client.get_experiment_by_name(sweep.experiment)
    if exp is None:
        raise SpotError(f"no experiment '{sweep.experiment}' in the MLflow store {tracking_uri}")
    try:
        parent = client.get_run(state["parent_run_id"])
    except Exception:  # noqa: BLE001 - MLflow raises its own error for a run it does not hold
        raise SpotError(
            f"the MLflow store {tracking_uri} does not hold launch {state['sweep_id']} (parent run "
            f"{state['parent_run_id']}); was it launched with another --tracking-uri or $MLFLOW_TRACKING_URI?"
        ) from None
    close_dead_runs(client, [exp.experiment_id])
    rows = summarize(sweep, client, exp.experiment_id, state["sweep_id"])
    now = int(time.time() * 1000)
    progress = {r.key: _progress(client, r.run_id, now) for r in rows if r.status == "RUNNING"}
    # A new launch holds the lock from its start but writes its record only once its parent run is open.
    previous = bool(running) and parent.info.status != "RUNNING"
    return Status(state["sweep_id"], rows, progress, running, previous)


def format_status(status: Status, axis_keys: tuple[str, ...], width: int = 70) -> str:
    """A plain-text table (axis values, seed, status, final score, progress or failure reason) and
    the counts per status."""
    header = [*axis_keys, "seed", "status", "score_final", "progress / reason"]
    body = [
        [
            *(tag_value(r.axes[k]) for k in axis_keys),
            str(r.seed),
            r.status,
            "" if r.score_final is None else f"{r.score_final:.2f}",
            status.progress.get(r.key) or first_line(r.reason, width),
        ]
        for r in status.rows
    ]
    tally = ", ".join(f"{n} {s.lower()}" for s, n in sorted(Counter(r.status for r in status.rows).items()))
    return f"{text_table(header, body)}\n\n{len(status.rows)} runs: {tally}"
