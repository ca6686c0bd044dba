"""The Python entry to results (docs/python.md): runs as a DataFrame, a paper table, the claims report.

Three calls, each the same code path as its command:

* :func:`load_runs`: a study folder, results CSVs or an MLflow store -> one row per run;
* :func:`table`: a paper table from that frame (``spot tables --table N``);
* :func:`claims_report`: the claims answered from that frame (``spot report``), as Markdown.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import pandas as pd

from spot.results import claims as claims_lib
from spot.results import export, load, report, table_format, tables


def load_runs(
    source: load.Paths | None = None,
    *,
    tracking_uri: str | None = None,
    experiments: Sequence[str] | None = None,
    sweep_id: str | None = None,
) -> pd.DataFrame:
    """Runs as a DataFrame, one row per run (columns in :mod:`spot.results.load`), every status.

    Args:
      source: a study folder (``experiments/<study>/``: the results its ``claims.yaml`` names), results
        CSVs (a file, a folder of ``*.csv``, or several), or ``None``: the MLflow store.
      tracking_uri: the store (``None``: ``$MLFLOW_TRACKING_URI``, else the folder's default store).
      experiments: only these experiments (``None``: all).
      sweep_id: only the runs of this sweep (tag ``sweep_id``; the store only).

    ``frame[frame.status == "FINISHED"]`` are the runs that count in tables and reports.
    """
    if source is None:
        return load.load_runs(tracking_uri, experiments, sweep_id)
    frame = load.load(_results(source), experiments=experiments)
    if sweep_id is None:
        return frame
    return frame[frame["sweep_id"] == sweep_id] if "sweep_id" in frame else frame.iloc[:0]


def _results(source: load.Paths) -> load.Paths:
    """A study folder's results (those its claims file names), else ``source`` itself."""
    if isinstance(source, (str, Path)) and (Path(source) / claims_lib.STUDY_FILE).is_file():
        return list(claims_lib.load(claims_lib.study_file(source)).results)
    return source


def table(
    runs: pd.DataFrame,
    number: int,
    *,
    metric: str = "eval/score_final",
    fmt: str | None = None,
    ddof: int = 1,
    allow_mixed: bool = False,
) -> pd.DataFrame | str:
    """Paper table ``number`` (1, 2, 3, 4, 7, 8) from ``runs``, the paper's numbers beside ours.

    ``fmt=None`` returns the table as a DataFrame (:func:`spot.results.tables.build_table`); ``"md"``,
    ``"latex"``, ``"csv"`` or ``"text"`` returns the text ``spot tables --table N --format FMT``
    prints for the same runs (Table 1 in Markdown with its across-datasets lines).
    """
    wide = tables.build_table(runs, number, metric, ddof=ddof, allow_mixed=allow_mixed)
    if fmt is None:
        return wide
    text = table_format.format_table(wide, fmt)
    if number == 1 and fmt == "md":
        text += table_format.across_datasets(runs, metric)
    return text


def claims_report(
    runs: pd.DataFrame,
    claims: str | Path | None = None,
    *,
    use: Mapping[str, Sequence[str]] | None = None,
    high_mode: float = 50.0,
) -> str:
    """The claims report (Markdown, what ``spot report`` writes) answered from ``runs``.

    ``claims``: a claims file or a study folder (its ``claims.yaml``); ``None``: the paper's
    claims. ``use``: replace sets of the claims file by experiments (``{"P": ["my_exp"]}``, as
    ``--use P=my_exp``). A frame from the store (with ``tags.*`` columns) is first cut to a results
    CSV's columns, as ``spot report`` does.
    """
    if claims is not None and Path(claims).is_dir():
        claims = claims_lib.study_file(claims)
    parsed = claims_lib.load(claims, use)
    if any(c.startswith("tags.") for c in runs):
        runs = export.to_frame(runs)
    return report.format_report(report.build(runs, parsed, high_mode))
