"""Finished results as small files: runs exported from MLflow to a CSV to commit.

A sweep's runs live in an MLflow store, which is large, machine-local and not something to commit.
:func:`export` writes the runs frame of :func:`spot.results.load.load_runs` (one row per run) to a
CSV with one row per run: identity (run id, experiment, sweep, status, method, dataset, source,
seed), ``config_hash`` (SHA-256 of every param except ``seed`` and ``tracking.*``: runs of one cell
share it), ``data_digest`` and ``git_commit`` (tags the run logged), every ``params.*`` and the
metrics named by :data:`METRIC_PREFIXES` (last logged value), and each run's evaluation curve
(:data:`~spot.results.load.CURVE_COLUMN`: every logged ``eval/score`` as ``step:value`` pairs
joined by ``;``) where the export read it (:func:`add_curves`). :func:`spot.results.load.read`
reads it back as the frame ``spot tables`` and ``spot report`` take, so every table and verdict can
be rebuilt from the committed file alone.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from spot import SpotError
from spot.results.load import CURVE_COLUMN, CURVE_METRIC, TAG_COLUMNS, config_hashes

ID_COLUMNS = (
    "run_id",
    "experiment",
    "sweep_id",
    "status",
    "method",
    "dataset",
    "paper_dataset",
    "dataset_source",
    "seed",
    "config_hash",
    "data_digest",
    "git_commit",
    "start_time",
    "end_time",
)
METRIC_PREFIXES = ("eval/", "diag/", "time/", "cache/", "reward/", "cvae/", "subgoal/", "shaping/", "iql/")


def format_curve(points: Iterable[tuple[int, float]]) -> str:
    """``step:value`` pairs joined by ``;``, in step order (values to 4 decimals)."""
    return ";".join(f"{int(step)}:{float(value):.4f}" for step, value in sorted(points))


def add_curves(runs: pd.DataFrame, client: Any) -> pd.DataFrame:
    """``runs`` with :data:`~spot.results.load.CURVE_COLUMN`: each run's ``eval/score`` history read
    from ``client`` (an ``MlflowClient``); empty for a run that logged none."""
    out = runs.copy()
    out[CURVE_COLUMN] = [
        format_curve((m.step, m.value) for m in client.get_metric_history(run_id, CURVE_METRIC))
        for run_id in runs["run_id"]
    ]
    return out


def to_frame(runs: pd.DataFrame) -> pd.DataFrame:
    """The export's columns from a :func:`spot.results.load.load_runs` frame."""
    out = pd.DataFrame(index=runs.index)
    for col in (
        "run_id",
        "experiment",
        "status",
        "method",
        "dataset",
        "paper_dataset",
        "dataset_source",
        "seed",
        "start_time",
        "end_time",
    ):
        out[col] = runs[col] if col in runs else pd.NA
    for col, tag in TAG_COLUMNS.items():
        out[col] = runs[tag] if tag in runs else pd.NA
    params = sorted(c for c in runs if c.startswith("params."))
    out["config_hash"] = config_hashes(runs)
    metrics = sorted(c for c in runs if c.startswith("metrics.") and c[len("metrics.") :].startswith(METRIC_PREFIXES))
    curves = [CURVE_COLUMN] if CURVE_COLUMN in runs else []
    out = pd.concat([out[list(ID_COLUMNS)], runs[params], runs[metrics], runs[curves]], axis=1)
    return out.sort_values(["experiment", "method", "dataset", "config_hash", "seed", "run_id"]).reset_index(drop=True)


def export(runs: pd.DataFrame, path: str | Path) -> Path:
    """Write ``runs`` (a :func:`spot.results.load.load_runs` frame) as a results CSV; returns the path."""
    path = Path(path)
    if not path.parent.is_dir():
        raise SpotError(f"results file {path}: folder {path.parent} does not exist")
    frame = to_frame(runs)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        frame.to_csv(tmp, index=False)
        tmp.replace(path)
    except OSError as err:
        tmp.unlink(missing_ok=True)  # nothing half-written stays behind
        raise SpotError(f"results file {path}: cannot write it ({err.strerror})") from None
    return path
