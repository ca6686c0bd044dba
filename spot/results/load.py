"""The one run loader: runs from an MLflow store or from results CSVs, as one frame.

:func:`load` is what ``spot tables`` and ``spot report`` call: with ``results`` it reads results
CSVs (:func:`read`), else the store (:func:`load_runs`). Both frames have one row per run with
``run_id``, ``experiment``, ``status``, ``start_time``, ``method``, ``dataset`` (our name),
``paper_dataset`` (the paper's row name), ``dataset_source``, ``seed``, ``config_hash`` (SHA-256 of
every param but ``seed`` and ``tracking.*``: the runs of one config share it), ``params.<key>`` and
``metrics.<name>`` (last logged value); the store's frame also has every ``tags.<key>``, under the
names runs are tagged with now (``tags.spot.sweep_id``, ``tags.spot.cache.reward``: a store written
before the bookkeeping tags moved under ``spot.`` gives the same columns, :mod:`spot.tracking.tagnames`).

A results CSV is what ``spot results export`` writes (:mod:`spot.results.export`). Reading never
executes anything: the file is parsed by pandas as text and numbers, and every column is checked
against what an export writes.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from spot import SpotError, tracking
from spot.results.paper import paper_dataset_name

REQUIRED = ("run_id", "experiment", "status", "method", "dataset", "seed")
CURVE_METRIC = "eval/score"  # the periodic evaluations' mean normalised score, logged at its IQL step
CURVE_COLUMN = f"curve.{CURVE_METRIC}"
TAG_COLUMNS = {
    "sweep_id": "tags.spot.sweep_id",
    "data_digest": "tags.spot.data_digest",
    "git_commit": "tags.spot.git_commit",
}
"""Results-CSV columns (:mod:`spot.results.export`) and the store frame's tag columns they come from."""
_RUN_COLUMNS = (
    "run_id",
    "run_name",
    "experiment_id",
    "experiment",
    "status",
    "start_time",
    "end_time",
    "artifact_uri",
    "method",
    "dataset",
    "paper_dataset",
    "dataset_source",
    "seed",
    "config_hash",
)

Paths = str | Path | Iterable[str | Path]


def load(
    results: Paths | None = None,
    tracking_uri: str | None = None,
    experiments: Sequence[str] | None = None,
    sweep_id: str | None = None,
) -> pd.DataFrame:
    """Every run of ``experiments`` (all if ``None``): from the results CSVs ``results`` (files or
    folders of ``*.csv``) when given, else from the MLflow store at ``tracking_uri`` (only the runs of
    sweep ``sweep_id`` when given; a results file has no sweep filter)."""
    if results is None:
        return load_runs(tracking_uri, experiments, sweep_id)
    runs = read(results)
    return runs[runs["experiment"].isin(experiments)] if experiments else runs


def config_hash(params: dict[str, str]) -> str:
    """SHA-256 (16 hex digits) of the params that define a cell: all but ``seed`` and ``tracking.*``."""
    keep = {k: str(v) for k, v in params.items() if k != "seed" and not k.startswith("tracking.") and not pd.isna(v)}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


def config_hashes(runs: pd.DataFrame) -> list[str]:
    """:func:`config_hash` of every run of ``runs`` (from its ``params.*`` columns)."""
    params = sorted(c for c in runs if c.startswith("params."))
    return [config_hash({c[len("params.") :]: r[c] for c in params}) for _, r in runs.iterrows()]


# --------------------------------------------------------------------------- MLflow
def load_runs(
    tracking_uri: str | None = None, experiment_names: Sequence[str] | None = None, sweep_id: str | None = None
) -> pd.DataFrame:
    """Every run of the experiments (all experiments if ``None``) in the store, one row per run.

    Sweep parent runs (runs without a ``method`` tag) are left out. Columns follow
    ``mlflow.search_runs``: ``run_id``, ``experiment``, ``status``, ``start_time``, ...,
    ``params.<key>``, ``metrics.<name>`` (last logged value) and ``tags.<key>`` (stored names, also
    for runs tagged with the old bare ones: :func:`spot.tracking.tagnames.normalized`), plus ``method``,
    ``dataset`` (our name), ``paper_dataset`` (the paper's row name), ``dataset_source``, ``seed``
    and ``config_hash``. All statuses are kept: :func:`spot.results.select.finished` picks the runs
    that count.
    """
    client = tracking.reader(tracking_uri)
    experiments = tracking.experiments(client, experiment_names)
    ids = list(experiments)
    found = tracking.search_runs(client, ids)
    if sweep_id:  # tagged spot.sweep_id, or sweep_id by older versions
        found = tracking.search_tagged(client, ids, {"sweep_id": sweep_id})
    rows = [_run_row(run, experiments) for run in found]
    df = pd.DataFrame(rows)
    if df.empty:
        return pd.DataFrame(columns=list(_RUN_COLUMNS))
    if "tags.method" not in df:
        df["tags.method"] = np.nan
    df = df[df["tags.method"].notna()].copy()
    for col in ("tags.dataset", "tags.spot.dataset_source", "tags.seed", "params.seed"):
        if col not in df:
            df[col] = np.nan
    df["method"] = df["tags.method"].astype(str)
    df["dataset"] = df["tags.dataset"].fillna("unknown").astype(str)
    df["paper_dataset"] = df["dataset"].map(paper_dataset_name)
    df["dataset_source"] = df["tags.spot.dataset_source"].fillna("unknown").astype(str)
    df["seed"] = pd.to_numeric(df["tags.seed"].fillna(df["params.seed"]), errors="coerce").astype("Int64")
    df["config_hash"] = config_hashes(df)
    first = [c for c in _RUN_COLUMNS if c in df]
    return df[first + sorted(c for c in df if c not in first)].reset_index(drop=True)


def _run_row(run: Any, experiments: dict[str, str]) -> dict[str, Any]:
    info, data = run.info, run.data
    row: dict[str, Any] = {
        "run_id": info.run_id,
        "run_name": info.run_name,
        "experiment_id": info.experiment_id,
        "experiment": experiments[info.experiment_id],
        "status": info.status,
        "start_time": pd.to_datetime(info.start_time, unit="ms"),
        "end_time": pd.to_datetime(info.end_time, unit="ms") if info.end_time else pd.NaT,
        "artifact_uri": info.artifact_uri,
    }
    row.update({f"params.{k}": v for k, v in data.params.items()})
    row.update({f"metrics.{k}": v for k, v in data.metrics.items()})
    row.update({f"tags.{k}": v for k, v in tracking.tagnames.normalized(data.tags).items()})  # old names too
    return row


# --------------------------------------------------------------------------- results CSVs
def parse_curve(text: object, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (int) and values (float) of a ``step:value;...`` curve string; empty arrays for no
    curve. Anything else is a :class:`SpotError` naming ``where``."""
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


def read(paths: Paths) -> pd.DataFrame:
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
    if "config_hash" not in df:  # a file written by hand: the hash from its params
        df["config_hash"] = config_hashes(df)
    for col in ("start_time", "end_time"):
        if col in df:
            df[col] = pd.to_datetime(df[col], errors="coerce")
    if df["run_id"].duplicated().any():
        dup = df.loc[df["run_id"].duplicated(), "run_id"].tolist()[:3]
        raise SpotError(f"results files {[str(f) for f in files]}: run ids appear twice, e.g. {dup}")
    return df


def _files(paths: Paths) -> list[Path]:
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
