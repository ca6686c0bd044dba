"""The end of a launch: one row per (config, seed) from MLflow, as a plain-text table, and the
sweep's paper table (ours beside the paper's, :mod:`spot.tables`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.sweep.spec import Sweep, run_key, tag_value


@dataclass(frozen=True)
class Row:
    """One (config, seed) line of the summary."""

    axes: dict[str, Any]
    seed: int
    key: str
    status: str
    score_final: float | None
    reason: str
    run_id: str
    finished_runs: int


def _row(axes: dict[str, Any], seed: int, key: str, runs: list[Any], ray_error: str | None) -> Row:
    finished = [r for r in runs if r.info.status == "FINISHED"]
    if finished:
        r = finished[0]
        return Row(
            axes, seed, key, "FINISHED", r.data.metrics.get("eval/score_final"), "", r.info.run_id, len(finished)
        )
    if runs:
        r = max(runs, key=lambda r: r.info.start_time or 0)
        return Row(axes, seed, key, r.info.status, None, r.data.tags.get("failure_reason", ""), r.info.run_id, 0)
    return Row(axes, seed, key, "ERROR" if ray_error else "NOT RUN", None, ray_error or "", "", 0)


def summarize(
    sweep: Sweep, client: Any, experiment_id: str, sweep_id: str, ray_errors: dict[str, str] | None = None
) -> list[Row]:
    """One :class:`Row` per (config, seed) from the sweep's MLflow runs (and Ray's trial errors)."""
    from spot import tracking

    by_key: dict[str, list[Any]] = {}
    for r in tracking.search_runs(client, [experiment_id], tracking.tag_filter({"sweep_id": sweep_id})):
        if "trial_key" in r.data.tags:
            by_key.setdefault(r.data.tags["trial_key"], []).append(r)
    rows = []
    for trial, seed in sweep.runs():
        key = run_key(trial.overrides, seed)
        rows.append(_row(trial.axes, seed, key, by_key.get(key, []), (ray_errors or {}).get(key)))
    return rows


def format_summary(rows: list[Row], axis_keys: tuple[str, ...], width: int = 70) -> str:
    """A plain-text table: axis values, seed, score_final, status, failure reason."""
    header = [*axis_keys, "seed", "score_final", "status", "reason"]
    body = [
        [
            *(tag_value(r.axes[k]) for k in axis_keys),
            str(r.seed),
            "" if r.score_final is None else f"{r.score_final:.2f}",
            r.status,
            (r.reason.splitlines() or [""])[0][:width],
        ]
        for r in rows
    ]
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
    lines = ["  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip() for line in (header, *body)]
    return "\n".join([lines[0], "  ".join("-" * w for w in widths), *lines[1:]])


def paper_table(sweep: Sweep, uri: str, sweep_id: str, out_dir: Path | None = None) -> str:
    """The sweep's paper table (ours beside the paper's) from this launch's finished runs, compact
    enough for a 120-column terminal; with ``out_dir`` the full Markdown table (CIs, Δ, notes) is
    written to ``out_dir/<sweep id>-table<N>.md`` and the text says where."""
    from spot import tables

    runs = tables.load_runs(uri, [sweep.experiment], sweep_id=sweep_id)
    try:
        table = tables.build_table(runs, sweep.table)
    except SpotError as e:  # e.g. a sweep whose runs do not form that table
        return f"(no Table {sweep.table}: {e})"
    text = tables.format_table(table, "text", width=120)
    if out_dir is not None:
        path = Path(out_dir) / f"{sweep_id}-table{sweep.table}.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(tables.format_table(table, "md"))
        text += f"full table with CIs and notes: {path}\n"
    return text
