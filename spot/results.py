"""Finished results as small files: runs exported from MLflow to CSV, and read back as the same frame.

A sweep's runs live in an MLflow store, which is large, machine-local and not something to commit.
:func:`export` writes the runs frame of :func:`spot.tables.load_runs` (one row per run) to a CSV
with one row per run: identity (run id, experiment, sweep, status, method, dataset, source, seed),
``config_hash`` (SHA-256 of every param except ``seed`` and ``tracking.*``: runs of one cell share
it), ``data_digest`` and ``git_commit`` (tags the run logged), every ``params.*`` and the metrics
named by :data:`METRIC_PREFIXES` (last logged value), and each run's evaluation curve
(:data:`CURVE_COLUMN`: every logged ``eval/score`` as ``step:value`` pairs joined by ``;``) where
the export read it (:func:`add_curves`). :func:`read` returns the frame
:func:`spot.tables.build_table` and :mod:`spot.report` take, so every table and verdict can be
rebuilt from the committed file alone (``spot tables --results``, ``spot report --results``).

Reading never executes anything: the file is parsed by pandas as text and numbers, and every
column is checked against what an export writes.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from spot import SpotError

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
TAG_COLUMNS = {"sweep_id": "tags.sweep_id", "data_digest": "tags.data_digest", "git_commit": "tags.git_commit"}
REQUIRED = ("run_id", "experiment", "status", "method", "dataset", "seed")
CURVE_METRIC = "eval/score"  # the periodic evaluations' mean normalised score, logged at its IQL step
CURVE_COLUMN = f"curve.{CURVE_METRIC}"


def format_curve(points: Iterable[tuple[int, float]]) -> str:
    """``step:value`` pairs joined by ``;``, in step order (values to 4 decimals)."""
    return ";".join(f"{int(step)}:{float(value):.4f}" for step, value in sorted(points))


def parse_curve(text: object, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (int) and values (float) of a :func:`format_curve` string; empty arrays for no curve.
    Anything else is a :class:`SpotError` naming ``where``."""
    if text is None or (isinstance(text, float) and np.isnan(text)) or text is pd.NA or text == "":
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    steps, values = [], []
    for item in str(text).split(";"):
        step, sep, value = item.partition(":")
        try:
            if not sep:
                raise ValueError
            steps.append(int(step))
            values.append(float(value))
        except ValueError:
            raise SpotError(
                f"{where}: {CURVE_COLUMN} item {item[:40]!r} is not STEP:VALUE (an integer step, a number)"
            ) from None
    return np.asarray(steps, np.int64), np.asarray(values, np.float64)


def add_curves(runs: pd.DataFrame, client: Any) -> pd.DataFrame:
    """``runs`` with :data:`CURVE_COLUMN`: each run's :data:`CURVE_METRIC` history read from
    ``client`` (an ``MlflowClient``); empty for a run that logged none."""
    out = runs.copy()
    out[CURVE_COLUMN] = [
        format_curve((m.step, m.value) for m in client.get_metric_history(run_id, CURVE_METRIC))
        for run_id in runs["run_id"]
    ]
    return out


def config_hash(params: dict[str, str]) -> str:
    """SHA-256 (16 hex digits) of the params that define a cell: all but ``seed`` and ``tracking.*``."""
    keep = {k: str(v) for k, v in params.items() if k != "seed" and not k.startswith("tracking.") and not pd.isna(v)}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


def to_frame(runs: pd.DataFrame) -> pd.DataFrame:
    """The export's columns from a :func:`spot.tables.load_runs` frame."""
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
    out["config_hash"] = [config_hash({c[len("params.") :]: r[c] for c in params}) for _, r in runs.iterrows()]
    metrics = sorted(c for c in runs if c.startswith("metrics.") and c[len("metrics.") :].startswith(METRIC_PREFIXES))
    curves = [CURVE_COLUMN] if CURVE_COLUMN in runs else []
    out = pd.concat([out[list(ID_COLUMNS)], runs[params], runs[metrics], runs[curves]], axis=1)
    return out.sort_values(["experiment", "method", "dataset", "config_hash", "seed", "run_id"]).reset_index(drop=True)


def export(runs: pd.DataFrame, path: str | Path) -> Path:
    """Write ``runs`` (a :func:`spot.tables.load_runs` frame) as a results CSV; returns the path."""
    path = Path(path)
    if not path.parent.is_dir():
        raise SpotError(f"results file {path}: folder {path.parent} does not exist")
    frame = to_frame(runs)
    tmp = path.with_name(f".{path.name}.tmp")
    frame.to_csv(tmp, index=False)
    tmp.replace(path)
    return path


def read(paths: str | Path | Iterable[str | Path]) -> pd.DataFrame:
    """One frame from results CSVs (a file, a folder of ``*.csv``, or several), shaped like ``load_runs``."""
    files = _files(paths)
    frames = []
    for f in files:
        try:
            df = pd.read_csv(f, dtype=str, keep_default_na=False, na_values=[""])
        except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as e:
            raise SpotError(f"results file {f}: not a results CSV ({type(e).__name__}: {e})") from None
        missing = [c for c in REQUIRED if c not in df]
        if missing:
            raise SpotError(
                f"results file {f}: missing columns {missing}; expected a file written by `spot results export`"
            )
        frames.append(df)
        for run_id, text in zip(df["run_id"], df.get(CURVE_COLUMN, []), strict=False):
            parse_curve(text, f"results file {f}, run {run_id}")  # a clear error now, not in the report
    df = pd.concat(frames, ignore_index=True)
    for col in df:
        if col.startswith("metrics."):
            df[col] = pd.to_numeric(df[col], errors="coerce")
    df["seed"] = pd.to_numeric(df["seed"], errors="coerce").astype("Int64")
    for col in ("start_time", "end_time"):
        if col in df:
            df[col] = pd.to_datetime(df[col], errors="coerce")
    if df["run_id"].duplicated().any():
        dup = df.loc[df["run_id"].duplicated(), "run_id"].tolist()[:3]
        raise SpotError(f"results files {[str(f) for f in files]}: run ids appear twice, e.g. {dup}")
    return df


def _files(paths: str | Path | Iterable[str | Path]) -> list[Path]:
    items = [paths] if isinstance(paths, (str, Path)) else list(paths)
    files: list[Path] = []
    for p in map(Path, items):
        if p.is_dir():
            files.extend(sorted(p.glob("*.csv")))
        elif p.is_file():
            files.append(p)
        else:
            raise SpotError(f"results path {p} does not exist")
    if not files:
        raise SpotError(f"no results CSV files in {[str(p) for p in items]}")
    return files
