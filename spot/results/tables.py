"""The paper's tables rebuilt from runs, with the paper's numbers beside ours (``spot tables``).

:func:`build_table` turns runs (a :func:`spot.results.load.load` frame: MLflow or results CSVs) into
Table 1, 2, 3, 4, 7 or 8 of the SPOT paper; :func:`spot.results.table_format.format_table` prints it
as Markdown, LaTeX, CSV or a terminal table. The CLI (``spot tables``), the sweep summary and the
notebooks in ``analysis/`` call these functions.

How a table cell is made:

* A cell is one (row, column) key, e.g. (``hopper-medium-replay``, ``spot``) in Table 1. Its runs
  are the runs that count (:func:`spot.results.select.finished`, the rule ``spot report`` uses too:
  FINISHED only, and a re-run of a (config, seed) replaces the earlier run) with that key; FAILED,
  KILLED and still-running runs never enter a cell and are listed in the table's notes instead.
* Ours = mean and standard deviation over the cell's runs (one per seed). The std is the sample
  std (``ddof=1``) by default; the paper does not say which it used. ``n`` = seeds in the cell.
* The paper's value comes from ``spot/paper_tables.csv`` (:mod:`spot.results.paper`) and ``diff``
  = ours − paper (means).
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

from collections.abc import Sequence

import numpy as np
import pandas as pd

from spot import SpotError, tracking
from spot.results import stats
from spot.results.paper import AVERAGE_ROW
from spot.results.select import finished as counted
from spot.results.select import not_finished
from spot.results.table_specs import SWEEP_EXPERIMENTS, TABLES, Spec, paper_cells, sort_key, sorted_frame, table_spec

__all__ = ["AVERAGE_ROW", "SWEEP_EXPERIMENTS", "TABLES", "build_table", "default_experiments", "mixed_params"]

FIELDS = ("mean", "std", "n", "ci_low", "ci_high", "paper", "paper_std", "diff", "best")
SOURCE_NOTES = {
    "recipe": "built locally with spot's dataset recipes, not the paper's D4RL/robomimic/Meta-World data",
    "file": "read from dataset files (e.g. the original D4RL/robomimic hdf5)",
}
REWARD_MODEL_STAGES = ("reward", "relabel")
SUBGOAL_STAGES = ("subgoals", "cvae", "shaping")  # reward-model time only where shaping is on
OFFLINE_RL_STAGES = ("iql", "eval")
CACHE_HIT_TAGS = ("spot.cache.reward", "spot.cache.relabel", "spot.cache.cvae")  # "hit" | "miss" (load's names)
CACHE_HIT_METRICS = ("cache/reward_hit", "cache/relabel_hit", "cache/cvae_hit")  # runs logged before the tags
BEST_FRACTION = 0.95


# --------------------------------------------------------------------------- runs
def default_experiments(table: int, tracking_uri: str | None = None) -> list[str] | None:
    """The experiment of ``table``'s sweep if the store has it (``sweeps/paper/<name>.yaml``), else
    its ``-smoke`` launch; None = all."""
    client = tracking.reader(tracking_uri)
    name = SWEEP_EXPERIMENTS[table_spec(table).number]
    for candidate in (name, f"{name}-smoke"):
        if tracking.has_experiment(client, candidate):
            return [candidate]
    return None


# --------------------------------------------------------------------------- building
def _run_values(runs: pd.DataFrame, spec: Spec, metric: str) -> pd.DataFrame:
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


def _mark_best(cells: pd.DataFrame, spec: Spec) -> pd.Series:
    best = pd.Series(False, index=cells.index)
    if spec.best == "none":
        return best
    candidates = cells["mean"].notna() & (cells["dataset"] != AVERAGE_ROW if "dataset" in cells else True)
    if spec.number == 1:
        candidates &= cells["method"] != "oracle"
    by = [*spec.rows, "source"] if spec.best == "row" else [spec.col, "source"]
    top = cells["mean"].where(candidates).groupby([cells[b] for b in by], dropna=False).transform("max")
    return candidates & (cells["mean"] >= top - (1 - BEST_FRACTION) * top.abs())


def _average_rows(cells: pd.DataFrame, spec: Spec) -> pd.DataFrame:
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


def _finished(runs: pd.DataFrame, spec: Spec, table: int) -> tuple[pd.DataFrame, pd.DataFrame, int]:
    """``(the runs the table counts, runs not FINISHED, finished runs replaced by a re-run)``: the
    report's rule (:func:`spot.results.select.finished`) on the runs the table takes; SpotError if
    nothing is left."""
    if runs.empty:
        raise SpotError(f"no runs to build table {table} from (check --experiment / --sweep-id / --tracking-uri)")
    excluded = not_finished(runs)
    finished = runs[runs["status"] == "FINISHED"]
    if spec.select is not None and not finished.empty:
        finished = finished[spec.select(finished, table)]
    done = counted(finished)
    if done.empty:
        raise SpotError(
            f"no FINISHED runs for table {table}" + (f" ({len(excluded)} runs did not finish)" if len(excluded) else "")
        )
    return done, excluded, len(finished) - len(done)


def _values(
    finished: pd.DataFrame, spec: Spec, table: int, metric: str, allow_mixed: bool, notes: list[str], replaced: int
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(one value per run and cell column, the runs used)``: runs without the metric left out
    (``replaced``: the re-run runs :func:`_finished` dropped, noted), mixed cells refused or noted."""
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
    if replaced:
        notes.append(f"run(s) replaced by a later run of the same config and seed: {replaced}")
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


def _with_paper(cells: pd.DataFrame, spec: Spec, table: int, paper_only_cells: bool) -> pd.DataFrame:
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


def _wide(cells: pd.DataFrame, spec: Spec) -> pd.DataFrame:
    """Long cells -> the table frame: rows (row keys, source) x columns (column key, field)."""
    wide = cells.set_index([*spec.rows, "source", spec.col])[list(FIELDS)].unstack(spec.col)
    wide = wide.swaplevel(0, 1, axis=1)
    col_values = sorted(dict.fromkeys(cells[spec.col]), key=lambda v: sort_key(spec.col, v))
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
    sweeps = sorted(used["tags.spot.sweep_id"].dropna().unique()) if "tags.spot.sweep_id" in used else []
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
    spec = table_spec(table)
    if ddof not in (0, 1):
        raise SpotError(f"ddof must be 0 (population std) or 1 (sample std), got {ddof}")
    notes: list[str] = []
    finished, excluded, replaced = _finished(runs, spec, table)
    long, used = _values(finished, spec, table, metric, allow_mixed, notes, replaced)
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
    cells = sorted_frame(cells, [*spec.rows, "source", spec.col])
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
    spec: Spec, cells: pd.DataFrame, metric: str, ddof: int, with_paper: bool, used: pd.DataFrame
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
