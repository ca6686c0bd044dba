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
# # The paper's figures from the MLflow runs
#
# Fig. 2 (extrapolation error vs similarity to the predicted subgoal), Fig. 4 (PCA of observations
# and subgoals) and Fig. 3 (a Hopper state rendered beside its predicted subgoal), all through
# `spot.figures` (the same code as `spot figures`). Each figure is shown inline and written to
# `out_dir` as a PNG.
#
# * Notebook: `jupytext --to notebook analysis/figures.py` and open it in Jupyter, or execute it
#   with papermill (parameters in the cell tagged `parameters` below):
#   `jupytext --to notebook analysis/figures.py -o /tmp/figures.ipynb &&
#   papermill /tmp/figures.ipynb /tmp/figures-run.ipynb -p fig2_dataset hopper-medium-replay`
# * Script: `python analysis/figures.py` writes the PNGs and prints the Fig. 2 numbers.
#
# Which runs: `fig2_experiments` if given; otherwise, as `spot tables --table 1` picks Table 1's
# runs (Fig. 2 is drawn from Table 1's PT and SPOT runs), the `table1` experiment, else
# `table1-smoke`, else every experiment in the store. `smoke=True` reads `table1-smoke` only.
# Rendering is headless (MuJoCo with `MUJOCO_GL=egl`, set by `spot.runtime.configure()` when unset).

# %%
import os
from pathlib import Path

from spot import SpotError, figures, runtime, tracking
from spot.results import load, tables

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
fig2_experiments: str = os.environ.get("SPOT_FIG2_EXPERIMENTS", "")  # comma-separated; "": as spot tables --table 1
smoke: bool = os.environ.get("SPOT_SMOKE", "") in ("1", "true")  # read table1-smoke
sweep_id: str = os.environ.get("SPOT_SWEEP_ID", "")  # only the runs of this sweep (tag sweep_id)
fig2_dataset: str = os.environ.get("SPOT_FIG2_DATASET", "")  # the paper's dataset name, if the runs span several
fig2_source: str = os.environ.get("SPOT_FIG2_SOURCE", "")  # recipe or file, if the runs span both
ddof: int = int(os.environ.get("SPOT_DDOF", "1"))  # std over runs: 1 sample, 0 population
fig4_run: str = os.environ.get("SPOT_FIG4_RUN", "")  # run whose projection to show; "": the first SPOT run with one
cvae: str = os.environ.get("SPOT_CVAE", "")  # Fig. 3: a CVAE stage-cache entry ($SPOT_CACHE_DIR/cvae-<hash>.npz)
cvae_dataset: str = os.environ.get("SPOT_CVAE_DATASET", "hopper-medium-expert")  # the dataset that CVAE was trained on
cvae_size: str = os.environ.get("SPOT_CVAE_SIZE", "small")  # tiny, small or paper
fig3_index: str = os.environ.get("SPOT_FIG3_INDEX", "100,200")  # dataset transitions to render, comma-separated
out_dir: str = os.environ.get("SPOT_ANALYSIS_OUT", "analysis/out")  # where the PNGs are written


# %%
def show_png(path: Path) -> None:
    if INLINE:
        display(Image(filename=str(path)))
    print(f"wrote {path}")


URI = tracking.resolve_uri(tracking_uri or None, read=True)  # the store to read; it must exist
OUT = Path(out_dir)
OUT.mkdir(parents=True, exist_ok=True)
if fig2_experiments:
    experiments = [n.strip() for n in fig2_experiments.split(",") if n.strip()]
elif smoke:
    experiments = [tables.SWEEP_EXPERIMENTS[1] + "-smoke"]
else:
    experiments = tables.default_experiments(1, URI)
runs = load.load_runs(URI, experiments, sweep_id or None)
print(f"{len(runs)} runs from {', '.join(experiments) if experiments else 'every experiment'}")

# %% [markdown]
# ## Fig. 2: extrapolation error vs cos(s, ĝ)
# Per run, the binned error comes from its `extrapolation_error.json` artifact (or the
# `diag/extrap_bin_*` metrics); the curves are the mean over runs per bin, the bands ± std.

# %%
try:
    bins = figures.extrapolation_bins(runs, URI, dataset=fig2_dataset or None, source=fig2_source or None)
except SpotError as e:
    print(f"Fig. 2 not drawn: {e}")
else:
    summary = figures.summarize_extrapolation(bins, ddof=ddof)
    if INLINE:
        display(Markdown("**Fig. 2: mean extrapolation error per method, group and bin**"), summary.round(3))
    else:
        print(summary.round(3).to_string(index=False))
    show_png(figures.plot_fig2(bins, OUT / "fig2.png", ddof=ddof))

# %% [markdown]
# ## Fig. 4: observations and subgoals, PCA
# Every SPOT run logs `subgoal_projection.png`; this shows one.

# %%
finished_spot = (runs["method"] == "spot") & (runs["status"] == "FINISHED")
candidates = [fig4_run] if fig4_run else list(runs.loc[finished_spot, "run_id"])
fig4, missing = None, []
for run_id in candidates:
    try:
        fig4 = figures.fetch_artifact(run_id, figures.FIG4_ARTIFACT, OUT / "fig4.png", URI)
        break
    except SpotError as e:
        missing.append(str(e))
if fig4:
    show_png(fig4)
else:
    print("Fig. 4 not drawn: no finished SPOT run with a subgoal projection", *missing[-3:], sep="\n")

# %% [markdown]
# ## Fig. 3: a state and its predicted subgoal
# ĝ is the CVAE's prior-mean subgoal for the dataset transition (s, a); both are rendered from the
# side with MuJoCo.

# %%
if cvae:
    from spot.data import registry

    params = figures.load_cvae(cvae)
    ds, _ = registry.load(cvae_dataset, cvae_size, progress=False)
    index = [int(i) for i in fig3_index.split(",")]
    obs, goal = figures.pairs_from_cvae(params, ds.observations, ds.actions, index)
    show_png(figures.render_state_and_subgoal(cvae_dataset, obs, goal, OUT / "fig3.png"))
else:
    print("Fig. 3 not drawn: set cvae to a CVAE stage-cache entry (and cvae_dataset to its dataset)")
