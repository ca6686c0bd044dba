"""One comparison of two arms: a report row, its effect, tests and verdict (the ``difference`` test).

Each comparison is dataset by dataset: datasets where either arm has no finished run are left out
and named, so two arms are never averaged over different datasets.

* a **mean difference**: over datasets, ``mean(x) - mean(y)`` (each dataset weighs the same);
  verdict *supported* if its CI lies above 0, *not supported* if below (each only with the
  permutation test passing), else *inconclusive*, and *too few seeds* while an arm has fewer than
  :data:`MIN_SEEDS` finished runs on a dataset;
* the **probability of improvement** P(x > y) with its CI (0.5 = no difference), shown beside it;
* a **stratified permutation test** of the mean difference (:func:`spot.results.stats.permutation_p`):
  *supported* and *not supported* also need its two-sided p below :data:`ALPHA`. The percentile
  bootstrap over three runs an arm calls a difference between two arms of one distribution in
  about 19 % of trials, not 5 % (docs/tables.md); the permutation test holds its level at any n;
* a **seed-matched difference**, a second reading beside the verdict (:func:`seed_matched`): runs of
  one seed start from the same PRNG keys, and arms that train the same reward model share that
  seed's model, so the per-seed differences x − y remove what the seed moves in both arms. The
  verdict column stays the unpaired one: the pairing was chosen after the runs were seen.

CIs are 95 % stratified-bootstrap percentile intervals (:mod:`spot.results.stats`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spot.results import stats
from spot.results.load import CURVE_COLUMN, parse_curve
from spot.results.select import RUN_KEY, Filter, by_dataset, dataset_column, finished

MIN_SEEDS = 3  # a verdict needs at least this many finished runs per arm and dataset (effect and CI shown below it)
HIGH_MODE = 50.0  # on the local Hopper data the runs are bimodal: ~20 or 55-91 normalised
# a verdict also needs the stratified permutation test's two-sided p below this; the seed-matched
# reading's sign-flip test uses the same level
ALPHA = 0.05
POWER = 0.8  # the planning section's power (spot.results.report.format_plan)
RUN_TIME = "metrics.time/total_s"  # a run's wall time (one core at budget lab): the planning section's cost


@dataclass(frozen=True)
class Mode:
    """How often one arm's periodic evaluations (step > 0) scored at least a threshold."""

    evals_high: int
    evals: int
    runs_high: int  # runs with at least one such evaluation
    runs: int

    def text(self) -> str:
        return f"{self.evals_high} of {self.evals} ({self.runs_high} of {self.runs} runs)"


def high_mode(df: pd.DataFrame, threshold: float) -> Mode | None:
    """:class:`Mode` of ``df``'s runs from their exported curves; ``None`` if a run has no curve."""
    if CURVE_COLUMN not in df or df.empty:
        return None
    evals_high = evals = runs_high = 0
    for run_id, text in zip(df["run_id"], df[CURVE_COLUMN], strict=True):
        steps, values = parse_curve(text, f"run {run_id}")
        values = values[steps > 0]
        if not len(values):
            return None
        hits = int((values >= threshold).sum())
        evals_high, evals, runs_high = evals_high + hits, evals + len(values), runs_high + (hits > 0)
    return Mode(evals_high, evals, runs_high, len(df))


@dataclass
class Row:
    """One line of the report."""

    claim: str
    text: str
    comparison: str
    experiment: str  # the experiment set as shown (its label, or its experiments joined by +)
    stat: str  # last | best | ood | a metric name
    effect: stats.Estimate | None = None
    poi: stats.Estimate | None = None
    n_x: int = 0
    n_y: int = 0
    means: tuple[float, float] | None = None  # each arm's mean over datasets of its per-dataset means
    min_n: int = 0  # the fewest finished runs of an arm on one dataset
    datasets: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    high_mode: float = HIGH_MODE  # the score that counts an evaluation as in the high mode (format_high)
    high: tuple[Mode, Mode] | None = None  # per arm, from exported curves (last-score rows only)
    # the effect's stratified permutation p-value (nan: no test, e.g. claim 4 without seed-matched gains)
    perm_p: float = float("nan")
    # seed-matched reading (seed_matched): per dataset, the seeds both arms ran and x − y at each
    paired: stats.Estimate | None = None
    paired_p: float = float("nan")  # its two-sided sign-flip p-value (stats.sign_flip_p)
    pairs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # dataset -> (seeds, diffs)
    plan: stats.Plan | None = None  # what these runs could detect, and the runs the observed effect needs
    sizes: tuple[list[int], list[int]] = ([], [])  # finished runs per dataset of each arm (as ``datasets``)
    run_s: tuple[float, float] = (float("nan"), float("nan"))  # each arm's median run time (RUN_TIME)
    plan_unit: str = "runs"  # what ``plan`` and ``sizes`` count (claim 4: "seeds", each a SPOT and a PT run)
    listed: tuple[str, str] | None = None  # (label, experiments) of a labelled set, listed under the tables
    digits: int = 1  # decimals of the effect and means
    by_design: bool = False  # the claim pairs seeds by design (``paired: true``): the paired verdict is its own

    @property
    def paired_verdict(self) -> str:
        """The seed-matched reading: from the exact sign-flip test, not the bootstrap CI, whose
        percentile interval over three pairs on one dataset is their range (the test cannot pass
        below six pairs)."""
        if self.paired is None:
            return "no pairs"
        if min(len(d) for _, d in self.pairs.values()) < MIN_SEEDS:
            return stats.TOO_FEW
        if self.paired_p < ALPHA:
            return stats.SUPPORTED if self.paired.value > 0 else stats.NOT_SUPPORTED
        return stats.INCONCLUSIVE

    @property
    def verdict(self) -> str:
        if self.effect is None:
            return "no runs"
        if self.min_n < MIN_SEEDS:
            return stats.TOO_FEW
        v = stats.verdict(self.effect)
        test_fails = np.isfinite(self.perm_p) and self.perm_p >= ALPHA
        if v != stats.INCONCLUSIVE and test_fails:
            # the CI excludes 0 but relabelling the runs gives as large a difference too often
            return f"{stats.INCONCLUSIVE} (the CI alone: {v}; permutation p = {self.perm_p:.2g})"
        # the CI bound near 0 changes side with the bootstrap seed (no seed passes while the test fails)
        if self.effect.other_verdicts and not test_fails:
            return f"{v} (borderline: {' / '.join(self.effect.other_verdicts)} under another bootstrap seed)"
        if v != stats.INCONCLUSIVE and not np.isfinite(self.perm_p):
            # claim 4 without seed-matched gains has no permutation test, and the CI alone calls too much
            return f"{v} (the CI alone: no permutation test for this effect)"
        return v


# --------------------------------------------------------------------------- notes on the runs
def failures(df: pd.DataFrame, select: Filter, label: str) -> list[str]:
    """A note counting the arm's runs that are not FINISHED, by status."""
    bad = df[select(df) & (df["status"] != "FINISHED")]
    if bad.empty:
        return []
    counts = bad.groupby("status").size().to_dict()
    return [f"{label}: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + " (not counted)"]


def mixed_data(
    done: pd.DataFrame, arms: tuple[Filter, Filter], shared: Sequence[str], labels: tuple[str, str]
) -> list[str]:
    """A note per compared dataset whose runs were trained on more than one data digest (a dataset
    rebuilt with other numerics, another build seed or size): the arms may not share their data."""
    if "data_digest" not in done:
        return []
    key, out = dataset_column(done), []
    for name in shared:
        counts = []
        for select, label in zip(arms, labels, strict=True):
            arm = done[select(done) & (done[key].astype(str) == name)]
            counts.append((label, arm["data_digest"].dropna().astype(str).value_counts().sort_index()))
        digests = set().union(*(set(c.index) for _, c in counts))
        if len(digests) > 1:
            who = "; ".join(f"{label}: " + ", ".join(f"{n} on {d[:12]}" for d, n in c.items()) for label, c in counts)
            out.append(f"{name}: the runs span {len(digests)} data digests ({who}); the arms may not share their data")
    return out


def mixed_config(
    done: pd.DataFrame, arms: tuple[Filter, Filter], shared: Sequence[str], labels: tuple[str, str]
) -> list[str]:
    """A note per arm and compared dataset whose runs logged one param with different values (not
    ``seed``, not ``tracking.*``; keys that only some runs logged are left aside, as keys added to the
    package later): the arm mixes configs, e.g. runs launched before and after a variant changed."""
    keys = [c for c in done if c.startswith("params.") and c != "params.seed" and not c.startswith("params.tracking.")]
    key, out = dataset_column(done), []
    for name in shared:
        for select, label in zip(arms, labels, strict=True):
            arm = done[select(done) & (done[key].astype(str) == name)]
            differ = [c for c in keys if arm[c].notna().all() and arm[c].astype(str).nunique() > 1]
            if not differ:
                continue
            what = "; ".join(
                f"{c[len('params.') :]}: "
                + ", ".join(f"{n} at {v}" for v, n in arm[c].astype(str).value_counts().sort_index().items())
                for c in differ[:3]
            )
            more = f", and {len(differ) - 3} more keys" if len(differ) > 3 else ""
            out.append(f"{name}: the {label} runs differ in {what}{more}; the arm mixes configs")
    return out


def mean_last(runs: pd.DataFrame, k: int) -> pd.Series:
    """Per run, the mean of its last ``k`` periodic evaluations (step > 0) from its exported curve
    (:data:`~spot.results.load.CURVE_COLUMN`); nan for a run with fewer, or without the column."""
    if CURVE_COLUMN not in runs:
        return pd.Series(np.nan, index=runs.index, dtype=np.float64)
    out = []
    for run_id, text in zip(runs["run_id"], runs[CURVE_COLUMN], strict=True):
        steps, values = parse_curve(text, f"run {run_id}")
        values = values[steps > 0][np.argsort(steps[steps > 0], kind="stable")]
        out.append(float(values[-k:].mean()) if len(values) >= k else np.nan)
    return pd.Series(out, index=runs.index, dtype=np.float64)


def digest_spread(runs: pd.DataFrame) -> list[str]:
    """The same note for a set of runs without arms (claim 4's cells, the dose section): per dataset
    with more than one data digest, how many runs are on each."""
    if "data_digest" not in runs or runs.empty:
        return []
    out = []
    for name, g in runs.groupby(dataset_column(runs), sort=True):
        counts = g["data_digest"].dropna().astype(str).value_counts().sort_index()
        if len(counts) > 1:
            who = ", ".join(f"{n} on {d[:12]}" for d, n in counts.items())
            out.append(f"{name}: the runs span {len(counts)} data digests ({who}); they may not share their data")
    return out


def left_out(runs: pd.DataFrame) -> list[dict[str, str]]:
    """The runs of ``runs`` that :func:`~spot.results.select.finished` drops, each with why: not
    FINISHED (its status, how long it ran, its failure reason where logged, and whether a finished
    run of its config and seed counts instead), or a finished run replaced by a later re-run."""
    if runs.empty:
        return []
    kept = finished(runs)
    cols = [c for c in RUN_KEY if c in runs]
    counts = {
        tuple(map(str, r)): run_id for r, run_id in zip(kept[cols].itertuples(index=False), kept["run_id"], strict=True)
    }
    order = runs.sort_values(["experiment", "start_time"] if "start_time" in runs else ["experiment"], kind="stable")
    out = []
    for idx, r in order.iterrows():
        if idx in kept.index:
            continue
        instead = counts.get(tuple(str(r[c]) for c in cols))
        if r["status"] == "FINISHED":
            why = f"replaced by the later re-run `{instead}` of the same config and seed"
        else:
            ran = pd.Timestamp(r.get("end_time", pd.NaT)) - pd.Timestamp(r.get("start_time", pd.NaT))
            why = str(r["status"]) + (f" after {ran.total_seconds():,.0f} s" if pd.notna(ran) else "")
            reason = r.get("tags.failure_reason")
            why += f" ({reason})" if isinstance(reason, str) and reason else ""
            why += "; not finished, never counted"
            why += (
                f"; `{instead}` of the same config and seed counts"
                if instead
                else "; no finished run of its config and seed"
            )
        seed = "" if pd.isna(r["seed"]) else str(r["seed"])
        out.append(
            {
                "run": str(r["run_id"]),
                "experiment": str(r["experiment"]),
                "method": str(r["method"]),
                "dataset": str(r[dataset_column(runs)]),
                "seed": seed,
                "why": why,
            }
        )
    return out


def median_time(runs: pd.DataFrame) -> float:
    """The median :data:`RUN_TIME` of ``runs`` (nan without the metric)."""
    if RUN_TIME not in runs:
        return float("nan")
    t = pd.to_numeric(runs[RUN_TIME], errors="coerce").dropna()
    return float(t.median()) if len(t) else float("nan")


# --------------------------------------------------------------------------- the difference test
def seed_matched(
    done: pd.DataFrame, x: Filter, y: Filter, metric: str, shared: Sequence[str]
) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """Per dataset of ``shared``: the seeds (ascending) at which both arms have a finished run with a
    finite ``metric``, and x − y at each. ``None`` when an arm holds two runs of one seed on a dataset
    (several configs in one arm: no single pair per seed) or a dataset has no seed in common."""
    key, out = dataset_column(done), {}
    for name in shared:
        per_arm = []
        for select in (x, y):
            arm = done[select(done) & (done[key].astype(str) == name)]
            values = pd.Series(
                pd.to_numeric(arm[metric], errors="coerce").to_numpy(np.float64),
                index=pd.to_numeric(arm["seed"], errors="coerce").to_numpy(),
            )
            values = values[np.isfinite(values.to_numpy()) & np.isfinite(values.index.to_numpy(np.float64))]
            if values.index.duplicated().any():
                return None
            per_arm.append(values)
        common = per_arm[0].index.intersection(per_arm[1].index).sort_values()
        if len(common) == 0:
            return None
        diffs = per_arm[0].loc[common].to_numpy() - per_arm[1].loc[common].to_numpy()
        out[name] = (common.to_numpy().astype(np.int64), diffs)
    return out


def compare(df: pd.DataFrame, x: Filter, y: Filter, metric: str, row: Row, labels: tuple[str, str]) -> Row:
    """Fill ``row`` with the mean difference x − y and P(x > y) over the datasets both arms have."""
    done = finished(df)
    xs, ys = by_dataset(done[x(done)], metric), by_dataset(done[y(done)], metric)
    shared = sorted(set(xs) & set(ys))
    row.notes += failures(df, x, labels[0]) + failures(df, y, labels[1])
    for name in sorted(set(xs) ^ set(ys)):
        row.notes.append(f"{name} left out: only {labels[0] if name in xs else labels[1]} has finished runs")
    if not shared:
        return row
    row.notes += mixed_data(done, (x, y), shared, labels) + mixed_config(done, (x, y), shared, labels)
    sx, sy = [xs[d] for d in shared], [ys[d] for d in shared]
    row.effect = stats.estimate([*sx, *sy], stats.mean_difference)
    row.poi = stats.estimate([*sx, *sy], stats.probability_of_improvement, checks=0)  # no verdict is read from it
    row.perm_p = stats.permutation_p([*sx, *sy])
    row.n_x, row.n_y, row.datasets = sum(map(len, sx)), sum(map(len, sy)), shared
    row.means = (float(np.mean([a.mean() for a in sx])), float(np.mean([a.mean() for a in sy])))
    row.min_n = min(len(a) for a in [*sx, *sy])
    row.plan = stats.power_plan([*sx, *sy], power=POWER, alpha=ALPHA, min_runs=MIN_SEEDS)
    row.sizes = ([len(a) for a in sx], [len(a) for a in sy])
    key = dataset_column(done)
    row.run_s = tuple(median_time(done[select(done) & done[key].astype(str).isin(shared)]) for select in (x, y))
    pairs = seed_matched(done, x, y, metric, shared) if "seed" in done else None
    if pairs:
        row.pairs = pairs
        row.paired = stats.estimate([d for _, d in pairs.values()], stats.mean_of_means, checks=0)
        row.paired_p = stats.sign_flip_p([d for _, d in pairs.values()])
    if row.stat == "last":  # the arms are the same for every statistic: counted once, shown once
        arms = [done[select(done) & done[key].astype(str).isin(shared)] for select in (x, y)]
        modes = [high_mode(arm, row.high_mode) for arm in arms]
        row.high = (modes[0], modes[1]) if modes[0] and modes[1] else None
    return row
