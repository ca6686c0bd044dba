# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # The paper's tables from the MLflow runs
#
# Rebuilds Tables 1, 2, 3, 4, 7 and 8 of the SPOT paper from the runs of the sweeps in `sweeps/`,
# with the paper's numbers and the difference (ours − paper) beside ours. Everything is computed
# by `spot.results` (the same code as `spot tables`); this notebook only chooses the runs, shows
# the tables inline and writes them to `out_dir/table<N>.{md,tex,csv}`. See docs/tables.md.
#
# * Notebook: `jupytext --to notebook analysis/tables.py` and open it in Jupyter, or execute it
#   with papermill (parameters in the cell tagged `parameters` below):
#   `jupytext --to notebook analysis/tables.py -o /tmp/tables.ipynb &&
#   papermill /tmp/tables.ipynb /tmp/tables-run.ipynb -p table_experiments "1=table1"`
# * Script: `python analysis/tables.py` prints the same tables as text.
#
# Which runs: a table named in `table_experiments` (`TABLE=EXP[,EXP...]` joined by `;`, e.g.
# `1=table1;8=table1,extra`) reads those experiments; otherwise, as
# `spot tables --table N` does, the experiment of the table's sweep (`table1`, `table2_topk`, ...),
# else its `--smoke` launch (`table1-smoke`, ...), else every experiment in the store.
# `smoke=True` reads the `-smoke` experiments only.

# %%
import os
from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from spot import SpotError, runtime, tracking
from spot.results import load, select, table_format, tables

runtime.configure()  # XLA flags and headless MuJoCo, before jax or mujoco start

try:  # inline output in Jupyter/papermill, text when run as a script
    from IPython import get_ipython
    from IPython.display import Image, Markdown, display

    INLINE = get_ipython() is not None
except ImportError:
    INLINE = False

# %% tags=["parameters"]
# Defaults come from the environment (SPOT_*), so the script form takes them too; papermill's
# `-p NAME VALUE` overrides them.
tracking_uri: str = os.environ.get(
    "SPOT_TRACKING_URI", ""
)  # MLflow store; "": $MLFLOW_TRACKING_URI, else ./spot_runs or ./mlruns
table_experiments: str = os.environ.get(
    "SPOT_TABLE_EXPERIMENTS", ""
)  # experiments per table (format in the first cell); others: as spot tables
smoke: bool = os.environ.get("SPOT_SMOKE", "") in ("1", "true")  # read the sweeps' -smoke experiments
sweep_id: str = os.environ.get("SPOT_SWEEP_ID", "")  # only the runs of this sweep (tag sweep_id)
metric: str = os.environ.get("SPOT_METRIC", "eval/score_final")  # score metric of tables 1-7
ddof: int = int(os.environ.get("SPOT_DDOF", "1"))  # std over seeds: 1 sample, 0 population
out_dir: str = os.environ.get("SPOT_ANALYSIS_OUT", "analysis/out")  # where tables and figures are written


# %%
def show(frame: pd.DataFrame, title: str) -> None:
    if INLINE:
        display(Markdown(f"**{title}**"), frame)
    else:
        print(f"{title}\n{frame.to_string()}\n")


def show_png(path: Path) -> None:
    if INLINE:
        display(Image(filename=str(path)))
    print(f"wrote {path}")


named: dict[int, list[str]] = {}
for part in filter(None, (p.strip() for p in table_experiments.split(";"))):
    number, _, names = part.partition("=")
    if not number.strip().isdigit() or int(number) not in tables.TABLES or not names.strip():
        raise SpotError(
            f"table_experiments: {part!r} is not TABLE=EXPERIMENT[,EXPERIMENT...] with TABLE one of "
            f"{', '.join(map(str, tables.TABLES))}"
        )
    named[int(number)] = [n.strip() for n in names.split(",") if n.strip()]


def experiments_for(number: int) -> list[str] | None:
    """The experiments table ``number`` reads; None = every experiment (as `spot tables`)."""
    if number in named:
        return named[number]
    if smoke:
        return [tables.SWEEP_EXPERIMENTS[number] + "-smoke"]
    return tables.default_experiments(number, URI)


URI = tracking.resolve_uri(tracking_uri or None, read=True)  # the store to read; it must exist
OUT = Path(out_dir)
OUT.mkdir(parents=True, exist_ok=True)
loaded: dict[tuple[str, ...] | None, pd.DataFrame] = {}
runs: dict[int, pd.DataFrame] = {}
for number in tables.TABLES:
    try:
        names = experiments_for(number)
        key = tuple(names) if names else None
        if key not in loaded:
            loaded[key] = load.load_runs(URI, names, sweep_id or None)
        runs[number] = loaded[key]
    except SpotError as e:
        print(f"table {number}: {e}")

# %% [markdown]
# ## The runs
# Runs per table, experiment, method, dataset and status; only FINISHED runs enter the cells.

# %%
counts = [
    r.groupby(["experiment", "method", "paper_dataset", "dataset_source", "status"])
    .size()
    .rename("runs")
    .reset_index()
    .assign(table=number)
    for number, r in runs.items()
    if not r.empty
]
if counts:
    overview = pd.concat(counts).set_index(
        ["table", "experiment", "method", "paper_dataset", "dataset_source", "status"]
    )
    show(overview, "runs per table")
else:
    print("no runs found")

# %% [markdown]
# ## Runs that did not finish
# They never enter a cell; each table's notes count them too.

# %%
failed = [select.not_finished(r).assign(table=number) for number, r in runs.items()]
failed = [f for f in failed if len(f)]
if failed:
    show(pd.concat(failed).set_index("table"), "runs that did not finish")
else:
    print("every run finished")

# %% [markdown]
# ## The tables
# Each cell: ours mean ± std over seeds (n seeds) [paper mean ± std, Δ = ours − paper], with the
# table's notes. Written to `out_dir/table<N>.md`, `.tex` and `.csv`.

# %%
built: dict[int, pd.DataFrame] = {}
for number, r in runs.items():
    try:
        built[number] = tables.build_table(r, number, metric, ddof=ddof)
    except SpotError as e:
        print(f"table {number}: {e}")
        continue
    for fmt, ext in (("md", "md"), ("latex", "tex"), ("csv", "csv")):
        (OUT / f"table{number}.{ext}").write_text(table_format.format_table(built[number], fmt))
    if INLINE:
        display(Markdown(table_format.format_table(built[number], "md")))
    else:
        print(table_format.format_table(built[number], "md"))

# %% [markdown]
# ## The numbers behind each table
# Fields per column: ours (`mean`, `std`, `n` seeds), the paper's (`paper`, `paper_std`) and
# `diff` = ours − paper, as a DataFrame to sort, filter or plot further.

# %%
for t in built.values():
    fields = [
        f for f in ("mean", "std", "n", "paper", "paper_std", "diff") if f in set(t.columns.get_level_values("field"))
    ]
    show(t.loc[:, pd.IndexSlice[:, fields]].round(2), t.attrs["title"])

# %% [markdown]
# ## Ours vs the paper
# Every score cell that both we and the paper have: our mean against the paper's, one colour per
# table; points on the diagonal reproduce the paper. Written to `out_dir/ours_vs_paper.png`.

# %%
points = []
for number, t in built.items():
    if t.attrs["kind"] != "score":
        continue
    cells = pd.DataFrame({f: t.xs(f, axis=1, level="field").stack() for f in ("mean", "paper")}).dropna()
    keep = [tables.AVERAGE_ROW not in (key if isinstance(key, tuple) else (key,)) for key in cells.index]
    points.append((number, cells[keep]))  # the average rows repeat the cells
if any(len(c) for _, c in points):
    fig = Figure(figsize=(4.5, 4.5))
    ax = fig.subplots()
    for number, cells in points:
        if len(cells):
            ax.scatter(cells["paper"], cells["mean"], s=18, label=f"Table {number} ({len(cells)} cells)")
    lo = min(min(c["paper"].min(), c["mean"].min()) for _, c in points if len(c))
    hi = max(max(c["paper"].max(), c["mean"].max()) for _, c in points if len(c))
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8, label="ours = paper")
    ax.set_xlabel("paper (mean over seeds)")
    ax.set_ylabel(f"ours ({metric}, mean over seeds)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "ours_vs_paper.png", dpi=120)
    show_png(OUT / "ours_vs_paper.png")
else:
    print("no score cell that the paper also has")
