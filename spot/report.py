"""The paper's claims, measured: one effect with its 95 % CI, n and a verdict per claim (`spot report`).

Input is a results frame (:mod:`spot.results`: a committed CSV, or runs read from MLflow). Each
claim compares two arms of runs from one experiment (a sweep's MLflow experiment), dataset by
dataset; datasets where either arm has no finished run are left out of that claim and named, so
two arms are never averaged over different datasets. Within a dataset and config, a re-run of a
seed replaces the earlier run; FAILED, KILLED and unfinished runs never count and are reported.

Effects (``x`` is the arm the paper says is better):

* a **mean difference**: over datasets, ``mean(x) - mean(y)`` (each dataset weighs the same);
  verdict *supported* if its CI lies above 0, *not supported* if below (each only with the
  permutation test below passing), else *inconclusive*, and
  *too few seeds* while an arm has fewer than :data:`MIN_SEEDS` finished runs on a dataset;
* the **probability of improvement** P(x > y) with its CI (0.5 = no difference), shown beside it;
* a **stratified permutation test** of the mean difference (:func:`spot.stats.permutation_p`):
  *supported* and *not supported* also need its two-sided p below 0.05. The percentile bootstrap
  over three runs an arm calls a difference between two arms of one distribution in about 19 % of
  trials, not 5 % (docs/tables.md); the permutation test holds its level at any n, and over one
  dataset at 3 vs 3 runs its p is never below 0.1. Claim 4's difference in differences has no
  permutation test and keeps the CI's verdict;
* a **seed-matched difference**, a second reading beside the verdict (:func:`seed_matched`): runs
  of one seed start from the same PRNG keys (the queries are the same at every seed), and arms that
  train the same reward model (PT, SPOT and its variants) share that seed's model, so the per-seed
  differences x − y remove what the seed moves in both arms. Their mean per dataset, averaged over
  datasets, with a stratified bootstrap over seeds, and the exact sign-flip test's p-value, which
  gives the reading (p < 0.05). The verdict column stays the unpaired one: the pairing was chosen
  after the runs were seen (docs/tables.md).

CIs are 95 % stratified-bootstrap percentile intervals (:mod:`spot.stats`). Both the last
evaluation (``eval/score_final``) and the best (``eval/score_best``) are reported, in separate
tables, because the paper does not say which it reports; verdicts are read from the last.

The claims (paper section; which runs):

1. SPOT ≥ PT and MR on average (§5.1, Table 1): ``method`` spot vs pt, spot vs mr.
2. Top-10 % attention subgoals beat bottom-10 % (Table 2): ``subgoal.group`` top vs bottom.
3. Cosine shaping with λ = 1 is best among Table 3's variants: cosine at λ = 1 vs the
   best-scoring other (kind, λ) cell, named in the row (the runner-up is picked on the point
   estimates, so its CI is slightly optimistic for the runner-up).
4. SPOT keeps its score with fewer queries (Table 4): SPOT's change from the most to the fewest
   queries minus PT's (> 0: SPOT loses less). Its permutation test exchanges the seed-matched gains
   (SPOT − PT of one seed, which share that seed's reward model) between the two query counts within
   each dataset; without such pairs the row has no test and says its verdict is the CI's alone.
5. MSE + cosine beats MSE for the CVAE (Table 7): ``cvae.loss`` mse_cos vs mse.
6. SPOT lowers out-of-distribution extrapolation error (Fig. 2): PT's
   ``diag/extrapolation_error_ood`` minus SPOT's (> 0: SPOT lower), from the Table 1 runs; row
   ``6P`` the same from the ``variant=paper`` runs of set P (PT and SPOT proper of row 1P).

Controls no table has (does the gain come from attention subgoals, or from a survival bonus?):
SPOT vs SPOT with **random dataset states** as subgoals (``subgoal.source=random``), and SPOT vs a
**constant bonus** of the same mean as SPOT's cosine term (``shaping.kind=constant``).

Claims 1 and C compare runs of the package's default fidelity variant (``variant=spot``; runs
logged before the key count as ``spot``). Rows ``1P`` and ``CP`` are the same comparisons under
``variant=paper`` (docs/fidelity.md), from the runs of lab_fidelity, lab_variant_rows, lab_paper and
lab_paper_random on Hopper and lab_walker and lab_walker_controls on Walker2d, with SPOT vs Oracle beside them
as a reference (not a claim of the paper). Rows
``2P``, ``3P`` and ``5P`` are claims 2, 3 and 5 on the same data and variant: lab_fidelity's SPOT
runs (top group, MSE + cosine CVAE, cosine shaping at λ = 1) against lab_paper_ablations'
bottom-group and MSE-only arms and lab_paper_shaping's other (kind, λ) arms; row ``4P`` is claim 4
with lab_paper_queries' 50-query PT and SPOT runs. Row ``OP`` (a reference, not a claim) is Oracle
with ``relabel.normalize=minmax`` (the true reward scaled, plus a per-step offset) against Oracle
(lab_paper_oracle_minmax, lab_variant_rows): the survival-bonus reading tested on the true reward.
Row ``OD`` (also a reference) is Oracle at ``iql.discount=0.995`` against Oracle at IQL's 0.99
(lab_oracle_discount, lab_variant_rows): does a longer horizon keep Oracle from falling? Row ``OC``
(a reference) is Oracle with CORL's IQL settings for hopper-medium-replay (``iql.actor_dist=deterministic``,
``iql.tau=0.001``; lab_oracle_corl) against Oracle; its runs are on the size-``paper-fast`` file, so
the row has runs only with ``--use O=lab_hopper_pf+lab_oracle_corl``.
:func:`dose_response` sets the term each arm adds to the reward per step against its score (a
description of the runs, not a claim).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spot import SpotError, results, stats

MIN_SEEDS = 3  # a verdict needs at least this many finished runs per arm and dataset (effect and CI shown below it)
METRICS = {"last": "metrics.eval/score_final", "best": "metrics.eval/score_best"}
OOD_METRIC = "metrics.diag/extrapolation_error_ood"
LENGTH = "metrics.eval/length"  # the last evaluation's mean episode length (logged from 2026-11-26 on)
# On the local Hopper data the runs are bimodal (docs/reproduction.md): ~20 or 55-91 normalised.
HIGH_MODE = 50.0
# a verdict also needs the stratified permutation test's two-sided p below this; the seed-matched
# reading's sign-flip test uses the same level
ALPHA = 0.05
POWER = 0.8  # the planning section's power (format_plan)
RUN_TIME = "metrics.time/total_s"  # a run's wall time (one core at budget lab): the planning section's cost
# Where each claim's runs are: the first entry in the list that has runs is used; "a+b" is the runs
# of experiments a and b together (the controls compare SPOT's Table 1 runs with the control runs).
# Claims 1 and 6 read lab_table1 (local hopper-medium-replay) and lab_table1_fr (hopper-full-replay).
# F is not a claim of the paper: SPOT's fidelity variants against each other (docs/fidelity.md); the
# `spot` variant's SPOT runs are lab_table1's (the same config). P holds the runs of rows 1P, CP, 2P,
# 3P, 4P and 5P (claims 1 to 5 and the controls under variant paper). O holds row OP: Oracle on its
# default reward against Oracle with relabel.normalize=minmax (the true reward plus a per-step offset),
# and row OD: Oracle at discount 0.995 against Oracle at its default 0.99 (a longer horizon); row OC
# (CORL's IQL settings) has its runs on another file, lab_hopper_pf's (``--use O=...``).
EXPERIMENTS = {
    "1": ("lab_table1+lab_table1_fr", "table1"),
    "2": ("lab_table2", "table2_topk"),
    "3": ("lab_table3", "table3_shaping"),
    "4": ("lab_table4", "table4_queries"),
    "5": ("lab_table7", "table7_cvae_loss"),
    "6": ("lab_table1+lab_table1_fr", "table1"),
    "C": ("lab_table1+lab_controls", "lab_controls"),
    "F": ("lab_fidelity+lab_table1", "fidelity"),
    "P": (
        "lab_fidelity+lab_variant_rows+lab_paper+lab_paper_random+lab_paper_ablations+lab_paper_shaping"
        "+lab_paper_queries+lab_walker+lab_walker_controls",
    ),
    "O": ("lab_variant_rows+lab_paper_oracle_minmax+lab_oracle_discount",),
}

Filter = Callable[[pd.DataFrame], pd.Series]


def _param(key: str, value: str) -> Filter:
    def select(df: pd.DataFrame) -> pd.Series:
        col = f"params.{key}"
        return df[col].astype(str) == value if col in df else pd.Series(False, index=df.index)

    return select


def _method(name: str) -> Filter:
    return lambda df: df["method"] == name


def _both(a: Filter, b: Filter) -> Filter:
    return lambda df: a(df) & b(df)


def _not(a: Filter) -> Filter:
    return lambda df: ~a(df)


def _numbers(key: str) -> Callable[[pd.DataFrame], pd.Series]:
    col = f"params.{key}"
    return lambda df: pd.to_numeric(df[col], errors="coerce") if col in df else pd.Series(np.nan, index=df.index)


def _equal_to(key: str, value: float) -> Filter:
    """Runs that logged the number ``key`` as ``value``."""
    return lambda df: _numbers(key)(df) == value


def _other_than(key: str, default: float) -> Filter:
    """Runs that logged the number ``key`` as something other than ``default`` (runs without it: the default)."""
    numbers = _numbers(key)

    def select(df: pd.DataFrame) -> pd.Series:
        values = numbers(df)
        return values.notna() & (values != default)

    return select


def _either(a: Filter, b: Filter) -> Filter:
    return lambda df: a(df) | b(df)


_RANDOM_SUBGOALS = _param("subgoal.source", "random")
# Oracle with min-max-normalised rewards: on locomotion, the true reward scaled plus a per-step offset
# (docs/reproduction.md). Oracle at another discount than IQL's 0.99 (row OD). Oracle with CORL's IQL
# settings for hopper-medium-replay, a deterministic actor and target rate 0.001 (row OC; a run with
# either setting stays out of every other Oracle arm). Oracle proper is every other Oracle run (runs
# without a key: its default)
_MINMAX = _param("relabel.normalize", "minmax")
_OTHER_HORIZON = _other_than("iql.discount", 0.99)
_CORL_ACTOR = _param("iql.actor_dist", "deterministic")
_OTHER_IQL = _either(_CORL_ACTOR, _other_than("iql.tau", 0.005))
_ORACLE_MINMAX = _both(_both(_method("oracle"), _MINMAX), _not(_OTHER_IQL))
_ORACLE_LONG = _both(_both(_method("oracle"), _equal_to("iql.discount", 0.995)), _not(_either(_MINMAX, _OTHER_IQL)))
_ORACLE_CORL = _both(
    _both(_method("oracle"), _both(_CORL_ACTOR, _equal_to("iql.tau", 0.001))), _not(_either(_MINMAX, _OTHER_HORIZON))
)
_ORACLE = _both(_method("oracle"), _not(_either(_either(_MINMAX, _OTHER_HORIZON), _OTHER_IQL)))
_CONSTANT_BONUS = _param("shaping.kind", "constant")
_BOTTOM_GROUP = _param("subgoal.group", "bottom")
_MSE_CVAE = _param("cvae.loss", "mse")
# another percentile group than the top one, or the CVAE on MSE alone (claims 2 and 5's other arms)
_NEXT_GROUPS = _either(_param("subgoal.group", "top_next"), _param("subgoal.group", "bottom_next"))
_ABLATED_GROUP = _either(_BOTTOM_GROUP, _NEXT_GROUPS)
_ABLATED = _either(_ABLATED_GROUP, _MSE_CVAE)
_CONTROL = _either(_RANDOM_SUBGOALS, _CONSTANT_BONUS)
SHAPING_KINDS = ("cosine", "neg_distance", "potential")  # Table 3's rows
TABLE3_OTHER_ARMS = len(SHAPING_KINDS) * 3 - 1  # Table 3's (kind, λ in 1, 0.5, 0.1) arms but cosine at 1


def _other_shaping(df: pd.DataFrame) -> pd.Series:
    """Table 3's other arms: a shaping kind other than cosine, or a weight other than 1 (runs
    without the keys count as cosine at 1)."""
    out = pd.Series(False, index=df.index)
    if "params.shaping.kind" in df:
        out |= df["params.shaping.kind"].astype(str).isin(SHAPING_KINDS[1:])
    if "params.shaping.weight" in df:
        out |= pd.to_numeric(df["params.shaping.weight"], errors="coerce").fillna(1.0) != 1.0
    return out


# SPOT proper: method spot with its top-group subgoals, its CVAE loss and cosine shaping at
# lambda 1, neither control (the control and ablation runs are also method spot)
_SPOT = _both(_method("spot"), _not(_either(_either(_CONTROL, _ABLATED), _other_shaping)))


def _in_variant(select: Filter, name: str) -> Filter:
    """``select``'s runs under fidelity variant ``name``; runs logged before the key are ``spot``."""

    def both(df: pd.DataFrame) -> pd.Series:
        variant = df["params.variant"].fillna("spot") if "params.variant" in df else pd.Series("spot", df.index)
        return select(df) & (variant == name)

    return both


def _variant(name: str) -> Filter:
    """SPOT's runs (no controls) under fidelity variant ``name``."""
    return _in_variant(_SPOT, name)


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
    if results.CURVE_COLUMN not in df or df.empty:
        return None
    evals_high = evals = runs_high = 0
    for run_id, text in zip(df["run_id"], df[results.CURVE_COLUMN], strict=True):
        steps, values = results.parse_curve(text, f"run {run_id}")
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
    experiment: str
    stat: str  # last | best | ood
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


# --------------------------------------------------------------------------- selecting runs
def finished(df: pd.DataFrame) -> pd.DataFrame:
    """FINISHED runs, one per (config, seed): a re-run replaces the earlier run."""
    out = df[df["status"] == "FINISHED"]
    if "start_time" in out:
        out = out.sort_values("start_time", kind="stable")
    return out.drop_duplicates(["config_hash", "seed"], keep="last")


def _experiment(df: pd.DataFrame, names: Sequence[str]) -> tuple[str, pd.DataFrame]:
    for name in names:
        sub = df[df["experiment"].isin(name.split("+"))]
        if len(sub):
            return name, sub
    return names[0], df.iloc[0:0]


def _dataset_column(df: pd.DataFrame) -> str:
    """The column that names a run's dataset: the paper's name where the results have it."""
    return "paper_dataset" if "paper_dataset" in df else "dataset"


def _by_dataset(df: pd.DataFrame, metric: str) -> dict[str, np.ndarray]:
    if metric not in df:
        return {}
    out = {}
    for name, g in df.groupby(_dataset_column(df), sort=True):
        v = pd.to_numeric(g[metric], errors="coerce").to_numpy(np.float64)
        v = v[np.isfinite(v)]
        if len(v):
            out[str(name)] = v
    return out


def _failures(df: pd.DataFrame, select: Filter, label: str) -> list[str]:
    bad = df[select(df) & (df["status"] != "FINISHED")]
    if bad.empty:
        return []
    counts = bad.groupby("status").size().to_dict()
    return [f"{label}: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + " (not counted)"]


def _mixed_data(
    done: pd.DataFrame, arms: tuple[Filter, Filter], shared: Sequence[str], labels: tuple[str, str]
) -> list[str]:
    """A note per compared dataset whose runs were trained on more than one data digest (a dataset
    rebuilt with other numerics, another build seed or size): the arms may not share their data."""
    if "data_digest" not in done:
        return []
    key, out = _dataset_column(done), []
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


def _digest_spread(runs: pd.DataFrame) -> list[str]:
    """The same note for a set of runs without arms (claim 4's cells, the dose section): per dataset
    with more than one data digest, how many runs are on each."""
    if "data_digest" not in runs or runs.empty:
        return []
    out = []
    for name, g in runs.groupby(_dataset_column(runs), sort=True):
        counts = g["data_digest"].dropna().astype(str).value_counts().sort_index()
        if len(counts) > 1:
            who = ", ".join(f"{n} on {d[:12]}" for d, n in counts.items())
            out.append(f"{name}: the runs span {len(counts)} data digests ({who}); they may not share their data")
    return out


def seed_matched(
    done: pd.DataFrame, x: Filter, y: Filter, metric: str, shared: Sequence[str]
) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """Per dataset of ``shared``: the seeds (ascending) at which both arms have a finished run with a
    finite ``metric``, and x − y at each. ``None`` when an arm holds two runs of one seed on a dataset
    (several configs in one arm: no single pair per seed) or a dataset has no seed in common."""
    key, out = _dataset_column(done), {}
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


def _median_time(runs: pd.DataFrame) -> float:
    """The median :data:`RUN_TIME` of ``runs`` (nan without the metric)."""
    if RUN_TIME not in runs:
        return float("nan")
    t = pd.to_numeric(runs[RUN_TIME], errors="coerce").dropna()
    return float(t.median()) if len(t) else float("nan")


def compare(df: pd.DataFrame, x: Filter, y: Filter, metric: str, row: Row, labels: tuple[str, str]) -> Row:
    """Fill ``row`` with the mean difference x − y and P(x > y) over the datasets both arms have."""
    done = finished(df)
    xs, ys = _by_dataset(done[x(done)], metric), _by_dataset(done[y(done)], metric)
    shared = sorted(set(xs) & set(ys))
    row.notes += _failures(df, x, labels[0]) + _failures(df, y, labels[1])
    for name in sorted(set(xs) ^ set(ys)):
        row.notes.append(f"{name} left out: only {labels[0] if name in xs else labels[1]} has finished runs")
    if not shared:
        return row
    row.notes += _mixed_data(done, (x, y), shared, labels)
    sx, sy = [xs[d] for d in shared], [ys[d] for d in shared]
    row.effect = stats.estimate([*sx, *sy], stats.mean_difference)
    row.poi = stats.estimate([*sx, *sy], stats.probability_of_improvement, checks=0)  # no verdict is read from it
    row.perm_p = stats.permutation_p([*sx, *sy])
    row.n_x, row.n_y, row.datasets = sum(map(len, sx)), sum(map(len, sy)), shared
    row.means = (float(np.mean([a.mean() for a in sx])), float(np.mean([a.mean() for a in sy])))
    row.min_n = min(len(a) for a in [*sx, *sy])
    row.plan = stats.power_plan([*sx, *sy], power=POWER, alpha=ALPHA, min_runs=MIN_SEEDS)
    row.sizes = ([len(a) for a in sx], [len(a) for a in sy])
    key = _dataset_column(done)
    row.run_s = tuple(_median_time(done[select(done) & done[key].astype(str).isin(shared)]) for select in (x, y))
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


# --------------------------------------------------------------------------- the claims
def _table3(base: Filter | None = None) -> Callable[[pd.DataFrame, str, Row], Row]:
    """Claim 3 among ``base``'s runs (all runs if ``None``)."""
    return lambda df, metric, row: _claim3(df, metric, row, base)


def _claim3(df: pd.DataFrame, metric: str, row: Row, base: Filter | None = None) -> Row:
    if "params.shaping.kind" not in df or "params.shaping.weight" not in df:
        return row
    shaped = df[df["params.shaping.kind"].isin(SHAPING_KINDS) & (base(df) if base else True)]
    best = _both(_param("shaping.kind", "cosine"), lambda d: pd.to_numeric(d["params.shaping.weight"]) == 1.0)
    done = finished(shaped)
    others = done[~best(done)] if len(done) else done
    if others.empty:
        return compare(shaped, best, _not(best), metric, row, ("cosine λ=1", "others"))
    means = others.groupby(["params.shaping.kind", "params.shaping.weight"])[metric].mean()
    kind, weight = means.idxmax()
    if len(means) < TABLE3_OTHER_ARMS:
        row.notes.append(
            f"only {len(means)} of Table 3's {TABLE3_OTHER_ARMS} other (kind, λ) arms have finished runs: "
            + ", ".join(f"{k} λ={w}" for k, w in means.index)
            + "; the verdict is against those alone"
        )
    row.comparison = f"cosine λ=1 vs runner-up {kind} λ={weight}"
    runner = _both(_param("shaping.kind", kind), _param("shaping.weight", str(weight)))
    return compare(shaped, best, runner, metric, row, ("cosine λ=1", f"{kind} λ={weight}"))


def _table4(base: Filter) -> Callable[[pd.DataFrame, str, Row], Row]:
    """Claim 4 among ``base``'s runs."""
    return lambda df, metric, row: _claim4(df[base(df)] if len(df) else df, metric, row)


def _claim4(df: pd.DataFrame, metric: str, row: Row) -> Row:
    for m in ("spot", "pt"):
        row.notes += _failures(df, lambda d, m=m: d["method"] == m, m)
    done = finished(df)
    if done.empty or "params.labels.num_queries" not in done:
        return row
    q = pd.to_numeric(done["params.labels.num_queries"])
    strata: list[list[np.ndarray]] = [[], [], [], []]  # spot few, spot most, pt few, pt most
    gains: list[list[np.ndarray] | None] = [[], []]  # per dataset, SPOT − PT of each seed: few, most
    cells_at: list[list[pd.DataFrame]] = [[], []]  # the compared runs at the fewest and at the most queries
    for name, g in done.groupby("paper_dataset"):
        qs = q[g.index]
        few, most = qs.min(), qs.max()
        cells = [
            g[(g["method"] == m) & (qs == n)][metric].dropna().to_numpy(np.float64)
            for m in ("spot", "pt")
            for n in (few, most)
        ]
        if few == most or any(len(c) == 0 for c in cells):
            row.notes.append(f"{name} left out: needs spot and pt runs at two query counts")
            continue
        for s, c in zip(strata, cells, strict=True):
            s.append(c)
        for i, n in enumerate((few, most)):  # the seed-matched gains at each count, for the permutation test
            cells_at[i].append(g[qs == n])
            pairs = seed_matched(g[qs == n], _method("spot"), _method("pt"), metric, [name])
            if pairs is None and gains[i] is not None:
                row.notes.append(
                    f"no permutation test: {name} at {n} queries has no seed-matched SPOT and PT runs "
                    "(no seed in common, or two runs of one seed in an arm)"
                )
            gains[i] = None if pairs is None or gains[i] is None else [*gains[i], pairs[name][1]]
        row.datasets.append(f"{name} ({few} vs {most} queries)")
        row.notes += _digest_spread(g[g["method"].isin(("spot", "pt")) & qs.isin((few, most))])
    if not strata[0]:
        return row
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
    row.means = (change[0], change[1])  # shown as "means x / y": SPOT's change, PT's change
    row.n_x, row.n_y = sum(map(len, strata[0] + strata[1])), sum(map(len, strata[2] + strata[3]))
    _gains_test(row, gains, cells_at, sum(map(len, flat)))
    return row


def _gains_test(
    row: Row, gains: list[list[np.ndarray] | None], cells_at: list[list[pd.DataFrame]], n_runs: int
) -> None:
    """Claim 4's permutation test and planning numbers on the seed-matched gains (SPOT − PT per seed)
    at the fewest and the most queries, per dataset (``None``: a count without pairs); ``n_runs`` is
    the number of runs behind the effect."""
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
    if gains[0] is not None and gains[1] is not None:
        row.perm_p = stats.permutation_p([*gains[0], *gains[1]])
        row.notes.append(
            f"permutation p from the seed-matched gains (SPOT − PT of one seed at one query count; "
            f"{sum(map(len, gains[0]))} at the fewest vs {sum(map(len, gains[1]))} at the most queries), "
            "exchanged between the query counts within each dataset"
            + ("" if matched else "; runs without a seed-matched partner are in the effect, not in the test")
        )
        # planning numbers for the same test: seeds per query count (each a SPOT and a PT run), their time
        # the sum of the two methods' median run times at that count
        row.plan = stats.power_plan([*gains[0], *gains[1]], power=POWER, alpha=ALPHA, min_runs=MIN_SEEDS)
        row.sizes = ([len(a) for a in gains[0]], [len(a) for a in gains[1]])
        runs_at = [pd.concat(c) for c in cells_at]
        row.run_s = tuple(sum(_median_time(r[r["method"] == m]) for m in ("spot", "pt")) for r in runs_at)
        row.plan_unit = "seeds"
        row.notes.append(
            "its planning numbers (Runs for a verdict) count seeds per query count, each a SPOT and a PT run, "
            "and their time is both runs'"
        )


Claim = tuple[str, str, str, str, Callable[[pd.DataFrame, str, Row], Row]]


def _versus(x: Filter, y: Filter, labels: tuple[str, str]) -> Callable[[pd.DataFrame, str, Row], Row]:
    return lambda df, m, r: compare(df, x, y, m, r, labels)


def _suffix(variant: str) -> str:
    return "" if variant == "spot" else f" (variant {variant})"


def _claim1(claim: str, key: str, variant: str, oracle: bool = False) -> list[Claim]:
    """Claim 1 among the runs of one fidelity variant; with ``oracle``, SPOT vs Oracle beside it as a
    reference (not a claim: the preference methods against IQL on the true reward)."""
    spot, where = _variant(variant), _suffix(variant)
    rows: list[Claim] = [
        (
            claim,
            key,
            f"SPOT ≥ {m.upper()} on average (Table 1){where}",
            f"spot vs {m}",
            _versus(spot, _in_variant(_method(m), variant), ("spot", m)),
        )
        for m in ("pt", "mr")
    ]
    if oracle:
        rows.append(
            (
                claim,
                key,
                f"reference: SPOT vs Oracle (IQL on the true reward){where}",
                "spot vs oracle",
                _versus(spot, _in_variant(_ORACLE, variant), ("spot", "oracle")),
            )
        )
    return rows


def _controls(claim: str, key: str, variant: str) -> list[Claim]:
    """The two controls among the runs of one fidelity variant, and the bonus alone as a reference
    (not a claim: the constant control is PT's reward plus the bonus)."""
    spot, where = _variant(variant), _suffix(variant)
    random_sg, constant = _in_variant(_RANDOM_SUBGOALS, variant), _in_variant(_CONSTANT_BONUS, variant)
    return [
        (
            claim,
            key,
            f"control: attention subgoals beat random-state subgoals{where}",
            "spot vs random subgoals",
            _versus(spot, random_sg, ("spot", "random subgoals")),
        ),
        (
            claim,
            key,
            f"control: SPOT beats a constant bonus of the same mean{where}",
            "spot vs constant bonus",
            _versus(spot, constant, ("spot", "constant bonus")),
        ),
        (
            claim,
            key,
            f"reference: PT's reward plus the constant bonus vs PT{where}",
            "constant bonus vs pt",
            _versus(constant, _in_variant(_method("pt"), variant), ("constant bonus", "pt")),
        ),
    ]


def _ablations(claim2: str, claim5: str, key: str, variant: str) -> list[Claim]:
    """Claims 2 and 5 among the runs of one fidelity variant: SPOT proper (top group, its CVAE loss)
    against the bottom-10 % group and against the CVAE on MSE alone, each changing only that key."""
    spot, where = _variant(variant), _suffix(variant)
    plain = _both(_method("spot"), _not(_either(_CONTROL, _other_shaping)))
    bottom = _in_variant(_both(plain, _both(_BOTTOM_GROUP, _not(_MSE_CVAE))), variant)
    mse = _in_variant(_both(plain, _both(_MSE_CVAE, _not(_ABLATED_GROUP))), variant)
    return [
        (
            claim2,
            key,
            f"top-10 % subgoals beat bottom-10 % (Table 2){where}",
            "group top vs bottom",
            _versus(spot, bottom, ("top", "bottom")),
        ),
        (
            claim5,
            key,
            f"MSE + cosine beats MSE for the CVAE (Table 7){where}",
            "mse_cos vs mse",
            _versus(spot, mse, ("mse_cos", "mse")),
        ),
    ]


# (claim id shown, key into EXPERIMENTS, text, comparison, how)
CLAIMS: tuple[Claim, ...] = (
    *_claim1("1", "1", "spot"),
    (
        "2",
        "2",
        "top-10 % subgoals beat bottom-10 % (Table 2)",
        "group top vs bottom",
        _versus(_param("subgoal.group", "top"), _param("subgoal.group", "bottom"), ("top", "bottom")),
    ),
    ("3", "3", "cosine shaping at λ = 1 is best (Table 3)", "cosine λ=1 vs runner-up", _table3()),
    (
        "4",
        "4",
        "SPOT keeps its score with fewer queries, PT does not (Table 4)",
        "(spot few − most) − (pt few − most)",
        _claim4,
    ),
    (
        "5",
        "5",
        "MSE + cosine beats MSE for the CVAE (Table 7)",
        "mse_cos vs mse",
        _versus(_param("cvae.loss", "mse_cos"), _param("cvae.loss", "mse"), ("mse_cos", "mse")),
    ),
    *_controls("C", "C", "spot"),
    (
        "F",
        "F",
        "fidelity: SPOT as the authors' code runs it vs as the paper's text says",
        "variant authors vs paper",
        _versus(_variant("authors"), _variant("paper"), ("authors", "paper")),
    ),
    (
        "F",
        "F",
        "fidelity: SPOT as the paper's text says vs this package's defaults",
        "variant paper vs spot",
        _versus(_variant("paper"), _variant("spot"), ("paper", "spot")),
    ),
    *_claim1("1P", "P", "paper", oracle=True),
    *_controls("CP", "P", "paper"),
    *_ablations("2P", "5P", "P", "paper"),
    (
        "4P",
        "P",
        "SPOT keeps its score with fewer queries, PT does not (Table 4) (variant paper)",
        "(spot few − most) − (pt few − most)",
        _table4(_either(_variant("paper"), _in_variant(_method("pt"), "paper"))),
    ),
    (
        "3P",
        "P",
        "cosine shaping at λ = 1 is best (Table 3) (variant paper)",
        "cosine λ=1 vs runner-up",
        _table3(_in_variant(_both(_method("spot"), _not(_either(_CONTROL, _ABLATED))), "paper")),
    ),
    (
        "OP",
        "O",
        "reference: Oracle's true reward plus a per-step offset (relabel.normalize=minmax) vs Oracle (variant paper)",
        "oracle minmax vs oracle",
        _versus(_in_variant(_ORACLE_MINMAX, "paper"), _in_variant(_ORACLE, "paper"), ("oracle minmax", "oracle")),
    ),
    (
        "OD",
        "O",
        "reference: Oracle at discount 0.995 (a longer horizon) vs Oracle at 0.99 (variant paper)",
        "oracle γ=0.995 vs oracle",
        _versus(_in_variant(_ORACLE_LONG, "paper"), _in_variant(_ORACLE, "paper"), ("oracle γ=0.995", "oracle")),
    ),
    (
        "OC",
        "O",
        "reference: Oracle with CORL's IQL for hopper-medium-replay (a deterministic actor, target rate 0.001) "
        "vs Oracle (variant paper)",
        "oracle corl vs oracle",
        _versus(_in_variant(_ORACLE_CORL, "paper"), _in_variant(_ORACLE, "paper"), ("oracle corl", "oracle")),
    ),
)


def build(
    df: pd.DataFrame, experiments: Mapping[str, Sequence[str]] | None = None, high: float = HIGH_MODE
) -> list[Row]:
    """Every claim's rows for the last and the best score, and claim 6 for the OOD error; ``high``
    is the score that counts an evaluation as in the high mode (runs with exported curves)."""
    exps = {**EXPERIMENTS, **(experiments or {})}
    runs = {key: _experiment(df, names) for key, names in exps.items()}  # each set's runs, selected once
    one_count = {key: most_queries(sub) for key, (_, sub) in runs.items()}

    def row_for(claim: str, key: str, text: str, comparison: str, stat: str) -> tuple[Row, pd.DataFrame]:
        """The row's experiment runs (claim 4 at every query count, the others at one) and the row,
        with the note on what was left out."""
        name, sub = runs[key]
        sub, note = (sub, None) if claim.startswith("4") else one_count[key]
        return Row(claim, text, comparison, name, stat, high_mode=high, notes=[note] if note else []), sub

    rows = []
    for stat, metric in METRICS.items():
        for claim, key, text, comparison, fn in CLAIMS:
            row, sub = row_for(claim, key, text, comparison, stat)
            rows.append(fn(sub, metric, row))
    for claim, key, variant, where in (("6", "6", "spot", ""), ("6P", "P", "paper", _suffix("paper"))):
        text = f"SPOT lowers OOD extrapolation error (Fig. 2){where}"
        row, sub = row_for(claim, key, text, "pt − spot, OOD error", "ood")
        pt = _in_variant(_method("pt"), variant)
        rows.append(compare(sub, pt, _variant(variant), OOD_METRIC, row, ("pt", "spot")))
    return rows


QUERIES = "params.labels.num_queries"


def most_queries(df: pd.DataFrame) -> tuple[pd.DataFrame, str | None]:
    """The runs at the largest query count of their dataset (runs without the key count as at it),
    and a note naming what was left out: every claim but 4 compares arms at one query count, so
    the 50-query runs of claim 4's arms (in the same experiment set) never enter claim 1's arms."""
    if df.empty or QUERIES not in df:
        return df, None
    q = pd.to_numeric(df[QUERIES], errors="coerce")
    keep = q.isna() | (q == q.groupby(df[_dataset_column(df)].astype(str)).transform("max"))
    if keep.all():
        return df, None
    counts = ", ".join(f"{int(n)} at {int(v)}" for v, n in q[~keep].value_counts().sort_index().items())
    return df[keep], f"runs at fewer queries than their dataset's most left out ({counts}; claim 4's arms)"


def aggregate(df: pd.DataFrame, metric: str = METRICS["last"], reference: str = "spot") -> pd.DataFrame:
    """Per method over the datasets every method has: IQM [CI] and P(reference > method) [CI]."""
    done = finished(df)
    per = {m: _by_dataset(g, metric) for m, g in done.groupby("method")}
    if not per:
        raise SpotError("no finished runs to aggregate")
    shared = sorted(set.intersection(*(set(v) for v in per.values())))
    out = []
    for m, by in sorted(per.items()):
        strata = [by[d] for d in shared]
        iqm = stats.estimate(strata, stats.iqm, checks=0) if shared else None
        poi = None
        if reference in per and m != reference and shared:
            strata_poi = [*(per[reference][d] for d in shared), *strata]
            poi = stats.estimate(strata_poi, stats.probability_of_improvement, checks=0)
        out.append(
            {
                "method": m,
                "datasets": len(shared),
                "runs": sum(map(len, strata)),
                "iqm": iqm.text() if iqm else "",
                f"P({reference} > method)": poi.text(2) if poi else "",
            }
        )
    return pd.DataFrame(out)


# --------------------------------------------------------------------------- dose and response
ADDED = ("metrics.shaping/r_final_mean", "metrics.shaping/r_model_mean")  # their difference: the term added


@dataclass
class Dose:
    """The term added to the learned reward per step against the final score, over the runs of
    SPOT and its variants and PT (whose added term is 0) under one fidelity variant, on one dataset."""

    experiment: str
    variant: str
    dataset: str
    arms: list[dict] = field(default_factory=list)  # label, runs, added, score (stats.cell), high
    rho: stats.Estimate | None = None
    notes: list[str] = field(default_factory=list)


def _arm_label(run: pd.Series) -> str:
    """A short name for the one setting that makes a SPOT-family run's arm (``PT`` for PT)."""
    if run["method"] == "pt":
        return "PT"

    def value(key: str, default: str) -> str:  # runs logged before a key have it missing (NaN)
        v = run.get(key)
        return default if v is None or pd.isna(v) else str(v)

    kind, weight = value("params.shaping.kind", "cosine"), float(value("params.shaping.weight", "1.0"))
    parts = [f"{kind} λ={weight:g}" if kind != "constant" else "constant bonus"]
    extra = {
        "params.subgoal.source": ("random", "random subgoals"),
        "params.subgoal.group": ("bottom", "bottom group"),
        "params.cvae.loss": ("mse", "CVAE mse"),
    }
    parts += [text for key, (v, text) in extra.items() if value(key, "") == v]
    return "SPOT, " + ", ".join(parts)


def dose_response(
    df: pd.DataFrame, experiments: Sequence[str], variant: str = "paper", high: float = HIGH_MODE
) -> list[Dose]:
    """Per dataset (scores of different datasets are never ranked together) and per arm, the mean
    term added per step (``shaping/r_final_mean − shaping/r_model_mean``) and the final score; over
    the dataset's runs, Spearman's ρ between the two with its paired-bootstrap CI. ρ > 0 (CI above
    0) says the score rises with the size of the added term, whatever the term is made of: the
    survival-bonus reading of rows CP. A description of the runs, not a claim of the paper."""
    name, sub = _experiment(df, experiments)
    done, note = most_queries(finished(sub))
    done = done[_in_variant(_either(_method("spot"), _method("pt")), variant)(done)] if len(done) else done
    if done.empty:
        return []
    doses = [_dose(g, name, variant, str(ds), high) for ds, g in done.groupby(_dataset_column(done), sort=True)]
    for dose in doses:
        dose.notes += [note] if note else []
    return doses


def _dose(done: pd.DataFrame, experiment: str, variant: str, dataset: str, high: float) -> Dose:
    """:func:`dose_response` on one dataset's finished runs."""
    dose = Dose(experiment, variant, dataset)
    added = done[ADDED[0]] - done[ADDED[1]] if all(c in done for c in ADDED) else pd.Series(np.nan, done.index)
    score = pd.to_numeric(done[METRICS["last"]], errors="coerce") if METRICS["last"] in done else np.nan
    done = done.assign(added=added, score=score)
    if lost := len(done) - len(done.dropna(subset=["added", "score"])):
        dose.notes.append(f"{lost} finished runs without the shaping metrics or a final score left out")
    done = done.dropna(subset=["added", "score"])
    if done.empty:
        return dose
    done = done.assign(arm=done.apply(_arm_label, axis=1))
    dose.notes += _digest_spread(done)
    for label, g in done.groupby("arm"):
        dose.arms.append(
            {
                "label": label,
                "runs": len(g),
                "added": float(g["added"].mean()),
                "score": stats.cell(g["score"].to_numpy(np.float64)),
                "high": high_mode(g, high),
                "length": _lengths(g),
            }
        )
    dose.arms.sort(key=lambda a: a["added"])
    dose.rho = stats.rank_correlation(done["added"].to_numpy(), done["score"].to_numpy())
    return dose


def _lengths(runs: pd.DataFrame) -> tuple[float, int]:
    """Mean final-evaluation episode length (``eval/length``) over the runs that logged it, and how
    many did (runs before the metric have none): on locomotion a fall ends an episode early, so it
    tells a run that falls from one that lasts."""
    lengths = pd.to_numeric(runs[LENGTH], errors="coerce").dropna() if LENGTH in runs else pd.Series(dtype=float)
    return (float(lengths.mean()) if len(lengths) else float("nan")), len(lengths)


def format_dose(dose: Dose) -> list[str]:
    """Lines of the dose-and-response section (none without runs)."""
    if not dose.arms:
        return []
    lines = [
        f"### The term added to the reward per step vs the final score on {dose.dataset} "
        f"(variant {dose.variant}, {_label(dose.experiment)})",
        "",
        "| arm | runs | added per step (mean) | final score: mean ± std [95% CI] | evaluations ≥ threshold "
        "| episode length (runs logging it) |",
        "|---|---|---|---|---|---|",
    ]
    for a in dose.arms:
        c = a["score"]
        ci = f"[{c['ci_low']:.1f}, {c['ci_high']:.1f}]" if np.isfinite(c["ci_low"]) else "(CI n/a)"
        high = a["high"].text() if a["high"] else "–"
        sd = f" ± {c['std']:.1f}" if np.isfinite(c["std"]) else ""  # one run has no std
        mean_length, logged = a["length"]
        length = f"{mean_length:.0f} ({logged} of {a['runs']})" if logged else "–"
        cells = [a["label"], a["runs"], f"{a['added']:.3f}", f"{c['mean']:.1f}{sd} {ci}", high, length]
        lines.append("| " + " | ".join(str(x) for x in cells) + " |")
    assert dose.rho is not None
    lines += [
        "",
        f"Spearman's ρ between the added term and the final score over the {dose.rho.n} runs: "
        f"{dose.rho.text(2)} (95% paired bootstrap): {stats.verdict(dose.rho)} that the score rises with "
        "the added term (a description of these runs, not a claim of the paper).",
    ]
    return [*lines, *[f"- {n}" for n in dose.notes], ""]


# --------------------------------------------------------------------------- output
def _label(experiment: str) -> str:
    """A long default experiment set (three or more experiments) by its key: ``set P``; the report
    lists each set's experiments once (:func:`format_rows`)."""
    if experiment.count("+") >= 2:
        for key, names in EXPERIMENTS.items():
            if names[0] == experiment:
                return f"set {key}"
    return experiment


def _plan_n(row: Row) -> str:
    """The planning section's n: the runs of each arm, or what else the row's plan counts (claim 4: seeds)."""
    if row.plan_unit == "runs":
        return _n(row)
    return f"{sum(row.sizes[0])} vs {sum(row.sizes[1])} {row.plan_unit}, {_datasets(len(row.sizes[0]))}"


def _datasets(k: int) -> str:
    return f"{k} dataset{'s' if k != 1 else ''}"


def _n(row: Row) -> str:
    return f"{row.n_x} vs {row.n_y} runs, {_datasets(len(row.datasets))}" if row.effect else "–"


def format_high(rows: Sequence[Row]) -> list[str]:
    """Lines of the high-mode section: per comparison (of the last-score rows) with curves for both
    arms, how many periodic evaluations reached the threshold. A description, not a test."""
    sel = [r for r in rows if r.high]
    if not sel:
        return []
    lines = [
        f"### Evaluations scoring ≥ {sel[0].high_mode:g} (the high mode), from the runs' evaluation curves",
        "",
        "| # | comparison | x: evaluations ≥ threshold | y: evaluations ≥ threshold |",
        "|---|---|---|---|",
    ]
    for r in sel:
        assert r.high is not None
        lines.append(f"| {r.claim} | {r.comparison} | {r.high[0].text()} | {r.high[1].text()} |")
    return [*lines, ""]


def format_paired(rows: Sequence[Row]) -> list[str]:
    """Lines of the seed-matched section: per row with pairs, each seed's x − y, their mean over
    datasets with its CI, and the reading it gives (not the verdict: that stays the unpaired one)."""
    sel = [r for r in rows if r.paired is not None]
    if not sel:
        return []
    lines = [
        "### Seed-matched differences (a second reading; the verdicts above are unpaired)",
        "",
        "Runs of one seed start from the same PRNG keys, and arms that train the same reward model "
        "share that seed's model; x − y per seed, its mean per dataset averaged over datasets, "
        "95% stratified bootstrap over seeds (over three pairs on one dataset the interval is their range). "
        "The reading "
        "is the exact sign-flip test's (two-sided p < 0.05), which no five or fewer pairs can pass "
        "(the smallest p of N pairs is 2 / 2^N). Seeds that only one arm ran are left out.",
        "",
        "| # | comparison | statistic | x − y by seed | effect [95% CI] | pairs | sign-flip p | reading |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sel:
        assert r.paired is not None
        digits = 3 if r.stat == "ood" else 1
        many = len(r.pairs) > 1
        by_seed = "; ".join(
            (f"{name}: " if many else "")
            + ", ".join(f"s{s} {d:+.{digits}f}" for s, d in zip(seeds, diffs, strict=True))
            for name, (seeds, diffs) in r.pairs.items()
        )
        n = sum(len(d) for _, d in r.pairs.values())
        lines.append(
            f"| {r.claim} | {r.comparison} | {r.stat} | {by_seed} | {r.paired.text(digits)} | {n} "
            f"| {r.paired_p:.3g} | {r.paired_verdict} |"
        )
    return [*lines, ""]


def _plan_number(value: float, digits: int, inf: str) -> str:
    if np.isnan(value):
        return "–"
    return inf if np.isinf(value) else f"{value:,.{digits}f}"


def _still_to_do(row: Row) -> str:
    """The runs each arm lacks for :attr:`Row.plan`'s runs per dataset, and their time at the arm's
    median run time (``time/total_s``; one core each at budget lab); none where the runs at hand
    already give a verdict (the plan is then the n a replication would want; a "borderline" verdict
    counts as one)."""
    assert row.plan is not None
    if row.verdict.startswith((stats.SUPPORTED, stats.NOT_SUPPORTED)):  # borderline ones too
        return "none: a verdict at this n"
    if not np.isfinite(row.plan.runs):
        return "–"
    need = int(row.plan.runs)
    missing = [sum(max(0, need - n) for n in sizes) for sizes in row.sizes]
    if not any(missing):
        return "0 + 0 (the runs at hand meet the plan; the verdict fell short at this n)"
    seconds = [m * t for m, t in zip(missing, row.run_s, strict=True) if m]
    time = f"{sum(seconds) / 3600:,.0f} h" if all(np.isfinite(seconds)) else "time not logged"
    unit = "" if row.plan_unit == "runs" else f" {row.plan_unit}"
    return f"{missing[0]:,} + {missing[1]:,}{unit} ({time})"


def format_plan(rows: Sequence[Row]) -> list[str]:
    """Lines of the planning section: per comparison with a permutation test, the pooled sd, the
    smallest effect its runs find with :data:`POWER`, and the runs the observed effect would need
    (:func:`spot.stats.power_plan`)."""
    sel = [r for r in rows if r.plan is not None and r.effect is not None and r.stat in ("last", "ood")]
    if not sel:
        return []
    lines = [
        "### Runs for a verdict (planning numbers, not findings)",
        "",
        f"From the two-sided two-sample t-test's power (noncentral t, α = {ALPHA:g}, power {POWER:.0%}) at "
        "the pooled within-dataset standard deviation of both arms: the smallest effect a t-test on the "
        f"runs at hand would find {POWER:.0%} of the time, and the runs per arm and dataset (equal arms) "
        "at which it would find the observed effect as often, never fewer than a verdict needs "
        f"({MIN_SEEDS}) nor than the permutation test needs to reach p < {ALPHA:g} "
        f"({stats.permutation_floor(1, ALPHA)} per arm on one dataset). ∞: no split of the runs at hand "
        f"gives p < {ALPHA:g}. Near that floor the permutation test finds less than the t-test (at 4 vs "
        "4 runs, the t-test's 80 % effect ~64 % of the time). "
        "The observed effect is itself uncertain (its CI is above) and the scores are often bimodal, "
        "so these numbers size the next runs; they are not evidence. The time is each arm's median "
        "`time/total_s` (one core per run at budget lab; a shared reward model's training counts "
        "in the first run of a seed only). Claim 4's rows count seeds per query count instead of runs "
        "(its test compares the seed-matched gains SPOT − PT at the two counts; a seed is a SPOT and a "
        "PT run, and its time both).",
        "",
        "| # | comparison | statistic | n | pooled sd | smallest effect found at this n | observed effect "
        "| runs per arm and dataset to find it | runs still to do (time) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sel:
        assert r.plan is not None and r.effect is not None
        digits = 3 if r.stat == "ood" else 1
        lines.append(
            f"| {r.claim} | {r.comparison} | {r.stat} | {_plan_n(r)} | {_plan_number(r.plan.sd, digits, '–')} "
            f"| {_plan_number(r.plan.mde, digits, '∞')} | {r.effect.value:+.{digits}f} "
            f"| {_plan_number(r.plan.runs, 0, f'> {stats.MAX_PLAN:,}')} | {_still_to_do(r)} |"
        )
    return [*lines, ""]


def format_rows(rows: Sequence[Row], extra: Sequence[str] = ()) -> str:
    """The report as Markdown: one table per statistic, the high-mode counts, the seed-matched
    differences, the runs a verdict would need, ``extra`` lines (the dose-and-response section), then the notes."""
    titles = {
        "last": "Last evaluation (`eval/score_final`): verdicts",
        "best": "Best evaluation (`eval/score_best`), for comparison",
        "ood": "Fig. 2: out-of-distribution extrapolation error (last)",
    }
    parts = []
    for stat, title in titles.items():
        sel = [r for r in rows if r.stat == stat]
        if not sel:
            continue
        parts += [
            f"### {title}",
            "",
            "| # | claim | comparison | experiment | effect [95% CI] | P(x > y) [95% CI] | means x / y | n | perm. p "
            "| verdict |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in sel:
            eff = r.effect.text(3 if stat == "ood" else 1) if r.effect else "–"
            poi = r.poi.text(2) if r.poi else "–"
            digits = 3 if stat == "ood" else 1
            means = f"{r.means[0]:.{digits}f} / {r.means[1]:.{digits}f}" if r.means else "–"
            perm = f"{r.perm_p:.2g}" if np.isfinite(r.perm_p) else "–"
            parts.append(
                f"| {r.claim} | {r.text} | {r.comparison} | {_label(r.experiment)} | {eff} | {poi} | {means} | {_n(r)} "
                f"| {perm} | {r.verdict} |"
            )
        parts.append("")
    parts += format_high(rows)
    parts += format_paired(rows)
    parts += format_plan(rows)
    parts += extra
    sets = sorted({(_label(r.experiment), r.experiment) for r in rows if _label(r.experiment) != r.experiment})
    if sets:
        parts += ["Experiment sets:", *[f"- {label}: {names}" for label, names in sets], ""]
    notes = sorted({f"claim {r.claim} ({r.comparison}, {_label(r.experiment)}): {n}" for r in rows for n in r.notes})
    if notes:
        parts += ["Notes:", *[f"- {n}" for n in notes]]
    return "\n".join(parts).rstrip() + "\n"
