# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # The paper's figures from the MLflow runs
#
# Fig. 2 (extrapolation error vs similarity to the predicted subgoal), Fig. 4 (PCA of observations
# and subgoals) and Fig. 3 (a Hopper state rendered beside its predicted subgoal), all through
# `spot.figures` (the same code as `spot figures`).
#
# Run it as a script (`python analysis/figures.py`) or as a notebook after
# `jupytext --to notebook analysis/figures.py`. Parameters come from the environment:
#
# * `SPOT_TRACKING_URI`: the MLflow store (default as in `spot tables`).
# * `SPOT_FIG2_EXPERIMENTS` (default `table1`, `-smoke` added with `SPOT_SMOKE=1`), `SPOT_SWEEP_ID`,
#   `SPOT_FIG2_DATASET`, `SPOT_FIG2_SOURCE`: the PT/SPOT runs of Fig. 2 (one dataset, one source).
# * `SPOT_FIG4_RUN`: the run whose projection to copy (default: the first SPOT run that has one).
# * `SPOT_CVAE`, `SPOT_CVAE_DATASET`, `SPOT_CVAE_SIZE`, `SPOT_FIG3_INDEX` (comma-separated):
#   Fig. 3 needs a CVAE (a stage-cache entry, `~/.cache/spot/stages/cvae-*.pkl`) and the dataset it
#   was trained for; without `SPOT_CVAE` the cell only says so.
# * `SPOT_ANALYSIS_OUT` (default `analysis/out`).
#
# Rendering is headless (MuJoCo with `MUJOCO_GL=egl`, set by `spot.figures` when unset).

# %%
import os
from pathlib import Path

from spot import SpotError, figures, tables

TRACKING_URI = os.environ.get("SPOT_TRACKING_URI", "")
SUFFIX = "-smoke" if os.environ.get("SPOT_SMOKE") == "1" else ""
FIG2_EXPERIMENTS = os.environ.get("SPOT_FIG2_EXPERIMENTS", "table1" + SUFFIX).split(",")
SWEEP_ID = os.environ.get("SPOT_SWEEP_ID") or None
FIG2_DATASET = os.environ.get("SPOT_FIG2_DATASET") or None
FIG2_SOURCE = os.environ.get("SPOT_FIG2_SOURCE") or None
FIG4_RUN = os.environ.get("SPOT_FIG4_RUN") or None
CVAE = os.environ.get("SPOT_CVAE") or None
CVAE_DATASET = os.environ.get("SPOT_CVAE_DATASET", "hopper-medium-expert")
CVAE_SIZE = os.environ.get("SPOT_CVAE_SIZE", "small")
FIG3_INDEX = [int(i) for i in os.environ.get("SPOT_FIG3_INDEX", "100,200").split(",")]
OUT = Path(os.environ.get("SPOT_ANALYSIS_OUT", "analysis/out"))
OUT.mkdir(parents=True, exist_ok=True)

runs = tables.load_runs(TRACKING_URI, FIG2_EXPERIMENTS, SWEEP_ID)

# %% [markdown]
# ## Fig. 2: extrapolation error vs cos(s, ĝ)
# Per run, the binned error comes from its `extrapolation_error.json` artifact (or the
# `diag/extrap_bin_*` metrics); the curves are the mean over runs per bin, the bands ± std.

# %%
bins = figures.extrapolation_bins(runs, TRACKING_URI, dataset=FIG2_DATASET, source=FIG2_SOURCE)
fig2 = figures.plot_fig2(bins, OUT / "fig2.png")
summary = figures.summarize_extrapolation(bins)
print(summary.round(3).to_string(index=False))
print(f"wrote {fig2}")

# %% [markdown]
# ## Fig. 4: observations and subgoals, PCA
# Every SPOT run logs `subgoal_projection.png`; this copies one.

# %%
candidates = [FIG4_RUN] if FIG4_RUN else list(runs.loc[(runs["method"] == "spot") & (runs["status"] == "FINISHED"), "run_id"])
fig4 = None
for run_id in candidates:
    try:
        fig4 = figures.fetch_artifact(run_id, figures.FIG4_ARTIFACT, OUT / "fig4.png", TRACKING_URI)
        break
    except SpotError as e:
        print(e)
print(f"wrote {fig4}" if fig4 else "no run with a subgoal projection")

# %% [markdown]
# ## Fig. 3: a state and its predicted subgoal
# ĝ is the CVAE's prior-mean subgoal for the dataset transition (s, a); both are rendered from the
# side with MuJoCo.

# %%
if CVAE:
    from spot.data import registry

    params = figures.load_cvae(CVAE)
    ds, _ = registry.load(CVAE_DATASET, CVAE_SIZE, progress=False)
    obs, goal = figures.pairs_from_cvae(params, ds.observations, ds.actions, FIG3_INDEX)
    print(f"wrote {figures.render_state_and_subgoal(CVAE_DATASET, obs, goal, OUT / 'fig3.png')}")
else:
    print("Fig. 3 skipped: set SPOT_CVAE to a CVAE stage-cache entry (and SPOT_CVAE_DATASET)")
