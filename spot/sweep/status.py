"""Where a sweep stands (``spot sweep FILE --status``): one line per (config, seed) of its last
launch, read from MLflow while the launch runs or after it ended; launches nothing.

A running (config, seed) shows its latest evaluation and how far its IQL has got; a finished one its
final score; a failed one its reason. Runs left RUNNING by a process of this host that is gone are
marked KILLED first, as every reading command does (:mod:`spot.tracking.processes`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.sweep.spec import Sweep
from spot.sweep.summary import Row, summarize, tag_value


@dataclass(frozen=True)
class Status:
    """A launch's rows, with the progress of each running (config, seed)."""

    sweep_id: str
    rows: list[Row]
    progress: dict[str, str]  # run key -> "eval 20.5 at 20000 / 300000 (3 min ago)"

    @property
    def done(self) -> bool:
        return all(r.status == "FINISHED" for r in self.rows)


def launch_id(sweep: Sweep, storage: str | Path) -> str:
    """The sweep id of the last launch recorded under ``storage`` (``spot sweep --storage``)."""
    state_file = Path(storage).resolve() / f"{sweep.experiment}.json"
    if not state_file.is_file():
        raise SpotError(f"sweep '{sweep.experiment}' was never launched with storage {state_file.parent}")
    try:
        state = json.loads(state_file.read_text())
        if not (isinstance(state, dict) and isinstance(state.get("sweep_id"), str) and state["sweep_id"]):
            raise ValueError("expected an object with a sweep_id")
    except (ValueError, UnicodeDecodeError) as e:
        raise SpotError(f"launch record {state_file} is damaged ({e})") from None
    return state["sweep_id"]


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

    sweep_id = launch_id(sweep, storage)
    client = tracking.reader(tracking_uri)
    exp = client.get_experiment_by_name(sweep.experiment)
    if exp is None:
        raise SpotError(f"no experiment '{sweep.experiment}' in the MLflow store {tracking_uri}")
    close_dead_runs(client, [exp.experiment_id])
    rows = summarize(sweep, client, exp.experiment_id, sweep_id)
    now = int(time.time() * 1000)
    progress = {r.key: _progress(client, r.run_id, now) for r in rows if r.status == "RUNNING"}
    return Status(sweep_id, rows, progress)


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
            status.progress.get(r.key) or (r.reason.splitlines() or [""])[0][:width],
        ]
        for r in status.rows
    ]
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
    lines = ["  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip() for line in (header, *body)]
    counts: dict[str, int] = {}
    for r in status.rows:
        counts[r.status] = counts.get(r.status, 0) + 1
    tally = ", ".join(f"{n} {s.lower()}" for s, n in sorted(counts.items()))
    rule = "  ".join("-" * w for w in widths)
    return "\n".join([lines[0], rule, *lines[1:], "", f"{len(status.rows)} runs: {tally}"])
