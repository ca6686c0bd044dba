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
# # A study through the Python API
#
# The calls of docs/python.md on a committed study: its runs as a pandas DataFrame
# (`spot.results.load_runs`), a look at them with pandas, a paper table and the claims report
# from the frame (`spot.results.table`, `spot.results.claims_report`: the same text as
# `spot tables` and `spot report`), and a sweep given as a dict (`spot.sweep.resolve` lists its
# trials; `spot.sweep.run_sweep` launches it).
#
# * Notebook: `jupytext --to notebook analysis/study.py` and open it in Jupyter, or execute it
#   with papermill: `jupytext --to notebook analysis/study.py -o /tmp/study.ipynb &&
#   papermill /tmp/study.ipynb /tmp/study-run.ipynb -p study experiments/lab-walker2d`
# * Script: `python analysis/study.py` (from the repository root) prints the same as text.

# %%
import os

import spot.results
import spot.sweep
from spot import runtime

runtime.configure()  # XLA flags and headless MuJoCo, before jax or mujoco start

try:  # inline output in Jupyter/papermill, text when run as a script
    from IPython import get_ipython
    from IPython.display import Markdown, display

    INLINE = get_ipython() is not None
except ImportError:
    INLINE = False


def show(obj, markdown: bool = False) -> None:
    if INLINE:
        display(Markdown(obj) if markdown else obj)
    else:
        print(obj if isinstance(obj, str) else obj.to_string())


# %% tags=["parameters"]
# Paths are relative to the working directory (the repository root when run as a script).
study: str = os.environ.get("SPOT_STUDY", "experiments/lab-walker2d")  # a study folder (its claims.yaml)
table_results: str = os.environ.get(
    "SPOT_TABLE_RESULTS", "experiments/lab-hopper-medium-replay/results/lab_table1.csv"
)  # results CSVs for Table 1
launch: bool = False  # True: run the tiny sweep below (Ray, a local MLflow store under ./spot_runs)

# %% [markdown]
# ## The study's runs as a DataFrame
# One row per run, every status; `status == "FINISHED"` are the runs tables and reports count.

# %%
runs = spot.results.load_runs(study)
finished = runs[runs["status"] == "FINISHED"]
print(f"{len(runs)} runs from {runs['experiment'].nunique()} experiments, {len(finished)} finished")
show(runs.groupby(["experiment", "status"]).size().unstack(fill_value=0))

# %% [markdown]
# Plain pandas from here: the final score of every finished run, by dataset and method.

# %%
score = "metrics.eval/score_final"
by_method = finished.groupby(["dataset", "method"])[score].agg(["mean", "std", "count"]).round(2)
show(by_method)

# %% [markdown]
# ## The claims report from the frame
# The study's claims (its `claims.yaml`), answered from `runs`: the text `spot report STUDY` writes.

# %%
report = spot.results.claims_report(runs, study)
show(report, markdown=True)

# %% [markdown]
# ## Table 1 from a results file
# As a DataFrame (`fmt=None`: cells with `mean, std, n, paper, diff, best`) and as the Markdown
# `spot tables --table 1 --results FILE` prints.

# %%
table_runs = spot.results.load_runs(table_results)
wide = spot.results.table(table_runs, 1)
show(wide.xs("mean", axis=1, level=1).round(2))
show(spot.results.table(table_runs, 1, fmt="md"), markdown=True)

# %% [markdown]
# ## A sweep from a dict
# The dict is a sweep file's content; it is validated as a file is. `resolve` lists the trials
# (`spot sweep FILE --dry-run`); `run_sweep` launches them and returns the summary rows.

# %%
sweep = {
    "name": "api-notebook",
    "base": {
        "budget": "tiny",
        "data": {"name": "hopper-medium-replay", "size": "tiny"},
        "labels.source": "script",
        "eval.episodes": 1,
    },
    "grid": {"method": ["oracle", "pt"]},
    "seeds": [0],
    "resources": {"cpu": 1, "gpu": 0},
}
for trial in spot.sweep.resolve(sweep).trials():
    print(trial.label, "seeds", list(trial.seeds))
if launch:
    rows = spot.sweep.run_sweep(sweep)
    show(spot.results.load_runs(experiments=["api-notebook"])[["run_name", "method", "status", score]])
