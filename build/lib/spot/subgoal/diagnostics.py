"""Subgoal diagnostics: extrapolation error vs subgoal proximity (SPOT paper, §5.3, Fig. 2),
precision/recall of generated subgoals and a PCA projection (App. C.1.1, Fig. 4).

* :func:`extrapolation_error_bins`: the paper defines extrapolation error as
  ``|r_model - r_true|``. The model reward and the dataset reward live on unrelated scales
  (PT's reward is identified only up to shift and scale), so each is first z-scored over the whole
  dataset passed in; the error is ``|z(r_model) - z(r_true)|``, in units of standard deviations.
  Errors are binned by ``cos(s, ĝ)`` (the x-axis of Fig. 2), separately for in-distribution
  transitions (those inside the labelled query segments the reward model was trained on) and
  out-of-distribution ones (all others).
* :func:`precision_recall`: the k-NN manifold estimate of Kynkäänniemi et al. (2019,
  "Improved Precision and Recall Metric for Assessing Generative Models"). Each sample of a set
  gets a ball whose radius is the distance to its k-th nearest neighbour in that set; precision
  is the fraction of generated samples inside some real ball, recall the fraction of real samples
  inside some generated ball. Here "real" = extracted subgoals, "generated" = CVAE subgoals,
  both in state space (z-scored with the real set's statistics by default).
* :func:`plot_projection`: 2-D PCA (fitted on the observations) of observations (blue) and
  subgoals (red), like the PCA panel of Fig. 4.

Figures are drawn on a bare :class:`matplotlib.figure.Figure` (Agg canvas), so importing this
module never touches pyplot's global backend.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.figure import Figure
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from spot import SpotError

GROUP_NAMES = ("in_distribution", "ood")


class ExtrapolationTable(NamedTuple):
    """Binned extrapolation error. Row 0 = in-distribution, row 1 = OOD (``GROUP_NAMES``).

    Attributes:
      edges: ``[bins + 1]`` cosine-similarity bin edges.
      mean_error: ``[2, bins]`` mean ``|z(r_model) - z(r_true)|`` per bin (NaN where empty).
      count: ``[2, bins]`` transitions per bin.
      overall: ``[2]`` mean error over each whole group (NaN if the group is empty).
    """

    edges: np.ndarray
    mean_error: np.ndarray
    count: np.ndarray
    overall: np.ndarray

    def metrics(self, prefix: str = "diag/extrapolation_error") -> dict[str, float]:
        """Flat scalars for logging: the overall error per group."""
        return {f"{prefix}_{name}": float(v) for name, v in zip(GROUP_NAMES, self.overall, strict=True)}


def _zscore(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    std = x.std()
    return (x - x.mean()) / (std if std > 0 else 1.0)


def extrapolation_error_bins(
    r_model: np.ndarray, r_true: np.ndarray, cos_sim: np.ndarray, in_dist_mask: np.ndarray, bins: int | np.ndarray = 10
) -> ExtrapolationTable:
    """Mean ``|z(r_model) - z(r_true)|`` per ``cos(s, ĝ)`` bin, in-distribution vs OOD.

    Args:
      r_model, r_true, cos_sim: ``[N]`` over the whole dataset.
      in_dist_mask: ``[N]`` bool, True for transitions inside labelled segments.
      bins: number of equal-width bins over ``[min cos, max cos]``, or explicit increasing edges
        (values outside them are left out). Bins are half-open ``[e_i, e_{i+1})`` except the
        last, which includes its right edge.
    """
    cos_sim = np.asarray(cos_sim, dtype=np.float64)
    in_dist = np.asarray(in_dist_mask, dtype=bool)
    err = np.abs(_zscore(r_model) - _zscore(r_true))
    if np.ndim(bins) == 0:
        lo, hi = float(cos_sim.min()), float(cos_sim.max())
        edges = np.linspace(lo, hi if hi > lo else lo + 1e-6, int(bins) + 1)
    else:
        edges = np.asarray(bins, dtype=np.float64)
    n_bins = edges.size - 1
    which = np.clip(np.searchsorted(edges, cos_sim, side="right") - 1, 0, n_bins - 1)
    inside = (cos_sim >= edges[0]) & (cos_sim <= edges[-1])
    count = np.zeros((2, n_bins), np.int64)
    total = np.zeros((2, n_bins))
    overall = np.full(2, np.nan)
    for row, group in enumerate((in_dist, ~in_dist)):
        sel = group & inside
        count[row] = np.bincount(which[sel], minlength=n_bins)
        total[row] = np.bincount(which[sel], weights=err[sel], minlength=n_bins)
        if group.any():
            overall[row] = err[group].mean()
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_error = np.where(count > 0, total / count, np.nan)
    return ExtrapolationTable(edges=edges, mean_error=mean_error, count=count, overall=overall)


def plot_extrapolation(
    tables: dict[str, ExtrapolationTable], path: str | Path, groups: tuple[str, ...] = GROUP_NAMES
) -> Path:
    """Fig. 2-style line plot: mean error vs bin centre, one line per (table, group).

    Args:
      tables: label -> table, e.g. ``{"PT": t_pt, "SPOT": t_spot}``.
      path: output PNG path (parent folders are created).
      groups: which groups to draw (``GROUP_NAMES`` subset).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(5, 3.5))
    ax = fig.add_subplot()
    for label, table in tables.items():
        centres = 0.5 * (table.edges[:-1] + table.edges[1:])
        for group in groups:
            row = GROUP_NAMES.index(group)
            style = "-o" if group == "in_distribution" else "--s"
            ax.plot(centres, table.mean_error[row], style, ms=3, label=f"{label} ({group})")
    ax.set_xlabel("cos(s, ĝ)")
    ax.set_ylabel("|z(r_model) − z(r_true)|")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def _subsample(x: np.ndarray, max_points: int, rng: np.random.Generator) -> np.ndarray:
    if x.shape[0] <= max_points:
        return x
    return x[rng.choice(x.shape[0], max_points, replace=False)]


def _knn_radii(x: np.ndarray, k: int) -> np.ndarray:
    """Distance of each row to its k-th nearest neighbour in ``x`` (itself excluded)."""
    k_eff = min(k, x.shape[0] - 1)
    dist, _ = cKDTree(x).query(x, k=k_eff + 1)
    return dist[:, -1]


def _inside_any_ball(queries: np.ndarray, centres: np.ndarray, radii: np.ndarray, chunk: int = 1024) -> np.ndarray:
    """``[len(queries)]`` bool: within ``radii[j]`` of some ``centres[j]``."""
    hit = np.zeros(queries.shape[0], bool)
    for start in range(0, queries.shape[0], chunk):
        d = cdist(queries[start : start + chunk], centres)
        hit[start : start + chunk] = (d <= radii[None, :]).any(axis=1)
    return hit


def precision_recall(
    real: np.ndarray, generated: np.ndarray, k: int = 3, max_points: int = 2000, standardize: bool = True, seed: int = 0
) -> dict[str, float]:
    """k-NN precision and recall of generated vs real samples (Kynkäänniemi et al., 2019).

    Args:
      real: ``[N_r, d]`` extracted subgoals.
      generated: ``[N_g, d]`` CVAE subgoals.
      k: neighbourhood size of the manifold balls.
      max_points: each set is subsampled (without replacement, ``seed``) to at most this many.
      standardize: z-score both sets with the real set's mean and std first.

    Returns:
      ``{"subgoal/precision", "subgoal/recall"}``.
    """
    if real.shape[0] < 2 or generated.shape[0] < 2:
        raise SpotError(f"need at least 2 samples per set, got {real.shape[0]} real and {generated.shape[0]} generated")
    rng = np.random.default_rng(seed)
    real = _subsample(np.asarray(real, np.float64), max_points, rng)
    generated = _subsample(np.asarray(generated, np.float64), max_points, rng)
    if standardize:
        mean, std = real.mean(axis=0), real.std(axis=0)
        std = np.where(std > 0, std, 1.0)
        real, generated = (real - mean) / std, (generated - mean) / std
    precision = _inside_any_ball(generated, real, _knn_radii(real, k)).mean()
    recall = _inside_any_ball(real, generated, _knn_radii(generated, k)).mean()
    return {"subgoal/precision": float(precision), "subgoal/recall": float(recall)}


def plot_projection(
    obs: np.ndarray, subgoals: np.ndarray, path: str | Path, max_points: int = 5000, seed: int = 0
) -> Path:
    """PCA scatter (fitted on ``obs``) of observations (blue) and subgoals (red), Fig. 4 style."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    obs = _subsample(np.asarray(obs, np.float64), max_points, rng)
    subgoals = _subsample(np.asarray(subgoals, np.float64), max_points, rng)
    mean = obs.mean(axis=0)
    _, _, vt = np.linalg.svd(obs - mean, full_matrices=False)
    basis = vt[:2].T  # [d, 2] (fewer columns if d < 2)
    fig = Figure(figsize=(4.5, 4))
    ax = fig.add_subplot()
    styles = ((obs, "tab:blue", "observations", 3, 0.3), (subgoals, "tab:red", "subgoals", 8, 0.8))
    for pts, colour, label, size, alpha in styles:  # subgoals drawn on top
        proj = (pts - mean) @ basis
        ys = proj[:, 1] if proj.shape[1] > 1 else np.zeros(len(proj))
        ax.scatter(proj[:, 0], ys, s=size, alpha=alpha, c=colour, label=label, linewidths=0)
    ax.set_xlabel("PC 1")
    ax.set_ylabel("PC 2")
    ax.legend(markerscale=4, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path
