# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # The paper's tables from the MLflow runs
#
# Rebuilds Tables 1, 2, 3, 4, 7 and 8 of the SPOT paper from the runs of the sweeps in `sweeps/`,
# with the paper's numbers and the difference (ours − paper) beside ours. Everything is computed
# by `spot.tables` (the same code as `spot tables`); this notebook only chooses the runs and
# writes the tables out. See docs/tables.md for how cells map to runs.
#
# Run it as a script (`python analysis/tables.py`; the percent format is plain Python) or open it
# as a notebook with `jupytext --to notebook analysis/tables.py`. Parameters come from the
# environment:
#
# * `SPOT_TRACKING_URI`: the MLflow store (default: `$MLFLOW_TRACKING_URI`, else
#   `./spot_runs/mlflow.db` or `./mlruns/mlflow.db`).
# * `SPOT_TABLE_EXPERIMENTS`: which experiments feed which table, e.g. `1=table1;8=table1,extra`
#   (default: each table's sweep, `table1`, `table2_topk`, ...; `SPOT_SMOKE=1` adds `-smoke`).
# * `SPOT_SWEEP_ID`, `SPOT_METRIC` (default `eval/score_final`), `SPOT_DDOF` (1 = sample std),
#   `SPOT_ANALYSIS_OUT` (default `analysis/out`).

# %%
import os
from pathlib import Path

from spot import SpotError, tables

TRACKING_URI = os.environ.get("SPOT_TRACKING_URI", "")
SUFFIX = "-smoke" if os.environ.get("SPOT_SMOKE") == "1" else ""
EXPERIMENTS = {n: [name + SUFFIX] for n, name in tables.SWEEP_EXPERIMENTS.items()}
for part in filter(None, os.environ.get("SPOT_TABLE_EXPERIMENTS", "").split(";")):
    number, _, names = part.partition("=")
    EXPERIMENTS[int(number)] = names.split(",")
SWEEP_ID = os.environ.get("SPOT_SWEEP_ID") or None
METRIC = os.environ.get("SPOT_METRIC", "eval/score_final")
DDOF = int(os.environ.get("SPOT_DDOF", "1"))
OUT = Path(os.environ.get("SPOT_ANALYSIS_OUT", "analysis/out"))
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## The runs
# One row per run; `status` shows which runs count (FINISHED) and which are listed as failed.

# %%
runs = {}
for number, names in EXPERIMENTS.items():
    try:
        runs[number] = tables.load_runs(TRACKING_URI, names, SWEEP_ID)
    except SpotError as e:
        print(f"table {number}: {e}")
overview = {n: r.groupby(["experiment", "method", "paper_dataset", "dataset_source", "status"]).size()
            for n, r in runs.items() if not r.empty}
for number, counts in overview.items():
    print(f"table {number}:\n{counts.to_string()}\n")

# %% [markdown]
# ## Runs that did not finish
# They never enter a cell; each table's notes count them too.

# %%
for number, r in runs.items():
    failed = tables.failed_runs(r)
    if len(failed):
        print(f"table {number}:\n{failed.to_string(index=False)}\n")

# %% [markdown]
# ## The tables
# Each cell: ours mean ± std over seeds (n seeds) [paper mean ± std, Δ = ours − paper]. Written to
# `OUT/table<N>.md`, `.tex` and `.csv`.

# %%
built = {}
for number, r in runs.items():
    try:
        built[number] = tables.build_table(r, number, METRIC, ddof=DDOF)
    except SpotError as e:
        print(f"table {number}: {e}\n")
        continue
    for fmt, ext in (("md", "md"), ("latex", "tex"), ("csv", "csv")):
        (OUT / f"table{number}.{ext}").write_text(tables.format_table(built[number], fmt))
    print(tables.format_table(built[number], "md"))

# %% [markdown]
# ## Ours − paper, in numbers
# The `diff` field of every table as a plain frame (rows × columns), for a quick look at where we
# are above or below the paper.

# %%
diffs = {n: t.xs("diff", axis=1, level="field") for n, t in built.items()}
for number, d in diffs.items():
    print(f"table {number}: ours − paper\n{d.round(2).to_string()}\n")
