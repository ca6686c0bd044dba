"""The two tests whose arms come from a table's design rather than from two filters alone.

* ``runner-up`` (:func:`runner_up`, the paper's Table 3): arm x against the best-scoring other arm,
  the other arms being the other values of the claim's ``by`` params among its runs. The runner-up
  is picked on the point estimates, so its CI is slightly optimistic for the runner-up; the row
  names it.
* ``queries`` (:func:`queries`, the paper's Table 4): x's change from the most to the fewest
  ``labels.num_queries`` minus y's (> 0: x loses less), per dataset, averaged over datasets. Its
  permutation test exchanges the seed-matched gains (x − y of one seed, which share that seed's
  reward model) between the two query counts within each dataset; without such pairs the row has no
  test and says its verdict is the CI's alone.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from spot.results import stats
from spot.results.claims import Claim
from spot.results.compare import (
    ALPHA,
    MIN_SEEDS,
    POWER,
    Row,
    compare,
    digest_spread,
    failures,
    median_time,
    seed_matched,
)
from spot.results.select import QUERIES, Filter, dataset_column, finished


def runner_up(df: pd.DataFrame, claim: Claim, metric: str, row: Row) -> Row:
    """Claim ``claim``'s arm x against the best-scoring other arm among its runs of ``df``."""
    cols = [f"params.{k}" for k in claim.by]
    if any(c not in df for c in cols):
        return row
    shaped = df[claim.among(df)]
    done = finished(shaped)
    others = done[~claim.x(done)] if len(done) else done
    if others.empty:
        return compare(shaped, claim.x, lambda d: claim.among(d) & ~claim.x(d), metric, row, claim.labels)
    means = others.groupby(cols)[metric].mean()
    best = means.idxmax()
    values = best if isinstance(best, tuple) else (best,)
    names = [_label(claim, key if isinstance(key, tuple) else (key,)) for key in means.index]
    if claim.others is not None and len(means) < claim.others:
        row.notes.append(
            f"only {len(means)} of the design's {claim.others} other arms have finished runs: "
            + ", ".join(names)
            + "; the verdict is against those alone"
        )
    label = _label(claim, values)
    row.comparison = f"{claim.comparison} {label}"
    runner = _equal_all(cols, values)
    return compare(shaped, claim.x, lambda d: claim.among(d) & runner(d), metric, row, (claim.labels[0], label))


def _label(claim: Claim, values: tuple) -> str:
    """The runner-up's name: ``claim.runner_label`` with each ``{KEY}`` replaced by its value."""
    text = claim.runner_label
    for key, value in zip(claim.by, values, strict=True):
        text = text.replace(f"{{{key}}}", str(value))
    return text


def _equal_all(cols: list[str], values: tuple) -> Filter:
    def select(df: pd.DataFrame) -> pd.Series:
        out = pd.Series(True, index=df.index)
        for col, value in zip(cols, values, strict=True):
            out &= df[col].astype(str) == str(value)
        return out

    return select


def queries(df: pd.DataFrame, claim: Claim, metric: str, row: Row) -> Row:
    """The difference in differences of ``claim`` (x's change from the most to the fewest queries
    minus y's) among its runs of ``df``, at every query count."""
    df = df[claim.among(df)] if len(df) else df
    (lx, ly), arms = claim.labels, (claim.x, claim.y)
    for select, label in zip(arms, claim.labels, strict=True):
        row.notes += failures(df, select, label)
    done = finished(df)
    if done.empty or QUERIES not in done:
        return row
    q = pd.to_numeric(done[QUERIES])
    strata: list[list[np.ndarray]] = [[], [], [], []]  # x few, x most, y few, y most
    gains: list[list[np.ndarray] | None] = [[], []]  # per dataset, x − y of each seed: few, most
    cells_at: list[list[pd.DataFrame]] = [[], []]  # the compared runs at the fewest and at the most queries
    for name, g in done.groupby(dataset_column(done)):
        qs = q[g.index]
        few, most = qs.min(), qs.max()
        cells = [g[s(g) & (qs == n)][metric].dropna().to_numpy(np.float64) for s in arms for n in (few, most)]
        if few == most or any(len(c) == 0 for c in cells):
            row.notes.append(f"{name} left out: needs {lx} and {ly} runs at two query counts")
            continue
        for s, c in zip(strata, cells, strict=True):
            s.append(c)
        for i, n in enumerate((few, most)):  # the seed-matched gains at each count, for the permutation test
            cells_at[i].append(g[qs == n])
            pairs = seed_matched(g[qs == n], claim.x, claim.y, metric, [name])
            if pairs is None and gains[i] is not None:
                row.notes.append(
                    f"no permutation test: {name} at {n} queries has no seed-matched {lx.upper()} and "
                    f"{ly.upper()} runs (no seed in common, or two runs of one seed in an arm)"
                )
            gains[i] = None if pairs is None or gains[i] is None else [*gains[i], pairs[name][1]]
        row.datasets.append(f"{name} ({few} vs {most} queries)")
        row.notes += digest_spread(g[(claim.x(g) | claim.y(g)) & qs.isin((few, most))])
    if not strata[0]:
        return row
    _diff_in_diff(row, strata)
    _gains_test(row, claim, gains, cells_at, sum(len(a) for s in strata for a in s))
    return row


def _diff_in_diff(row: Row, strata: list[list[np.ndarray]]) -> None:
    """The effect, means and sizes of the difference in differences over the strata (x few, x most,
    y few, y most; one array per dataset each)."""
    m = len(strata[0])

    def diff_in_diff(*xs: np.ndarray, axis: int = -1) -> np.ndarray:
        mean = [np.mean(x, axis=axis) for x in xs]
        return np.mean([(mean[i] - mean[m + i]) - (mean[2 * m + i] - mean[3 * m + i]) for i in range(m)], axis=0)

    flat = [a for s in strata for a in s]
    row.min_n = min(len(a) for a in flat)
    row.effect = stats.estimate(flat, diff_in_diff)
    change = [
        float(np.mean([few.mean() - most.mean() for few, most in zip(strata[i], strata[i + 1], strict=True)]))
        for i in (0, 2)
    ]
    row.means = (change[0], change[1])  # shown as "means x / y": x's change, y's change
    row.n_x, row.n_y = sum(map(len, strata[0] + strata[1])), sum(map(len, strata[2] + strata[3]))


def _gains_test(
    row: Row, claim: Claim, gains: list[list[np.ndarray] | None], cells_at: list[list[pd.DataFrame]], n_runs: int
) -> None:
    """The permutation test and planning numbers on the seed-matched gains (x − y per seed) at the
    fewest and the most queries, per dataset (``None``: a count without pairs); ``n_runs`` is the
    number of runs behind the effect."""
    x, y = claim.labels[0].upper(), claim.labels[1].upper()
    tested = gains[0] is not None and gains[1] is not None
    matched = tested and sum(map(len, gains[0] + gains[1])) * 2 == n_runs
    if tested and not matched:
        # the test's statistic (the gains' difference) is the effect only when every run has its partner;
        # where they point different ways the test cannot back the effect's verdict
        paired = float(stats.mean_difference(*gains[0], *gains[1]))
        if np.sign(paired) != np.sign(row.effect.value):
            row.notes.append(
                f"no permutation test: the seed-matched gains' difference ({paired:+.1f}) and the effect of all "
                f"runs ({row.effect.value:+.1f}) point different ways"
            )
            gains[0] = None
    if gains[0] is None or gains[1] is None:
        return
    row.perm_p = stats.permutation_p([*gains[0], *gains[1]])
    row.notes.append(
        f"permutation p from the seed-matched gains ({x} − {y} of one seed at one query count; "
        f"{sum(map(len, gains[0]))} at the fewest vs {sum(map(len, gains[1]))} at the most queries), "
        "exchanged between the query counts within each dataset"
        + ("" if matched else "; runs without a seed-matched partner are in the effect, not in the test")
    )
    # planning numbers for the same test: seeds per query count (each an x and a y run), their time
    # the sum of the two arms' median run times at that count
    row.plan = stats.power_plan([*gains[0], *gains[1]], power=POWER, alpha=ALPHA, min_runs=MIN_SEEDS)
    row.sizes = ([len(a) for a in gains[0]], [len(a) for a in gains[1]])
    runs_at = [pd.concat(c) for c in cells_at]
    row.run_s = tuple(sum(median_time(r[s(r)]) for s in (claim.x, claim.y)) for r in runs_at)
    row.plan_unit = "seeds"
    row.notes.append(
        f"its planning numbers (Runs for a verdict) count seeds per query count, each a {x} and a {y} run, "
        "and their time is both runs'"
    )
