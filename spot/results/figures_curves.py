"""Pictures of results: evaluation curves over seeds with CI bands, and a performance profile.

Both take a runs frame of :func:`spot.results.load.load` (from results CSVs or an MLflow store) and
use its finished runs (:func:`spot.results.select.finished`).

* **Curves** (:func:`curve_points`, :func:`summarize_curves`, :func:`draw_curves`): each run's
  evaluation curve (the ``curve.eval/score`` column of a results CSV, or the ``eval/score`` history
  read from MLflow by :func:`spot.results.export.add_curves`), grouped per method or per value of a
  param (``by``); at every step the mean over the group's runs (seeds) with a 95 % percentile
  bootstrap CI of that mean (:func:`spot.results.stats.bootstrap_ci`). One panel per dataset.
* **Performance profile** (:func:`profile`, :func:`draw_profile`): Agarwal et al.'s (2021) score
  distribution, as ``rliable.plot_utils.plot_performance_profiles`` draws it: for every threshold
  τ, the fraction of runs whose final normalised score is above τ (each dataset's fraction, averaged
  over datasets so every dataset weighs the same), with a 95 % stratified bootstrap band (the runs
  of each dataset resampled on their own). ``rliable`` itself does not install beside this
  project's pins (see :mod:`spot.results.stats`), so this is the same computation in NumPy/SciPy.

Figures are bare :class:`matplotlib.figure.Figure` objects; :func:`save` writes one in the format
of the file's extension, in one step (a temporary file renamed), so a failure leaves nothing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from spot import SpotError
from spot.results import stats
from spot.results.load import CURVE_COLUMN, parse_curve
from spot.results.select import finished
from spot.results.table_format import METHOD_LABELS

SCORE = "metrics.eval/score_final"
COLUMNS = 3  # panels (datasets) per row of the curves figure
N_RESAMPLES = 2000  # per step and group: a band to look at, not a verdict (the report's CIs use 20000)


def image_format(path: str | Path) -> str:
    """The output format named by ``path``'s extension; SpotError if matplotlib cannot write it."""
    from matplotlib.backend_bases import FigureCanvasBase

    fmt = Path(path).suffix.lower().lstrip(".")
    formats = FigureCanvasBase.get_supported_filetypes()
    if fmt not in formats:
        raise SpotError(f"--out {path}: unknown figure format {fmt!r}; use one of .{', .'.join(sorted(formats))}")
    return fmt


def save(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` in the format its extension names; nothing is left on failure."""
    path = Path(path)
    fmt = image_format(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise SpotError(f"--out {path}: folder '{folder}' does not exist; expected a file in an existing folder")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # created with the usual permissions
    try:
        fig.savefig(tmp, dpi=dpi, format=fmt)
        os.replace(tmp, path)
    except OSError as err:
        raise SpotError(f"--out {path}: cannot write it ({err.strerror})") from None
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path


def group_column(runs: pd.DataFrame, by: str) -> str:
    """The column ``by`` names: ``method``, or a param (``reward.lambda`` or ``params.reward.lambda``)."""
    if by == "method":
        return "method"
    col = by if by.startswith("params.") else f"params.{by}"
    if col not in runs:
        known = sorted(c[len("params.") :] for c in runs if c.startswith("params."))
        varied = [k for k in known if runs[f"params.{k}"].nunique(dropna=False) > 1]
        raise SpotError(f"--by {by}: the runs have no param {col[len('params.') :]!r}; params that vary: {varied}")
    return col


def _label(method: str, col: str, value: Any) -> str:
    name = METHOD_LABELS.get(method, method)
    return name if col == "method" else f"{name} {col[len('params.') :]}={value}"


# --------------------------------------------------------------------------- curves
def curve_points(runs: pd.DataFrame, by: str = "method") -> pd.DataFrame:
    """One row per (finished run, evaluation): ``run_id``, ``dataset``, ``group`` (the legend label:
    the method, or the method and the value of the param ``by``), ``seed``, ``step``, ``value``."""
    col = group_column(runs, by)
    if CURVE_COLUMN not in runs:
        raise SpotError(f"the runs have no evaluation curves (column {CURVE_COLUMN}); export them with curves")
    rows = []
    for _, r in finished(runs).iterrows():
        steps, values = parse_curve(r[CURVE_COLUMN], f"run {r['run_id']}")
        group = _label(r["method"], col, r[col])
        for step, value in zip(steps, values, strict=True):
            rows.append((r["run_id"], r["dataset"], group, r["seed"], int(step), float(value)))
    if not rows:
        raise SpotError("no finished run has an evaluation curve (eval/score) to draw")
    return pd.DataFrame(rows, columns=["run_id", "dataset", "group", "seed", "step", "value"])


def summarize_curves(points: pd.DataFrame, *, n_resamples: int = N_RESAMPLES, seed: int = 0) -> pd.DataFrame:
    """Per ``dataset``, ``group`` and ``step``: the mean over runs, its bootstrap CI (``low``,
    ``high``; NaN below two runs) and ``n`` (runs)."""
    rows = []
    for (dataset, group, step), g in points.groupby(["dataset", "group", "step"], sort=True):
        values = g["value"].to_numpy()
        low, high = stats.bootstrap_ci([values], stats.mean_of_means, n_resamples=n_resamples, seed=seed)
        rows.append((dataset, group, step, float(values.mean()), low, high, len(values)))
    return pd.DataFrame(rows, columns=["dataset", "group", "step", "mean", "low", "high", "n"])


def draw_curves(summary: pd.DataFrame, title: str = "") -> Figure:
    """One panel per dataset, one line per group: the mean over seeds and its 95 % CI band."""
    datasets = list(dict.fromkeys(summary["dataset"]))
    cols = min(len(datasets), COLUMNS)
    rows = -(-len(datasets) // cols)
    fig = Figure(figsize=(5.5 * cols, 4 * rows), layout="constrained")
    grid = fig.subplots(rows, cols, squeeze=False)
    axes = grid.ravel()
    for ax in axes[len(datasets) :]:
        ax.set_visible(False)
    for ax, dataset in zip(axes, datasets, strict=False):
        sub = summary[summary["dataset"] == dataset]
        for group, s in sub.groupby("group", sort=True):
            s = s.sort_values("step")
            line = ax.plot(s["step"], s["mean"], "-", lw=1.5, label=f"{group} (n={s['n'].max()})")[0]
            ax.fill_between(s["step"], s["low"], s["high"], color=line.get_color(), alpha=0.2, lw=0)
        ax.set_title(str(dataset), fontsize=9)
        ax.set_xlabel("IQL step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in grid[:, 0]:
        ax.set_ylabel("normalised score (mean over seeds, 95% CI)")
    if title:
        fig.suptitle(title, fontsize=9)
    return fig


# --------------------------------------------------------------------------- performance profile
def final_scores(runs: pd.DataFrame, metric: str = SCORE, by: str = "method") -> dict[str, dict[str, np.ndarray]]:
    """Per group (as :func:`curve_points` labels it) and dataset, the finished runs' ``metric``."""
    col = group_column(runs, by)
    if metric not in runs:
        raise SpotError(f"the runs have no metric {metric[len('metrics.') :]!r} (column {metric})")
    done = finished(runs).dropna(subset=[metric])
    if done.empty:
        raise SpotError(f"no finished run has {metric[len('metrics.') :]}")
    out: dict[str, dict[str, np.ndarray]] = {}
    for (method, value, dataset), g in done.groupby(["method", col, "dataset"], sort=True, dropna=False):
        out.setdefault(_label(method, col, value), {})[dataset] = g[metric].to_numpy(np.float64)
    return out


def _above(tau: float):  # the profile's statistic at one threshold, vectorised for the bootstrap
    def fraction(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean([np.mean(s > tau, axis=axis) for s in strata], axis=0)

    return fraction


def profile(
    scores: dict[str, dict[str, np.ndarray]],
    taus: np.ndarray | None = None,
    *,
    n_resamples: int = N_RESAMPLES,
    seed: int = 0,
) -> pd.DataFrame:
    """Per group and threshold τ: ``fraction`` of runs scoring above τ (averaged over the datasets
    every group has) and its stratified bootstrap CI (``low``, ``high``)."""
    common = set.intersection(*(set(d) for d in scores.values()))
    if not common:
        raise SpotError(f"no dataset has runs of every group {sorted(scores)}; a profile compares them on the same")
    datasets = sorted(common)
    if taus is None:
        top = max(float(np.max(scores[g][d])) for g in scores for d in datasets)
        taus = np.linspace(0.0, max(top, 1.0) * 1.02, 61)
    rows = []
    for group, per in scores.items():
        strata = [per[d] for d in datasets]
        for tau in taus:
            stat = _above(float(tau))
            low, high = stats.bootstrap_ci(strata, stat, n_resamples=n_resamples, seed=seed)
            rows.append((group, float(tau), float(stat(*strata)), low, high, sum(map(len, strata)), len(datasets)))
    return pd.DataFrame(rows, columns=["group", "tau", "fraction", "low", "high", "runs", "datasets"])


def draw_profile(prof: pd.DataFrame, metric: str = SCORE) -> Figure:
    """The profile: fraction of runs above τ against τ, one line and band per group."""
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    for group, s in prof.groupby("group", sort=True):
        line = ax.plot(s["tau"], s["fraction"], "-", lw=1.5, label=f"{group} ({s['runs'].iloc[0]} runs)")[0]
        ax.fill_between(s["tau"], s["low"], s["high"], color=line.get_color(), alpha=0.2, lw=0)
    k = int(prof["datasets"].iloc[0])
    ax.set_xlabel(f"normalised score τ ({metric[len('metrics.') :]})")
    ax.set_ylabel("fraction of runs with score > τ")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"performance profile over {k} dataset{'s' if k != 1 else ''} (95% stratified bootstrap)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return fig
