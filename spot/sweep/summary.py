"""The end of a launch: one row per (config, seed) from MLflow, as a plain-text table, where the
trials' time went (:func:`format_breakdown`) and the sweep's paper table (ours beside the paper's,
:mod:`spot.results.tables`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
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
    trial_id: str = ""
    timing: dict[str, float] = field(default_factory=dict)  # the trial's time/trial_* and trial/* metrics
    device: str = ""  # the spot.trial_device tag: what JAX ran on


def _row(axes: dict[str, Any], seed: int, key: str, runs: list[Any], ray_error: str | None) -> Row:
    from spot.tracking import tagnames

    finished = [r for r in runs if r.info.status == "FINISHED"]
    if finished:
        r = finished[0]
        m = r.data.metrics
        return Row(
            axes,
            seed,
            key,
            "FINISHED",
            m.get("eval/score_final"),
            "",
            r.info.run_id,
            len(finished),
            trial_id=tagnames.get(r.data.tags, "trial_id"),
            timing={k: v for k, v in m.items() if k.startswith(("time/trial_", "trial/"))},
            device=tagnames.get(r.data.tags, "trial_device"),
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
    from spot.tracking import tagnames

    by_key: dict[str, list[Any]] = {}
    parents = []
    for r in tracking.search_tagged(client, [experiment_id], {"sweep_id": sweep_id}):  # spot.sweep_id or sweep_id
        if tagnames.has(r.data.tags, "trial_key"):
            by_key.setdefault(tagnames.get(r.data.tags, "trial_key"), []).append(r)
        else:
            parents.append(r.info.run_id)
    if parents:
        share_view(client, experiment_id, sweep_id, parents[0], sweep.axis_keys)
    rows = []
    if sweep.search is not None:  # the configs the searcher proposed: the runs there are
        for key, runs in by_key.items():
            tags = runs[0].data.tags
            axes = {k: tags.get(f"axis.{k}", "") for k in sweep.axis_keys}
            rows.append(_row(axes, int(tags.get("seed", -1)), key, runs, (ray_errors or {}).get(key)))
        return sorted(rows, key=lambda r: (r.trial_id, r.seed))
    for trial, seed in sweep.runs():
        key = run_key(trial.overrides, seed)
        rows.append(_row(trial.axes, seed, key, by_key.get(key, []), (ray_errors or {}).get(key)))
    return rows


def share_view(client: Any, experiment_id: str, sweep_id: str, parent_run_id: str, axis_keys: tuple[str, ...]) -> None:
    """The view the printed link opens (:func:`spot.tracking.ui.share_sweep_view`: the trials' runs
    with their method, dataset, seed, axes and scores as columns); a store that refuses the
    experiment tag leaves the link on MLflow's own view, with a note."""
    from spot import tracking
    from spot.sweep.signals import say

    try:
        tracking.ui.share_sweep_view(client, experiment_id, sweep_id, parent_run_id, axis_keys)
    except Exception as e:  # noqa: BLE001 - the summary matters more than the link's columns
        say(f"note: the sweep's view of the runs table was not saved ({type(e).__name__}: {e})")


def text_table(header: list[str], body: list[list[str]]) -> str:
    """Columns padded to their widest cell, two spaces apart, a rule of dashes under the header."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
    lines = ["  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip() for line in (header, *body)]
    return "\n".join([lines[0], "  ".join("-" * w for w in widths), *lines[1:]])


def first_line(reason: str, width: int = 70) -> str:
    """A failure reason's first line, cut to ``width`` characters."""
    return (reason.splitlines() or [""])[0][:width]


def format_summary(rows: list[Row], axis_keys: tuple[str, ...], width: int = 70) -> str:
    """A plain-text table: axis values, seed, score_final, status, failure reason."""
    header = [*axis_keys, "seed", "score_final", "status", "reason"]
    body = [
        [
            *(tag_value(r.axes[k]) for k in axis_keys),
            str(r.seed),
            "" if r.score_final is None else f"{r.score_final:.2f}",
            r.status,
            first_line(r.reason, width),
        ]
        for r in rows
    ]
    return text_table(header, body)


def paper_table(sweep: Sweep, uri: str, sweep_id: str, out_dir: Path | None = None) -> str:
    """The sweep's paper table (ours beside the paper's) from this launch's finished runs, compact
    enough for a 120-column terminal; with ``out_dir`` the full Markdown table (CIs, Δ, notes) is
    written to ``out_dir/<sweep id>-table<N>.md`` and the text says where."""
    from spot.results import load, table_format, tables

    runs = load.load_runs(uri, [sweep.experiment], sweep_id=sweep_id)
    try:
        table = tables.build_table(runs, sweep.table)
    except SpotError as e:  # e.g. a sweep whose runs do not form that table
        return f"(no Table {sweep.table}: {e})"
    text = table_format.format_table(table, "text", width=120)
    if out_dir is not None:
        path = Path(out_dir) / f"{sweep_id}-table{sweep.table}.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(table_format.format_table(table, "md"))
        text += f"full table with CIs and notes: {path}\n"
    return text


# --------------------------------------------------------------------------- where the time went
PHASE_COLUMNS = ("startup", "data", "compile", "train", "evaluate", "tracking", "other")


def log_fit_cpu(client: Any, parent_run_id: str, meter: Any) -> None:
    """The Tune experiment's wall time, the CPU seconds of the driver's process tree over it and
    their ratio to the machine's cores (:class:`spot.phases.CpuMeter`) on the parent run:
    ``sweep/fit_wall_s``, ``sweep/fit_cpu_s``, ``sweep/cpus``, ``sweep/cpu_util``."""
    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    values = {
        "sweep/fit_wall_s": meter.wall_s,
        "sweep/fit_cpu_s": meter.cpu_s,
        "sweep/cpus": meter.cpus,
        "sweep/cpu_util": meter.util,
    }
    client.log_batch(parent_run_id, metrics=[Metric(k, float(v), now, 0) for k, v in values.items()])


def _trials(rows: list[Row]) -> list[tuple[str, list[Row]]]:
    """The timed trials (their first row carries the trial's breakdown), in the rows' order."""
    out: dict[str, list[Row]] = {}
    for r in rows:
        if r.timing and r.trial_id:
            out.setdefault(r.trial_id, []).append(r)
    return list(out.items())


def format_breakdown(
    rows: list[Row], axis_keys: tuple[str, ...], fit: dict[str, float] | None = None, per_trial: bool = False
) -> str:
    """Where the trials' time went: seconds per phase (:mod:`spot.phases`) summed over the trials
    that ran in this launch, each phase's share of their wall time, the CPU utilisation of the
    trials (their process's CPU seconds over wall time and CPUs) and, with ``fit`` (the parent
    run's ``sweep/*`` metrics of :func:`log_fit_cpu`), of the whole sweep; with ``per_trial`` one
    line per trial first. Empty if no trial was timed."""
    trials = _trials(rows)
    if not trials:
        return ""
    header = ["trial", *PHASE_COLUMNS, "wall", "cpu%"]

    def cells(label: str, t: dict[str, float], util: float | None) -> list[str]:
        return [
            label,
            *(f"{t.get(f'time/trial_{p}_s', 0.0):.1f}" for p in PHASE_COLUMNS),
            f"{t.get('time/trial_wall_s', 0.0):.1f}",
            "" if util is None else f"{100 * util:.0f}",
        ]

    body = []
    if per_trial:
        for _, trial_rows in trials:
            r = trial_rows[0]
            seeds = ",".join(str(x.seed) for x in trial_rows)
            label = ",".join([*(f"{tag_value(r.axes[k])}" for k in axis_keys), f"s{seeds}"])
            body.append(cells(label[:40], r.timing, r.timing.get("trial/cpu_util")))
    total = {k: sum(rs[0].timing.get(k, 0.0) for _, rs in trials) for k in trials[0][1][0].timing}
    cpu_s = total.get("time/trial_cpu_s", 0.0)
    cpu_time = sum(  # per trial: wall seconds of the trial function x its CPUs
        rs[0].timing.get("time/trial_cpu_s", 0.0) / rs[0].timing["trial/cpu_util"]
        for _, rs in trials
        if rs[0].timing.get("trial/cpu_util")
    )
    body.append(cells(f"total ({len(trials)} trials)", total, cpu_s / cpu_time if cpu_time > 0 else None))
    wall = total.get("time/trial_wall_s", 0.0) or 1.0
    body.append(["share", *(f"{100 * total.get(f'time/trial_{p}_s', 0.0) / wall:.0f}%" for p in PHASE_COLUMNS), "", ""])
    widths = [max(len(x[i]) for x in (header, *body)) for i in range(len(header))]

    def line(xs: list[str]) -> str:
        return "  ".join([xs[0].ljust(widths[0]), *(x.rjust(w) for x, w in zip(xs[1:], widths[1:], strict=True))])

    out = ["where the trials' time went (seconds):", line(header), "  ".join("-" * w for w in widths), *map(line, body)]
    out.append("cpu%: the trial process's CPU seconds over the trial function's wall time times the CPUs it had")
    if "trial/compiles" in total:  # spot.phases counts the programs each trial handed to XLA
        out.append(
            f"programs: {total['trial/compiles']:.0f} compiled or loaded, "
            f"{total.get('trial/compile_cache_hits', 0.0):.0f} of them from the persistent compilation cache"
        )
    if fit and fit.get("sweep/fit_wall_s"):
        out.append(
            f"sweep: {fit['sweep/fit_wall_s']:.0f} s in Tune, {fit['sweep/fit_cpu_s']:.0f} CPU-seconds of the "
            f"launch's processes (driver, Ray, trials, MLflow server): CPU utilisation "
            f"{100 * fit['sweep/cpu_util']:.0f}% of {fit['sweep/cpus']:.0f} cores"
        )
    devices = sorted({r.device for _, rs in trials for r in rs if r.device})
    if devices:
        out.append(f"device (jax.devices()): {'; '.join(devices)}")
    return "\n".join(out)


def breakdown_text(client: Any, parent_run_id: str, rows: list[Row], axis_keys: tuple[str, ...]) -> str:
    """:func:`format_breakdown` of a launch's rows with its parent run's ``sweep/*`` metrics."""
    try:
        fit = {k: v for k, v in client.get_run(parent_run_id).data.metrics.items() if k.startswith("sweep/")}
    except Exception:  # noqa: BLE001 - the trials' own figures are still worth printing
        fit = None
    return format_breakdown(rows, axis_keys, fit)
