"""Interval estimates for scores over seeds and datasets, the way reviewers of RL papers ask for them.

Agarwal et al. (2021, "Deep RL at the edge of the statistical precipice") recommend, per method
across a benchmark's tasks, the interquartile mean (IQM) and the probability of improvement, each
with a 95 % **stratified bootstrap** confidence interval: the runs of every task (dataset) are
resampled with replacement independently, so each resample keeps every task with its own number
of seeds. Their package ``rliable`` does not import beside this project's pins (``arch`` < 8, which
it requires, fails on pandas 3), so the resampling is SciPy's :func:`scipy.stats.bootstrap`, which
resamples every sample it is given independently: given the per-task arrays as separate samples it
is exactly the stratified bootstrap. CIs are percentile intervals.

Every function takes ``strata``: a sequence of 1-D arrays, one per task, each with that task's
per-seed scores. A CI needs at least two values in every stratum; otherwise it is ``(nan, nan)``
and the verdict says "too few seeds".
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import stats as sps
from scipy.optimize import brentq

CONFIDENCE = 0.95
N_RESAMPLES = 20000
SEED_CHECKS = 4  # estimate() redraws the CI under this many other bootstrap seeds (verdict stability)
SUPPORTED, NOT_SUPPORTED, INCONCLUSIVE, TOO_FEW = ("supported", "not supported", "inconclusive", "too few seeds")


def _arrays(strata: Sequence[Sequence[float]]) -> list[np.ndarray]:
    return [np.asarray(s, dtype=np.float64).ravel() for s in strata]


def _sorted(strata: Sequence[Sequence[float]]) -> list[np.ndarray]:
    """Each stratum in ascending order: a resample draws positions, so sorting first makes an
    unpaired CI a function of each stratum's values alone, not of the order the runs were listed in
    (a re-exported results file lists them in another order and must give the same report)."""
    return [np.sort(a) for a in _arrays(strata)]


def _bootstrap(
    samples: Sequence[np.ndarray],
    statistic: Callable[..., np.ndarray],
    *,
    paired: bool,
    vectorized: bool,
    confidence: float = CONFIDENCE,
    n_resamples: int = N_RESAMPLES,
    seed: int = 0,
) -> Any:
    """SciPy's bootstrap with percentile intervals, seeded: independent resamples of each sample,
    or (``paired``) of the samples' positions together."""
    return sps.bootstrap(
        tuple(samples),
        statistic,
        n_resamples=n_resamples,
        confidence_level=confidence,
        method="percentile",
        vectorized=vectorized,
        paired=paired,
        rng=np.random.default_rng(seed),
    )


def bootstrap_ci(
    strata: Sequence[Sequence[float]],
    statistic: Callable[..., np.ndarray],
    *,
    confidence: float = CONFIDENCE,
    n_resamples: int = N_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile CI of ``statistic(*strata, axis=-1)`` under the stratified bootstrap.

    ``statistic`` must be vectorised: it receives arrays whose last axis holds one resample of
    each stratum. Returns ``(nan, nan)`` when a stratum has fewer than two values.
    """
    arrays = _sorted(strata)
    if not arrays or min(len(a) for a in arrays) < 2:
        return float("nan"), float("nan")
    if all(np.ptp(a) == 0 for a in arrays):  # every resample gives the same value
        v = float(statistic(*arrays, axis=-1))
        return v, v
    res = _bootstrap(
        arrays, statistic, paired=False, vectorized=True, confidence=confidence, n_resamples=n_resamples, seed=seed
    )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


# --------------------------------------------------------------------------- statistics
def mean_of_means(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """The mean over strata of each stratum's mean (every dataset weighs the same)."""
    return np.mean([np.mean(s, axis=axis) for s in strata], axis=0)


def iqm(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean of all runs pooled over strata (the 25 % trimmed mean)."""
    return sps.trim_mean(np.concatenate(strata, axis=axis), 0.25, axis=axis)


def _split(strata: Sequence[np.ndarray]) -> tuple[Sequence[np.ndarray], Sequence[np.ndarray]]:
    if len(strata) % 2:
        raise ValueError("paired statistics take the x strata followed by as many y strata")
    half = len(strata) // 2
    return strata[:half], strata[half:]


def mean_difference(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """``strata = (x_1..x_M, y_1..y_M)``: mean over tasks of ``mean(x_m) - mean(y_m)``."""
    xs, ys = _split(strata)
    return np.mean([np.mean(x, axis=axis) - np.mean(y, axis=axis) for x, y in zip(xs, ys, strict=True)], axis=0)


def probability_of_improvement(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
    """``strata = (x_1..x_M, y_1..y_M)``: mean over tasks of P(X > Y) + ½ P(X = Y).

    Per task this is the Mann-Whitney U statistic divided by ``n_x n_y``.
    """
    xs, ys = _split(strata)
    per_task = []
    for x, y in zip(xs, ys, strict=True):
        x = np.moveaxis(np.asarray(x), axis, -1)[..., :, None]
        y = np.moveaxis(np.asarray(y), axis, -1)[..., None, :]
        per_task.append(((x > y) + 0.5 * (x == y)).mean(axis=(-2, -1)))
    return np.mean(per_task, axis=0)


# --------------------------------------------------------------------------- summaries
@dataclass(frozen=True)
class Estimate:
    """A point estimate with its 95 % CI and the number of values behind it."""

    value: float
    low: float
    high: float
    n: int
    # verdicts that other bootstrap seeds give (estimate()); empty when every seed agrees. A CI bound
    # is a Monte Carlo estimate: when one lies near 0 its side of 0 can change with the seed.
    other_verdicts: tuple[str, ...] = ()

    def text(self, digits: int = 1) -> str:
        if np.isnan(self.low):
            return f"{self.value:.{digits}f} (CI n/a)"
        return f"{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def cell(values: Sequence[float], *, seed: int = 0) -> dict[str, float]:
    """One table cell: ``n``, ``mean``, sample ``std`` (ddof 1) and the mean's bootstrap CI."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    low, high = bootstrap_ci([x], mean_of_means, seed=seed)
    return {
        "n": len(x),
        "mean": float(x.mean()) if len(x) else float("nan"),
        "std": float(x.std(ddof=1)) if len(x) > 1 else float("nan"),
        "ci_low": low,
        "ci_high": high,
    }


def estimate(
    strata: Sequence[Sequence[float]], statistic: Callable[..., np.ndarray], *, seed: int = 0, checks: int = SEED_CHECKS
) -> Estimate:
    """``statistic`` on ``strata`` with its stratified-bootstrap CI (bootstrap seed ``seed``), and the
    verdicts that ``checks`` other bootstrap seeds (``seed + 1`` ...) would give where they differ."""
    arrays = _arrays(strata)
    value, n = float(statistic(*arrays, axis=-1)), sum(len(a) for a in arrays)
    est = Estimate(value, *bootstrap_ci(arrays, statistic, seed=seed), n)
    redrawn = (Estimate(value, *bootstrap_ci(arrays, statistic, seed=seed + k), n) for k in range(1, checks + 1))
    others = {verdict(e) for e in redrawn}
    others.discard(verdict(est))
    return replace(est, other_verdicts=tuple(sorted(others)))


def verdict(est: Estimate, null: float = 0.0) -> str:
    """``supported`` if the CI lies above ``null``, ``not supported`` if below, else inconclusive."""
    if np.isnan(est.low):
        return TOO_FEW
    if est.low > null:
        return SUPPORTED
    if est.high < null:
        return NOT_SUPPORTED
    return INCONCLUSIVE


EXACT_LIMIT = 200_000  # permutation_p enumerates every relabelling up to this many, else draws N_RESAMPLES


def _relabellings(n: int, k: int) -> np.ndarray:
    """Every way to choose which ``k`` of ``n`` pooled runs form arm x: a bool array [C(n, k), n]."""
    rows = list(itertools.combinations(range(n), k))
    out = np.zeros((len(rows), n), bool)
    out[np.repeat(np.arange(len(rows)), k), np.asarray(rows, np.int64).ravel()] = True
    return out


def permutation_p(strata: Sequence[Sequence[float]], *, n_resamples: int = N_RESAMPLES, seed: int = 0) -> float:
    """Two-sided p-value of :func:`mean_difference` (``strata = (x_1..x_M, y_1..y_M)``) under the
    stratified permutation null: within each task the runs of both arms are exchangeable, so every
    split of a task's pooled runs into its two arms' sizes is as likely as the one observed. The
    relabellings are enumerated exactly while their number (the product over tasks of
    C(n_x + n_y, n_x)) is at most :data:`EXACT_LIMIT`; otherwise ``n_resamples`` are drawn
    (seeded), each one-sided count taking one more hit and one more draw. Two-sided as SciPy's
    ``permutation_test`` has it: twice the smaller one-sided p, at most 1. SciPy's function
    relabels across all samples together and cannot keep tasks apart, hence this one.

    The smallest p over one task is 2 / C(n_x + n_y, n_x): 0.1 at 3 vs 3, so that no verdict on
    one task at 3 vs 3 runs can pass at 0.05; 2/56 = 0.036 at 5 vs 3; 2/252 at 5 vs 5. ``nan``
    when a task has no runs in an arm or a score is not finite."""
    xs, ys = _split(_arrays(strata))
    if not xs or min(min(len(x) for x in xs), min(len(y) for y in ys)) == 0:
        return float("nan")
    if not all(np.isfinite(a).all() for a in (*xs, *ys)):
        return float("nan")  # a missing score is the caller's to drop, not a value to relabel
    pooled = [np.concatenate([x, y]) for x, y in zip(xs, ys, strict=True)]
    observed = float(mean_difference(*xs, *ys))
    sizes = [math.comb(len(v), len(x)) for v, x in zip(pooled, xs, strict=True)]
    rng = np.random.default_rng(seed)
    if math.prod(sizes) <= EXACT_LIMIT:
        masks = [_relabellings(len(v), len(x)) for v, x in zip(pooled, xs, strict=True)]
        grids = np.meshgrid(*[np.arange(len(m)) for m in masks], indexing="ij")
        picks = [m[g.ravel()] for m, g in zip(masks, grids, strict=True)]  # [R, n_m] per task
        exact = True
    else:
        picks = []
        for v, x in zip(pooled, xs, strict=True):
            order = rng.permuted(np.tile(np.arange(len(v)), (n_resamples, 1)), axis=1)
            picks.append(order < len(x))
        exact = False
    diffs = []
    for v, mask in zip(pooled, picks, strict=True):
        n_x = mask[0].sum()
        x_mean = (mask * v).sum(axis=1) / n_x
        y_mean = (~mask * v).sum(axis=1) / (len(v) - n_x)
        diffs.append(x_mean - y_mean)
    null, tol = np.mean(diffs, axis=0), 1e-9 * max(1.0, abs(observed))
    above, below = int(np.sum(null >= observed - tol)), int(np.sum(null <= observed + tol))
    if exact:
        one_sided = min(above, below) / len(null)
    else:
        one_sided = (min(above, below) + 1) / (len(null) + 1)
    return min(1.0, 2 * one_sided)


def verdict_rate(
    pool: Sequence[float],
    n_x: int,
    n_y: int,
    *,
    shift: float = 0.0,
    permutation: bool,
    trials: int = 1000,
    n_resamples: int = 2000,
    alpha: float = 1 - CONFIDENCE,
    seed: int = 0,
) -> float:
    """How often the verdict rule calls a difference: per trial, ``n_x`` and ``n_y`` scores drawn
    from ``pool`` with replacement, ``shift`` added to x's, and a call (*supported* or *not
    supported*) if the 95 % bootstrap CI of the mean difference excludes 0 (and, with
    ``permutation``, :func:`permutation_p` is below ``alpha``). At ``shift`` 0 the arms are
    exchangeable and this is the rule's false-verdict rate (nominal: ``alpha``); above 0, its power."""
    values = np.asarray(pool, np.float64)
    rng = np.random.default_rng(seed)
    called = 0
    for t in range(trials):
        x, y = rng.choice(values, n_x) + shift, rng.choice(values, n_y)
        low, high = bootstrap_ci([x, y], mean_difference, n_resamples=n_resamples, seed=seed + t)
        if (low > 0 or high < 0) and (not permutation or permutation_p([x, y]) < alpha):
            called += 1
    return called / trials


def min_permutation_p(sizes: Sequence[tuple[int, int]]) -> float:
    """The smallest p :func:`permutation_p` can return for arms of ``sizes`` (``(n_x, n_y)`` per task)
    when it enumerates: 2 / (the number of relabellings), at most 1. (Past :data:`EXACT_LIMIT`
    relabellings it samples, and its smallest p is 2 / (N_RESAMPLES + 1): far below 0.05 either way.)"""
    return min(1.0, 2.0 / math.prod(math.comb(a + b, a) for a, b in sizes))


def permutation_floor(tasks: int, alpha: float = 1 - CONFIDENCE) -> int:
    """The fewest runs per arm and task (equal arms) at which :func:`permutation_p` can fall below
    ``alpha``: 4 on one task at 0.05 (2/70), 3 on two (2/400)."""
    return next(m for m in itertools.count(1) if min_permutation_p([(m, m)] * tasks) < alpha)


def t_test_power(d: float, n_x: float, n_y: float, alpha: float = 1 - CONFIDENCE, df: float | None = None) -> float:
    """Power of the two-sided two-sample t-test (equal variances) at standardised effect ``d``:
    P(|T| > t_crit) with T noncentral t on ``df`` degrees of freedom (n_x + n_y − 2 unless given)
    and noncentrality d / √(1/n_x + 1/n_y) (SciPy's ``nct``). Where ``nct`` returns nan (from
    noncentralities of ~8 on; the power there is above 0.94 at 6 or more degrees of freedom, and
    the fallback within 1e-6 of it) the normal approximation stands in."""
    df = n_x + n_y - 2 if df is None else df
    nc = d / math.sqrt(1 / n_x + 1 / n_y)
    crit = float(sps.t.ppf(1 - alpha / 2, df))
    power = float(sps.nct.sf(crit, df, nc) + sps.nct.cdf(-crit, df, nc))
    if math.isnan(power):
        power = float(sps.norm.sf(crit - nc) + sps.norm.cdf(-crit - nc))
    return power


MAX_PLAN = 10_000  # power_plan's runs per arm and task: beyond this many it says inf


@dataclass(frozen=True)
class Plan:
    """What a comparison's runs could detect, and how many would detect its observed effect."""

    sd: float  # the pooled within-task standard deviation of both arms' runs (ddof 1 per task and arm)
    mde: float  # the smallest |effect| found with ``power`` at the arms' sizes (inf: the test cannot pass)
    runs: float  # runs per arm and task to find the observed |effect| with ``power`` (inf: > MAX_PLAN)


def power_plan(
    strata: Sequence[Sequence[float]], *, power: float = 0.8, alpha: float = 1 - CONFIDENCE, min_runs: int = 1
) -> Plan:
    """Planning numbers for :func:`mean_difference` over ``strata = (x_1..x_M, y_1..y_M)``, from the
    two-sided two-sample t-test's power (:func:`t_test_power`) at the pooled within-task standard
    deviation (N − 2M degrees of freedom over N runs). The effect averages the M tasks'
    differences, so with m_x,i and m_y,i runs in task i its variance is sd² Σ (1/m_x,i + 1/m_y,i) / M²:
    a t-test's with the effective sizes M² / Σ 1/m_x,i and M² / Σ 1/m_y,i per arm (M m_x and M m_y
    where the tasks' sizes are equal; fewer where they differ).
    ``mde``: the effect the arms' current sizes find with ``power`` (inf where even the most extreme
    split gives a permutation p of at least ``alpha``: :func:`min_permutation_p`); ``runs``: the
    fewest runs per arm and task, equal arms, that find the observed |effect| with ``power``, no
    fewer than ``min_runs`` nor than the permutation test needs to reach p below ``alpha``. Both are
    the t-test's: near the permutation floor the permutation test finds less (at 4 vs 4 runs on one
    task it finds the t-test's 80 % effect ~64 % of the time: only the complete separation passes).
    The observed effect is itself an estimate with its CI: ``runs`` plans the next runs, it is no
    finding. ``nan`` where an arm of a task has fewer than 2 runs or the sd is 0 or not finite."""
    xs, ys = _split(_arrays(strata))
    nan = Plan(float("nan"), float("nan"), float("nan"))
    if not xs or min(len(a) for a in (*xs, *ys)) < 2 or not all(np.isfinite(a).all() for a in (*xs, *ys)):
        return nan
    dof = sum(len(a) - 1 for a in (*xs, *ys))
    sd = math.sqrt(sum(float(np.sum((a - a.mean()) ** 2)) for a in (*xs, *ys)) / dof)
    if not sd > 0:
        return nan
    tasks = len(xs)
    n_x, n_y = (tasks**2 / sum(1 / len(a) for a in arm) for arm in (xs, ys))  # effective sizes
    # power rises with the effect and with the runs: the effect is a root (brentq), the runs a
    # bisection over integers
    if min_permutation_p([(len(x), len(y)) for x, y in zip(xs, ys, strict=True)]) >= alpha:
        mde = math.inf
    else:
        mde = sd * float(brentq(lambda d: t_test_power(d, n_x, n_y, alpha, dof) - power, 1e-9, 1e3))

    d = abs(float(mean_difference(*xs, *ys))) / sd

    def power_at(m: int) -> float:  # m runs per arm and task
        return t_test_power(d, m * tasks, m * tasks, alpha, 2 * tasks * (m - 1))

    low, high = max(permutation_floor(tasks, alpha), min_runs), MAX_PLAN  # runs per arm and task
    if d == 0 or power_at(high) < power:
        return Plan(sd, mde, math.inf)
    if power_at(low) >= power:
        return Plan(sd, mde, float(low))
    while high - low > 1:  # the power at low runs < power <= the power at high runs
        mid = (low + high) // 2
        low, high = (low, mid) if power_at(mid) >= power else (mid, high)
    return Plan(sd, mde, float(high))


def sign_flip_p(strata: Sequence[Sequence[float]], *, n_resamples: int = N_RESAMPLES, seed: int = 0) -> float:
    """Two-sided p-value of :func:`mean_of_means` of paired differences (one stratum per task)
    under the sign-flip null: within a pair the two arms are exchangeable, so each difference is
    as likely to carry either sign. SciPy's :func:`scipy.stats.permutation_test` on one sample
    (``permutation_type="samples"`` flips signs), exact while the 2^N sign patterns of the N
    differences number at most ``n_resamples``. The smallest p it can give is 2 / 2^N: no pattern
    of five or fewer differences reaches 0.05. ``nan`` without differences or with a non-finite one;
    1 for a single difference (its two sign patterns are equally extreme; SciPy needs two)."""
    arrays = _arrays(strata)
    if not arrays or min(len(a) for a in arrays) == 0 or not all(np.isfinite(a).all() for a in arrays):
        return float("nan")
    if sum(len(a) for a in arrays) == 1:
        return 1.0
    bounds = np.cumsum([len(a) for a in arrays])[:-1]

    def statistic(d: np.ndarray, axis: int = -1) -> np.ndarray:
        return mean_of_means(*np.split(d, bounds, axis=axis), axis=axis)

    res = sps.permutation_test(
        (np.concatenate(arrays),),
        statistic,
        permutation_type="samples",
        vectorized=True,
        n_resamples=n_resamples,
        alternative="two-sided",
        rng=np.random.default_rng(seed),
    )
    return float(res.pvalue)


def sign_flip_exact(n: int, n_resamples: int = N_RESAMPLES) -> bool:
    """Whether :func:`sign_flip_p` enumerates every one of the 2^n sign assignments of ``n``
    differences (SciPy's ``permutation_test`` does while they number at most ``n_resamples``);
    otherwise it draws ``n_resamples`` of them."""
    return n >= 1 and 2**n <= n_resamples


def spearman(u: np.ndarray, v: np.ndarray, axis: int = -1) -> np.ndarray:
    """Spearman's ρ along ``axis``, vectorised: Pearson's correlation of the average ranks (ties share
    their mean rank, as :func:`scipy.stats.spearmanr` does); nan where u or v is constant."""
    ru, rv = sps.rankdata(u, axis=axis), sps.rankdata(v, axis=axis)
    du, dv = ru - ru.mean(axis=axis, keepdims=True), rv - rv.mean(axis=axis, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sum(du * dv, axis=axis) / np.sqrt(np.sum(du * du, axis=axis) * np.sum(dv * dv, axis=axis))


def rank_correlation(x: Sequence[float], y: Sequence[float], *, seed: int = 0) -> Estimate:
    """Spearman's rank correlation of paired values with a 95 % percentile CI from SciPy's paired
    bootstrap (the pairs are resampled together). Resamples whose x or y values are all equal have
    no correlation and are left out of the percentiles. The CI is ``(nan, nan)`` below 4 pairs; the
    value too below 2 pairs or when x or y is constant."""
    a, b = _arrays([x, y])
    if len(a) != len(b):
        raise ValueError(f"rank_correlation: {len(a)} x values but {len(b)} y values")
    if len(a) < 2 or np.ptp(a) == 0 or np.ptp(b) == 0:  # constant values have no rank correlation
        return Estimate(float("nan"), float("nan"), float("nan"), len(a))
    order = np.lexsort((b, a))  # pairs in (x, y) order: the CI does not depend on how they were listed
    a, b = a[order], b[order]
    value = float(spearman(a, b))
    if len(a) < 4:
        return Estimate(value, float("nan"), float("nan"), len(a))
    with warnings.catch_warnings():  # the constant resamples (their rho is nan, left out below)
        warnings.simplefilter("ignore", (sps.DegenerateDataWarning, RuntimeWarning))
        res = _bootstrap((a, b), spearman, paired=True, vectorized=True, seed=seed)
    tail = 100 * (1 - CONFIDENCE) / 2
    low, high = np.nanpercentile(res.bootstrap_distribution, [tail, 100 - tail])
    return Estimate(value, float(low), float(high), len(a))
