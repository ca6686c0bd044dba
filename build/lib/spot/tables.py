"""The paper's tables rebuilt from MLflow runs, with the paper's numbers beside ours.

:func:`load_runs` reads the runs of one or more experiments (optionally one sweep) into a pandas
frame; :func:`build_table` turns the finished ones into Table 1, 2, 3, 4, 7 or 8 of the SPOT paper;
:func:`format_table` prints it as Markdown, LaTeX or CSV. The CLI (``spot tables``) and the
notebooks in ``analysis/`` call these three functions and nothing else.

How a table cell is made:

* A cell is one (row, column) key, e.g. (``hopper-medium-replay``, ``spot``) in Table 1. Its runs
  are the FINISHED runs with that key; FAILED, KILLED and still-running runs never enter a cell
  and are listed in the table's notes instead. If two finished runs share a cell and a seed, the
  later one counts (a re-run replaces the earlier run).
* Ours = mean and standard deviation over the cell's runs (one per seed). The std is the sample
  std (``ddof=1``) by default; the paper does not say which it used. ``n`` = seeds in the cell.
* The paper's value comes from ``spot/paper_tables.csv`` (a copy of the numbers transcribed from
  the paper) and ``diff`` = ours − paper (means).
* Runs built from different dataset sources (``recipe``: built locally with spot's recipes;
  ``file``: read from dataset files such as the original D4RL hdf5) are never averaged together:
  ``source`` is always the last row-index level, so each source gets its own rows.
* Runs in one cell must share every param except ``seed`` and ``tracking.*``; a cell whose runs
  differ elsewhere (say ``iql.steps``) is refused with the differing keys named, unless
  ``allow_mixed=True`` (then the table's notes list them).
* ``best`` marks the paper's bold: in score tables, ours ≥ 95% of the best of ours (per row in
  Tables 1, 3, 7, with Oracle left out in Table 1 as the paper does; per column in Table 2).

The returned frame has a row index of the table's row keys plus ``source``, and columns
``(column key, field)`` with fields :data:`FIELDS`; ``table.attrs`` holds the title, notes and the
list of excluded runs.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from spot import SpotError, stats, tracking
from spot.config import METHODS

TABLES = (1, 2, 3, 4, 7, 8)
FIELDS = ("mean", "std", "n", "ci_low", "ci_high", "paper", "paper_std", "diff", "best")
FORMATS = ("md", "latex", "csv", "text")
METHOD_ORDER = METHODS  # the config's method order: columns of Table 1, curves of Fig. 2
METHOD_LABELS = {"oracle": "Oracle", "mr": "MR", "pt": "PT", "ipl": "IPL", "hpl": "HPL", "spot": "SPOT"}
SOURCE_ORDER = ("recipe", "file")
SOURCE_NOTES = {
    "recipe": "built locally with spot's dataset recipes, not the paper's D4RL/robomimic/Meta-World data",
    "file": "read from dataset files (e.g. the original D4RL/robomimic hdf5)",
}
SHAPING_ORDER = ("neg_distance", "potential", "cosine", "?")
CVAE_LOSS_ORDER = ("mse", "mse_cos")
CVAE_LOSS_FROM_PAPER = {"mse": "mse", "mse+cosine": "mse_cos"}
TIME_COLUMNS = ("reward_model_s", "offline_rl_s", "total_s", "wall_s")
REWARD_MODEL_STAGES = ("reward", "relabel")
SUBGOAL_STAGES = ("subgoals", "cvae", "shaping")  # reward-model time only where shaping is on
OFFLINE_RL_STAGES = ("iql", "eval")
CACHE_HIT_TAGS = ("cache.reward", "cache.relabel", "cache.cvae")  # "hit" | "miss"
CACHE_HIT_METRICS = ("cache/reward_hit", "cache/relabel_hit", "cache/cvae_hit")  # runs logged before the tags
BEST_FRACTION = 0.95
# The MLflow experiment each table's sweep writes (sweeps/<name>.yaml; `--smoke` adds "-smoke").
SWEEP_EXPERIMENTS = {
    1: "table1",
    2: "table2_topk",
    3: "table3_shaping",
    4: "table4_queries",
    7: "table7_cvae_loss",
    8: "table1",
}
AVERAGE_ROW = "average"
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
)


# --------------------------------------------------------------------------- the paper's numbers
@cache
def paper_tables() -> pd.DataFrame:
    """The paper's numbers: columns table, dataset, method, setting, mean, std, note."""
    with resources.files("spot").joinpath("paper_tables.csv").open("r", encoding="utf-8") as fh:
        df = pd.read_csv(fh)
    for col in ("setting", "note"):
        df[col] = df[col].fillna("").astype(str)
    return df


@cache
def _paper_datasets() -> tuple[str, ...]:
    names = paper_tables()["dataset"]
    return tuple(dict.fromkeys(n for n in names if n != AVERAGE_ROW))


def paper_dataset_name(name: str) -> str:
    """Our dataset name -> the paper's row name where one matches, else ``name`` unchanged.

    ``hopper-medium-replay-v2`` -> ``hopper-medium-replay``; ``lift_mh_low_dim`` -> ``lift-mh``.
    """
    n = str(name).strip().lower().replace("_", "-")
    n = re.sub(r"-v\d+$", "", n)
    n = re.sub(r"-low-dim$", "", n)
    return n if n in _paper_datasets() else str(name)


def _setting(setting: str, key: str) -> str:
    for part in setting.split(";"):
        k, _, v = part.partition("=")
        if k.strip() == key:
            return v.strip()
    raise SpotError(f"paper table setting {setting!r} has no {key!r}")


def _note_seconds(note: str, what: str) -> float:
    m = re.search(rf"{what} (\d+) s", note)
    return float(m.group(1)) if m else float("nan")


def paper_cells(table: int) -> pd.DataFrame:
    """The paper's cells of ``table`` keyed like :func:`build_table`'s cells (row keys + column)."""
    spec = _spec(table)
    p = paper_tables()
    p = p[(p["table"] == table) & (p["dataset"] != AVERAGE_ROW)]
    out = pd.DataFrame({"paper": p["mean"].astype(float), "paper_std": p["std"].astype(float)})
    if table == 1:
        out["dataset"], out[spec.col] = p["dataset"], p["method"]
    elif table == 2:
        out["group"], out[spec.col] = p["setting"], p["dataset"]
    elif table == 3:
        out["dataset"] = p["dataset"]
        out["shaping.kind"] = [_setting(s, "shaping") for s in p["setting"]]
        out[spec.col] = [float(_setting(s, "lambda")) for s in p["setting"]]
    elif table == 4:
        out["dataset"], out["method"] = p["dataset"], p["method"]
        out["labels.num_queries"] = [int(_setting(s, "queries")) for s in p["setting"]]
        out[spec.col] = "score"
    elif table == 7:
        out["dataset"] = p["dataset"]
        out[spec.col] = [CVAE_LOSS_FROM_PAPER[_setting(s, "cvae_loss")] for s in p["setting"]]
    else:  # table 8: reward-model seconds in `mean`, the rest in `note`
        rows = []
        for _, r in p.iterrows():
            values = {
                "reward_model_s": float(r["mean"]),
                "offline_rl_s": _note_seconds(r["note"], "offline RL"),
                "total_s": _note_seconds(r["note"], "total"),
            }
            rows += [
                {"method": r["method"], "dataset": r["dataset"], spec.col: k, "paper": v, "paper_std": float("nan")}
                for k, v in values.items()
            ]
        out = pd.DataFrame(rows)
    return out.reset_index(drop=True)


# --------------------------------------------------------------------------- runs
def default_experiments(table: int, tracking_uri: str | None = None) -> list[str] | None:
    """The experiment of ``table``'s sweep if the store has it, else its budget-lab sweep's
    (``sweeps/lab_table<N>.yaml``), else its ``-smoke`` launch; None = all."""
    client = tracking.reader(tracking_uri)
    number = _spec(table).number
    name = SWEEP_EXPERIMENTS[number]
    for candidate in (name, f"lab_table{1 if number == 8 else number}", f"{name}-smoke"):
        if tracking.has_experiment(client, candidate):
            return [candidate]
    return None


def load_runs(
    tracking_uri: str | None = None, experiment_names: Sequence[str] | None = None, sweep_id: str | None = None
) -> pd.DataFrame:
    """Every run of the experiments (all experiments if ``None``), one row per run.

    Sweep parent runs (runs without a ``method`` tag) are left out. Columns follow
    ``mlflow.search_runs``: ``run_id``, ``experiment``, ``status``, ``start_time``, ...,
    ``params.<key>``, ``metrics.<name>`` (last logged value) and ``tags.<key>``, plus ``method``,
    ``dataset`` (our name), ``paper_dataset`` (the paper's row name), ``dataset_source`` and
    ``seed``. All statuses are kept; :func:`build_table` uses the FINISHED ones and lists the rest.
    """
    client = tracking.reader(tracking_uri)
    experiments = tracking.experiments(client, experiment_names)
    filter_string = tracking.tag_filter({"sweep_id": sweep_id}) if sweep_id else ""
    rows = [_run_row(run, experiments) for run in tracking.search_runs(client, list(experiments), filter_string)]
    df = pd.DataFrame(rows)
    if df.empty:
        return pd.DataFrame(columns=list(_RUN_COLUMNS))
    if "tags.method" not in df:
        df["tags.method"] = np.nan
    df = df[df["tags.method"].notna()].copy()
    for col in ("tags.dataset", "tags.dataset_source", "tags.seed", "params.seed"):
        if col not in df:
            df[col] = np.nan
    df["method"] = df["tags.method"].astype(str)
    df["dataset"] = df["tags.dataset"].fillna("unknown").astype(str)
    df["paper_dataset"] = df["dataset"].map(paper_dataset_name)
    df["dataset_source"] = df["tags.dataset_source"].fillna("unknown").astype(str)
    df["seed"] = pd.to_numeric(df["tags.seed"].fillna(df["params.seed"]), errors="coerce").astype("Int64")
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
    row.update({f"tags.{k}": v for k, v in data.tags.items()})
    return row


def failed_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs that are not FINISHED (FAILED, KILLED, still RUNNING), with the failure reason."""
    out = runs[runs["status"] != "FINISHED"]
    cols = ["run_id", "experiment", "method", "dataset", "seed", "status"]
    reason = out["tags.failure_reason"] if "tags.failure_reason" in out else pd.Series("", index=out.index)
    return out[cols].assign(failure_reason=reason.fillna("")).reset_index(drop=True)


# --------------------------------------------------------------------------- table specs
def _param(runs: pd.DataFrame, key: str, table: int) -> pd.Series:
    col = f"params.{key}"
    if col not in runs or runs[col].isna().any():
        raise SpotError(f"table {table} needs the param {key!r}, which some runs do not have")
    return runs[col]


def _shaped(runs: pd.DataFrame, table: int) -> pd.Series:
    return _param(runs, "shaping.kind", table) != "none"


def _group_label(group: str, top_k: float) -> str:
    k = f"{top_k:g}"
    k2 = f"{2 * top_k:g}"
    return {"top": f"top-{k}", "top_next": f"top-{k}-{k2}", "bottom_next": f"bottom-{k}-{k2}", "bottom": f"bottom-{k}"}[
        group
    ]


@dataclass(frozen=True)
class _Spec:
    number: int
    title: str
    rows: tuple[str, ...]
    col: str
    kind: str  # "score" | "time"
    best: str  # "row" | "col" | "none"
    select: Callable[[pd.DataFrame, int], pd.Series] | None
    keys: Callable[[pd.DataFrame, int], dict[str, pd.Series]]


_SPECS = {
    1: _Spec(
        1,
        "Table 1: score per dataset and method",
        ("dataset",),
        "method",
        "score",
        "row",
        None,
        lambda r, t: {"dataset": r["paper_dataset"], "method": r["method"]},
    ),
    2: _Spec(
        2,
        "Table 2: score per Top-K% percentile group (SPOT)",
        ("group",),
        "dataset",
        "score",
        "col",
        _shaped,
        lambda r, t: {
            "group": pd.Series(
                [
                    _group_label(g, float(k))
                    for g, k in zip(_param(r, "subgoal.group", t), _param(r, "subgoal.top_k", t), strict=True)
                ],
                index=r.index,
            ),
            "dataset": r["paper_dataset"],
        },
    ),
    3: _Spec(
        3,
        "Table 3: score per shaping kind and weight λ",
        ("dataset", "shaping.kind"),
        "shaping.weight",
        "score",
        "row",
        _shaped,
        lambda r, t: {
            "dataset": r["paper_dataset"],
            "shaping.kind": _param(r, "shaping.kind", t),
            "shaping.weight": _param(r, "shaping.weight", t).astype(float),
        },
    ),
    4: _Spec(
        4,
        "Table 4: score per number of preference queries",
        ("dataset", "method", "labels.num_queries"),
        "metric",
        "score",
        "none",
        None,
        lambda r, t: {
            "dataset": r["paper_dataset"],
            "method": r["method"],
            "labels.num_queries": _param(r, "labels.num_queries", t).astype(int),
            "metric": pd.Series("score", index=r.index),
        },
    ),
    7: _Spec(
        7,
        "Table 7: score per CVAE loss (SPOT)",
        ("dataset",),
        "cvae.loss",
        "score",
        "row",
        _shaped,
        lambda r, t: {"dataset": r["paper_dataset"], "cvae.loss": _param(r, "cvae.loss", t)},
    ),
    8: _Spec(
        8,
        "Table 8: wall time per stage, seconds",
        ("method", "dataset"),
        "time",
        "time",
        "none",
        None,
        lambda r, t: {"method": r["method"], "dataset": r["paper_dataset"]},
    ),
}


def _spec(table: int) -> _Spec:
    if table not in _SPECS:
        raise SpotError(f"unknown table {table}; the paper's tables here are {', '.join(map(str, TABLES))}")
    return _SPECS[table]


# --------------------------------------------------------------------------- ordering
def _group_rank(label: str) -> int:
    for rank, pattern in enumerate(
        (r"top-[\d.]+$", r"top-[\d.]+-[\d.]+$", r"bottom-[\d.]+-[\d.]+$", r"bottom-[\d.]+$")
    ):
        if re.fullmatch(pattern, str(label)):
            return rank
    return 99


def _sort_key(name: str, value: Any) -> tuple:
    if name == "dataset":
        order = _paper_datasets()
        if value == AVERAGE_ROW:
            return (2, 0, "")
        return (0, order.index(value), "") if value in order else (1, 0, str(value))
    orders: dict[str, Sequence[Any]] = {
        "method": METHOD_ORDER,
        "source": SOURCE_ORDER,
        "shaping.kind": SHAPING_ORDER,
        "cvae.loss": CVAE_LOSS_ORDER,
        "time": TIME_COLUMNS,
    }
    if name in orders:
        order = orders[name]
        return (0, list(order).index(value), "") if value in order else (1, 0, str(value))
    if name == "group":
        return (_group_rank(value), 0, str(value))
    if name == "labels.num_queries":
        return (0, -int(value), "")
    if name == "shaping.weight":
        return (0, float(value), "")
    return (0, 0, str(value))


def _sorted_frame(df: pd.DataFrame, names: Sequence[str]) -> pd.DataFrame:
    keys = [
        tuple(_sort_key(n, v) for n, v in zip(names, row, strict=True))
        for row in df[list(names)].itertuples(index=False)
    ]
    order = sorted(range(len(df)), key=lambda i: keys[i])
    return df.iloc[order].reset_index(drop=True)


# --------------------------------------------------------------------------- building
def _run_values(runs: pd.DataFrame, spec: _Spec, metric: str) -> pd.DataFrame:
    """``[run, col, value]`` rows: one per run for score tables, four per run for Table 8."""
    if spec.kind == "score":
        col = f"metrics.{metric}"
        if col not in runs:
            have = sorted(c[len("metrics.") :] for c in runs if c.startswith("metrics.eval/"))
            raise SpotError(f"no run logged the metric {metric!r}; eval metrics logged: {', '.join(have) or 'none'}")
        return pd.DataFrame({"run_id": runs["run_id"], "value": runs[col].astype(float)})

    def stage_sum(stages: Sequence[str]) -> pd.Series:
        cols = [f"metrics.time/{s}_s" for s in stages if f"metrics.time/{s}_s" in runs]
        if not cols:
            return pd.Series(0.0, index=runs.index)
        return runs[cols].astype(float).fillna(0.0).sum(axis=1)

    wall = (
        runs["metrics.time/total_s"].astype(float)
        if "metrics.time/total_s" in runs
        else pd.Series(np.nan, index=runs.index)
    )
    kind = runs["params.shaping.kind"] if "params.shaping.kind" in runs else pd.Series("none", index=runs.index)
    shaped = kind.fillna("none") != "none"
    rm = stage_sum(REWARD_MODEL_STAGES) + stage_sum(SUBGOAL_STAGES).where(shaped, 0.0)
    rl = stage_sum(OFFLINE_RL_STAGES)
    timed = wall.notna()  # runs that reached the end of the pipeline log time/total_s
    values = {"reward_model_s": rm, "offline_rl_s": rl, "total_s": rm + rl, "wall_s": wall}
    return pd.concat(
        [pd.DataFrame({"run_id": runs["run_id"], "time": name, "value": v.where(timed)}) for name, v in values.items()],
        ignore_index=True,
    )


def mixed_params(runs: pd.DataFrame, cell_keys: pd.DataFrame) -> list[str]:
    """``"cell (...): key in {a, b}"`` for every param (but seed, tracking.*) that varies inside a cell."""
    params = [
        c for c in runs if c.startswith("params.") and c != "params.seed" and not c.startswith("params.tracking.")
    ]
    if not params:
        return []
    filled = runs[params].astype(object).where(runs[params].notna(), "<unset>")
    cell = list(cell_keys.columns)
    problems = []
    for key, group in pd.concat([cell_keys, filled], axis=1).groupby(cell, dropna=False):
        for p in params:
            values = sorted(set(map(str, group[p])))
            if len(values) > 1:
                problems.append(f"cell {key}: {p[len('params.') :]} in {{{', '.join(values)}}}")
    return problems


def _mark_best(cells: pd.DataFrame, spec: _Spec) -> pd.Series:
    best = pd.Series(False, index=cells.index)
    if spec.best == "none":
        return best
    candidates = cells["mean"].notna() & (cells["dataset"] != AVERAGE_ROW if "dataset" in cells else True)
    if spec.number == 1:
        candidates &= cells["method"] != "oracle"
    by = [*spec.rows, "source"] if spec.best == "row" else [spec.col, "source"]
    top = cells["mean"].where(candidates).groupby([cells[b] for b in by], dropna=False).transform("max")
    return candidates & (cells["mean"] >= top - (1 - BEST_FRACTION) * top.abs())


def _average_rows(cells: pd.DataFrame, spec: _Spec) -> pd.DataFrame:
    """Table 1's Average row: mean over the datasets we ran, the paper's mean over the same ones."""
    rows = []
    for (source, method), g in cells.groupby(["source", spec.col], sort=False):
        ours = g[g["mean"].notna()]
        if ours["dataset"].nunique() < 2:
            continue
        paper_ok = ours["paper"].notna().all()
        rows.append(
            {
                "dataset": AVERAGE_ROW,
                "source": source,
                spec.col: method,
                "mean": ours["mean"].mean(),
                "std": ours["std"].mean(),
                "n": len(ours),
                "paper": ours["paper"].mean() if paper_ok else np.nan,
                "paper_std": ours["paper_std"].mean() if paper_ok else np.nan,
            }
        )
    return pd.DataFrame(rows)


def _finished(runs: pd.DataFrame, spec: _Spec, table: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(finished runs the table takes, runs not FINISHED)``; SpotError if nothing is left."""
    if runs.empty:
        raise SpotError(f"no runs to build table {table} from (check --experiment / --sweep-id / --tracking-uri)")
    excluded = failed_runs(runs)
    finished = runs[runs["status"] == "FINISHED"]
    if spec.select is not None and not finished.empty:
        finished = finished[spec.select(finished, table)]
    if finished.empty:
        raise SpotError(
            f"no FINISHED runs for table {table}" + (f" ({len(excluded)} runs did not finish)" if len(excluded) else "")
        )
    return finished, excluded


def _values(
    finished: pd.DataFrame, spec: _Spec, table: int, metric: str, allow_mixed: bool, notes: list[str]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(one value per run and cell column, the runs used)``: runs without the metric left out,
    a later run of the same cell and seed replacing an earlier one, mixed cells refused or noted."""
    keys = pd.DataFrame(spec.keys(finished, table), index=finished.index)
    base = pd.concat(
        [
            finished[["run_id", "seed", "start_time", "dataset_source"]].rename(columns={"dataset_source": "source"}),
            keys,
        ],
        axis=1,
    )
    cell = [*spec.rows, "source"] + ([spec.col] if spec.kind == "score" else [])
    long = _run_values(finished, spec, metric).merge(base, on="run_id", how="left")
    missing = long["value"].isna()
    if missing.any():
        what = metric if spec.kind == "score" else "time/total_s"
        notes.append(f"{long.loc[missing, 'run_id'].nunique()} finished runs did not log {what} and are left out")
        long = long[~missing]
    if long.empty:
        raise SpotError(
            f"no finished run for table {table} logged {metric if spec.kind == 'score' else 'time metrics'}"
        )
    long = long.sort_values("start_time")
    dup = long.duplicated([*spec.rows, "source", spec.col, "seed"], keep="last")
    if dup.any():
        notes.append(f"run(s) replaced by a later run of the same cell and seed: {long.loc[dup, 'run_id'].nunique()}")
        long = long[~dup]
    used = finished[finished["run_id"].isin(long["run_id"])]
    mixed = mixed_params(used, base.loc[used.index, cell])
    if mixed:
        if not allow_mixed:
            raise SpotError(
                f"table {table}: runs in one cell differ in more than the seed, so they are not "
                f"averaged: {'; '.join(mixed[:5])}{' ...' if len(mixed) > 5 else ''}. Pick runs with "
                "--experiment / --sweep-id, or pass --allow-mixed to average them anyway"
            )
        notes += [f"mixed params averaged ({m})" for m in mixed]
    return long, used


def _with_paper(cells: pd.DataFrame, spec: _Spec, table: int, paper_only_cells: bool) -> pd.DataFrame:
    """``cells`` with the paper's mean and std, plus (``paper_only_cells``) the paper's cells we
    did not run in the rows we ran."""
    paper = paper_cells(table)
    join = [*spec.rows, spec.col]
    cells = cells.merge(paper, on=join, how="left")
    if paper_only_cells:
        anchor = "dataset" if "dataset" in spec.rows else spec.col
        ran = cells[[anchor, "source"]].drop_duplicates()
        extra = paper.merge(ran, on=anchor).merge(
            cells[[*join, "source"]], on=[*join, "source"], how="left", indicator=True
        )
        extra = extra[extra["_merge"] == "left_only"].drop(columns="_merge")
        cells = pd.concat([cells, extra.assign(n=0)], ignore_index=True)
    return cells


def _wide(cells: pd.DataFrame, spec: _Spec) -> pd.DataFrame:
    """Long cells -> the table frame: rows (row keys, source) x columns (column key, field)."""
    wide = cells.set_index([*spec.rows, "source", spec.col])[list(FIELDS)].unstack(spec.col)
    wide = wide.swaplevel(0, 1, axis=1)
    col_values = sorted(dict.fromkeys(cells[spec.col]), key=lambda v: _sort_key(spec.col, v))
    wide = wide.reindex(columns=pd.MultiIndex.from_product([col_values, FIELDS], names=[spec.col, "field"]))
    row_order = list(dict.fromkeys(map(tuple, cells[[*spec.rows, "source"]].itertuples(index=False))))
    wide = wide.reindex(pd.MultiIndex.from_tuples(row_order, names=[*spec.rows, "source"]))
    for c in col_values:
        wide[(c, "n")] = wide[(c, "n")].fillna(0).astype(int)
        wide[(c, "best")] = wide[(c, "best")].astype("boolean").fillna(False).astype(bool)
        for f in ("mean", "std", "ci_low", "ci_high", "paper", "paper_std", "diff"):
            wide[(c, f)] = wide[(c, f)].astype(float)
    return wide


def _run_notes(used: pd.DataFrame, excluded: pd.DataFrame) -> list[str]:
    """Where the counted runs came from, and which runs were not counted."""
    sweeps = sorted(used["tags.sweep_id"].dropna().unique()) if "tags.sweep_id" in used else []
    notes = [
        f"runs: {len(used)} from experiment(s) {', '.join(sorted(used['experiment'].unique()))}"
        + (f", sweep(s) {', '.join(sweeps)}" if sweeps else "")
    ]
    if len(excluded):
        by_status = excluded["status"].value_counts()
        notes.append(
            f"not counted: {len(excluded)} runs not FINISHED ("
            + ", ".join(f"{s}: {c}" for s, c in sorted(by_status.items()))
            + "): "
            + ", ".join(excluded["run_id"].str[:8])
        )
    return notes


def build_table(
    runs: pd.DataFrame,
    table: int,
    metric: str = "eval/score_final",
    *,
    ddof: int = 1,
    allow_mixed: bool = False,
    paper_only_cells: bool = True,
) -> pd.DataFrame:
    """Table ``table`` of the paper from ``runs`` (a :func:`load_runs` frame).

    Args:
      runs: runs of any status; only FINISHED ones enter cells, the others are listed in the notes.
      table: 1, 2, 3, 4, 7 or 8.
      metric: the score metric (score tables); Table 8 always uses the ``time/<stage>_s`` metrics.
      ddof: 1 = sample std over seeds (default), 0 = population std.
      allow_mixed: average cells whose runs differ in params other than seed (noted) instead of refusing.
      paper_only_cells: also show the paper's cells for the datasets we ran but cells we did not.

    Returns:
      Index = the table's row keys + ``source``; columns = ``(column key, field)`` with fields
      ``mean, std, n, paper, paper_std, diff, best``. ``attrs``: ``table, title, metric, ddof,
      kind, rows, col, notes, excluded``.
    """
    spec = _spec(table)
    if ddof not in (0, 1):
        raise SpotError(f"ddof must be 0 (population std) or 1 (sample std), got {ddof}")
    notes: list[str] = []
    finished, excluded = _finished(runs, spec, table)
    long, used = _values(finished, spec, table, metric, allow_mixed, notes)
    agg = long.groupby([*spec.rows, "source", spec.col], dropna=False)["value"]
    cells = pd.DataFrame({"mean": agg.mean(), "std": agg.std(ddof=ddof), "n": agg.count()})
    ci = agg.apply(lambda v: stats.bootstrap_ci([v.dropna().to_numpy()], stats.mean_of_means))
    cells["ci_low"], cells["ci_high"] = [c[0] for c in ci], [c[1] for c in ci]
    cells = cells.reset_index()
    with_paper = spec.kind == "time" or metric.startswith("eval/score")
    if with_paper:
        cells = _with_paper(cells, spec, table, paper_only_cells)
    else:
        cells["paper"] = cells["paper_std"] = np.nan
        notes.append(f"paper values omitted: {metric} is not a score metric")
    if table == 1:
        avg = _average_rows(cells, spec)
        if not avg.empty:
            cells = pd.concat([cells, avg], ignore_index=True)
    cells["diff"] = cells["mean"] - cells["paper"]
    cells["best"] = _mark_best(cells, spec)
    cells["n"] = cells["n"].fillna(0).astype(int)
    cells = _sorted_frame(cells, [*spec.rows, "source", spec.col])
    wide = _wide(cells, spec)
    notes = _standard_notes(spec, cells, metric, ddof, with_paper, used) + notes + _run_notes(used, excluded)
    wide.attrs = {
        "table": table,
        "title": spec.title,
        "metric": metric if spec.kind == "score" else "time/*",
        "ddof": ddof,
        "kind": spec.kind,
        "rows": [*spec.rows, "source"],
        "col": spec.col,
        "notes": notes,
        "excluded": excluded.to_dict("records"),
    }
    return wide


def _standard_notes(
    spec: _Spec, cells: pd.DataFrame, metric: str, ddof: int, with_paper: bool, used: pd.DataFrame
) -> list[str]:
    std = "sample std (ddof=1)" if ddof == 1 else "population std (ddof=0)"
    unit = "the stage times in seconds" if spec.kind == "time" else metric
    notes = [
        f"cell: ours mean ± {std} over seeds of {unit} (n seeds), CI = 95% bootstrap interval of the mean"
        + (" [paper mean ± std, Δ = ours − paper]" if with_paper else "")
    ]
    if spec.best != "none":
        where = "row" if spec.best == "row" else "column"
        notes.append(
            f"bold: ours ≥ {BEST_FRACTION:.0%} of the {where}'s best (the paper's 'top 95%')"
            + (", Oracle left out as in the paper" if spec.number == 1 else "")
        )
    for source in dict.fromkeys(cells["source"]):
        notes.append(f"dataset source {source}: {SOURCE_NOTES.get(source, 'unknown origin')}")
    if cells["source"].nunique() > 1:
        notes.append("runs from different dataset sources are never averaged together (one row per source)")
    if spec.number == 1 and (cells["dataset"] == AVERAGE_ROW).any():
        notes.append(
            "average: mean over the datasets we ran ± mean of their stds (the paper's Avg.std), n = datasets; paper = "
            "the mean of the paper's values on the same datasets (the paper's printed Average for MR, PT, "
            "IPL and HPL differs from the mean of its own rows)"
        )
    if spec.number == 3 and (cells["shaping.kind"] == "?").any():
        notes.append("shaping.kind '?': paper values whose shaping kind is lost in the extracted paper text")
    if spec.number == 8:
        notes.append(
            "reward model = time/{"
            + ",".join(REWARD_MODEL_STAGES)
            + "}_s, plus time/{"
            + ",".join(SUBGOAL_STAGES)
            + "}_s where shaping is on (runs without shaping spend those "
            "on the Fig. 2 diagnostics only); offline RL = time/{"
            + ",".join(OFFLINE_RL_STAGES)
            + "}_s; total = the two; wall = time/total_s (everything, data loading and diagnostics "
            "included). Paper: one GTX 1080 Ti"
        )
        hit = pd.Series(False, index=used.index)
        for t in CACHE_HIT_TAGS:
            if f"tags.{t}" in used:
                hit |= used[f"tags.{t}"] == "hit"
        for m in CACHE_HIT_METRICS:
            if f"metrics.{m}" in used:
                hit |= used[f"metrics.{m}"].astype(float) > 0
        if hit.any():
            notes.append(
                f"{int(hit.sum())} of {len(used)} runs reused a cached reward model, relabelling or CVAE: "
                "their reward-model time leaves out that training"
            )
    return notes


# --------------------------------------------------------------------------- formatting
def _num(x: float, kind: str) -> str:
    if kind == "time":
        return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.1f}"
    return f"{x:.2f}"


def _pm(mean: float, std: float, kind: str, pm: str) -> str:
    return _num(mean, kind) + (f" {pm} {_num(std, kind)}" if np.isfinite(std) else "")


def _cell_text(c: pd.Series, kind: str, fmt: str) -> str:
    pm, delta = ("$\\pm$", "$\\Delta$") if fmt == "latex" else ("±", "Δ")
    parts = []
    if np.isfinite(c["mean"]):
        ours = _pm(c["mean"], c["std"], kind, pm)
        if c["best"]:
            ours = f"\\textbf{{{ours}}}" if fmt == "latex" else f"**{ours}**"
        parts.append(f"{ours} ({int(c['n'])})")
        if np.isfinite(c.get("ci_low", np.nan)):
            dash = "--" if fmt == "latex" else "–"
            parts.append(f"CI {_num(c['ci_low'], kind)}{dash}{_num(c['ci_high'], kind)}")
    elif np.isfinite(c["paper"]):
        parts.append("--" if fmt == "latex" else "–")
    if np.isfinite(c["paper"]):
        paper = _pm(c["paper"], c["paper_std"], kind, pm)
        if np.isfinite(c["diff"]):
            sign = "+" if c["diff"] >= 0 else "-"
            paper += f", {delta} {sign}{_num(abs(c['diff']), kind)}"
        parts.append(f"{{\\scriptsize [{paper}]}}" if fmt == "latex" else f"[{paper}]")
    return " ".join(parts)


def _col_label(col: str, value: Any) -> str:
    if col == "method":
        return METHOD_LABELS.get(value, str(value))
    if col == "shaping.weight":
        return f"λ={value:g}"
    return str(value)


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}
_LATEX_UNICODE = {
    "±": r"$\pm$",
    "Δ": r"$\Delta$",
    "λ": r"$\lambda$",
    "≥": r"$\geq$",
    "−": "-",
    "–": "--",
    "ĝ": r"$\hat g$",
}


def _latex(text: str) -> str:
    out = "".join(_LATEX_SPECIAL.get(ch, ch) for ch in str(text))
    return "".join(_LATEX_UNICODE.get(ch, ch) for ch in out)


def format_table(table: pd.DataFrame, fmt: str = "md", width: int = 120) -> str:
    """Render a :func:`build_table` frame: ``md`` (Markdown with notes), ``latex`` (tabular + notes),
    ``csv``, or ``text`` (a compact plain table for a terminal of ``width`` columns).

    CSV has one line per row, the row keys first and then ``<column>/<field>`` numbers.
    """
    if fmt not in FORMATS:
        raise SpotError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    a = table.attrs
    rows, col, kind = a["rows"], a["col"], a["kind"]
    if fmt == "csv":
        flat = table.copy()
        flat.columns = [f"{c}/{f}" for c, f in flat.columns]
        return flat.reset_index().to_csv(index=False)
    col_values = list(dict.fromkeys(table.columns.get_level_values(0)))
    if fmt == "text":
        return _text_table(table, col_values, width)
    header = [*rows, *(_col_label(col, v) for v in col_values)]
    body = []
    for key, line in table.iterrows():
        key = key if isinstance(key, tuple) else (key,)
        cells = [_cell_text(line[v], kind, fmt) for v in col_values]
        body.append([*map(str, key), *cells])
    title = f"{a['title']} (metric {a['metric']})" if kind == "score" else a["title"]
    if fmt == "md":
        lines = [f"**{title}**", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in body]
        lines += [""] + [f"- {n}" for n in a["notes"]]
        return "\n".join(lines) + "\n"
    esc_body = [[_latex(x) for x in r[: len(rows)]] + r[len(rows) :] for r in body]
    lines = [
        f"% {_latex(title)}",
        "\\begin{tabular}{" + "l" * len(rows) + "|" + "c" * len(col_values) + "}",
        "\\hline",
        " & ".join(_latex(h) for h in header) + " \\\\",
        "\\hline",
    ]
    lines += [" & ".join(r) + " \\\\" for r in esc_body]
    lines += ["\\hline", "\\end{tabular}", ""]
    lines += [f"\\par{{\\footnotesize {_latex(n)}}}" for n in a["notes"]]
    return "\n".join(lines) + "\n"


def _text_cell(c: pd.Series, kind: str) -> str:
    """``ours±std (paper)`` with one decimal (times: :func:`_num`), ``*`` for the paper's bold rule."""

    def num(x: float) -> str:
        return _num(x, kind) if kind == "time" else f"{x:.1f}"

    ours = "–"
    if np.isfinite(c["mean"]):
        ours = num(c["mean"]) + (f"±{num(c['std'])}" if np.isfinite(c["std"]) and kind != "time" else "")
    ours += "*" if c["best"] else ""
    return ours + (f" ({num(c['paper'])})" if np.isfinite(c["paper"]) else "")


def _text_table(table: pd.DataFrame, col_values: list[Any], width: int) -> str:
    """Plain fixed-width columns, split into blocks of columns so that no line exceeds ``width``."""
    a = table.attrs
    keys = [" ".join(map(str, k if isinstance(k, tuple) else (k,))) for k in table.index]
    cols = [
        [_col_label(a["col"], v), *(_text_cell(table.loc[k, v], a["kind"]) for k in table.index)] for v in col_values
    ]
    key_w = max(len(k) for k in ["", *keys])
    widths = [max(map(len, c)) for c in cols]
    blocks, cur, used = [], [], key_w
    for i, w in enumerate(widths):
        if cur and used + 2 + w > width:
            blocks.append(cur)
            cur, used = [], key_w
        cur.append(i)
        used += 2 + w
    blocks.append(cur)
    title = f"{a['title']} (metric {a['metric']})" if a["kind"] == "score" else a["title"]
    lines = [title, "ours mean±std over seeds (paper); * = the paper's bold rule; full table: --format md"]
    for block in blocks:
        lines.append("")
        for r in range(len(keys) + 1):
            left = "" if r == 0 else keys[r - 1]
            lines.append((left.ljust(key_w) + "".join("  " + cols[i][r].rjust(widths[i]) for i in block)).rstrip())
    return "\n".join(lines) + "\n"


def check_out(path: str | Path) -> None:
    """:class:`SpotError` unless ``--out`` names a file that can be written: its folder exists and
    it is not a folder itself."""
    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise SpotError(f"--out {path}: folder '{folder}' does not exist; expected a file in an existing folder")
    if out.is_dir():
        raise SpotError(f"--out {path}: is a folder; expected a file name")


def write_out(path: str | Path, text: str) -> None:
    """Write a table to ``path`` (checked with :func:`check_out`); an OS error is a :class:`SpotError`."""
    check_out(path)
    try:
        Path(path).write_text(text)
    except OSError as err:
        raise SpotError(f"--out {path}: cannot write it ({err.strerror})") from None
