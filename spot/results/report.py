"""The claims report (``spot report``): a claims file's questions answered from runs, as Markdown.

:func:`build` reads each claim's experiment set from the runs (the first of its sets that has
runs), picks the runs its test looks at (every test but ``queries`` at their dataset's most
queries), and fills one :class:`~spot.results.compare.Row` per claim and metric (tests in
:mod:`spot.results.compare` and :mod:`spot.results.designs`); ``dose-response`` entries give the
sections of :mod:`spot.results.dose`. :func:`format_report` writes, in this order: one table per
statistic (last evaluation, the mean of each run's last K evaluations where a claim asks for
``lastK``, best evaluation, the OOD error, then any other metric), the high-mode counts, the paired
verdicts of claims paired by design (``paired: true``), the seed-matched differences of the other
rows, the runs a verdict would need, the dose-and-response sections, the runs of the sets read that
no row counts (and why), the labelled experiment sets and the notes. Both the last evaluation
(``eval/score_final``) and the best (``eval/score_best``) are reported, in separate tables,
because the paper does not say which it reports; verdicts are read from the last.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spot.results import stats
from spot.results.claims import Claim, ClaimsFile, last_k, metric_column
from spot.results.compare import ALPHA, HIGH_MODE, MIN_SEEDS, POWER, Row, compare, left_out, mean_last
from spot.results.designs import queries, runner_up
from spot.results.dose import Dose, dose_response, format_dose
from spot.results.load import CURVE_COLUMN
from spot.results.select import experiment_set, finished, most_queries

TITLES = {
    "last": "Last evaluation (`eval/score_final`): verdicts",
    "best": "Best evaluation (`eval/score_best`), for comparison",
    "ood": "Fig. 2: out-of-distribution extrapolation error (last)",
}


def title(stat: str) -> str:
    """A statistic's table title (its metric name in backticks when it has none of its own)."""
    k = last_k(stat)
    if k is not None:
        return (
            f"Mean of the last {k} evaluations (each run's last {k} points of `{CURVE_COLUMN}`), "
            "beside the last evaluation"
        )
    return TITLES.get(stat, f"`{stat}`")


@dataclass
class Report:
    """The rows of a claims file's comparisons, its dose-and-response sections, and the runs of the
    sets it read that no row counts (:func:`spot.results.compare.left_out`)."""

    rows: list[Row] = field(default_factory=list)
    doses: list[Dose] = field(default_factory=list)
    left_out: list[dict[str, str]] = field(default_factory=list)


def _stat_order(claims: ClaimsFile) -> list[str]:
    """The statistics in report order: last, the lastK means, best, ood, then other metrics as first named."""
    named = list(dict.fromkeys(m for c in claims.claims if c.test != "dose-response" for m in c.metrics))
    means = [m for m in named if last_k(m) is not None]
    first = [s for s in ("last",) if s in named] + means + [s for s in TITLES if s != "last" and s in named]
    return first + [m for m in named if m not in first]


def _with_last_k(runs: pd.DataFrame, claims: ClaimsFile) -> pd.DataFrame:
    """``runs`` with the derived column of every ``lastK`` statistic the claims name."""
    ks = sorted({k for c in claims.claims for m in c.metrics if (k := last_k(m)) is not None})
    return runs.assign(**{metric_column(f"last{k}"): mean_last(runs, k) for k in ks}) if ks else runs


def _short_curves(sub: pd.DataFrame, claim: Claim, stat: str) -> list[str]:
    """A note for a ``lastK`` row: the finished runs of its arms whose curve has fewer than K evaluations."""
    k = last_k(stat)
    done = finished(sub)
    if k is None or done.empty:
        return []
    arms = done[claim.x(done) | claim.y(done)]
    short = int(arms[metric_column(stat)].isna().sum())
    if not short:
        return []
    return [f"{short} finished run(s) have fewer than {k} evaluations in `{CURVE_COLUMN}`: left out of `{stat}`"]


def build(runs: pd.DataFrame, claims: ClaimsFile, high: float = HIGH_MODE) -> Report:
    """Every claim's rows, statistic by statistic (each in the file's claim order), and the dose
    sections; ``high`` is the score that counts an evaluation as in the high mode."""
    runs = _with_last_k(runs, claims)
    chosen = {}  # each claim's set, read once
    for claim in claims.claims:
        if claim.sets not in chosen:
            alternatives = claims.alternatives(claim)
            i, sub = experiment_set(runs, [s.experiments for s in alternatives])
            chosen[claim.sets] = (alternatives[i], sub, *most_queries(sub))
    read = pd.concat([sub for _, sub, _, _ in chosen.values()]) if chosen else runs.iloc[0:0]
    report = Report(left_out=left_out(read[~read.index.duplicated()]))
    for stat in _stat_order(claims):
        for claim in claims.claims:
            if claim.test == "dose-response" or stat not in claim.metrics:
                continue
            expset, sub, at_most, note = chosen[claim.sets]
            sub, note = (sub, None) if claim.test == "queries" else (at_most, note)
            row = Row(claim.id, claim.text, claim.comparison, expset.shown, stat, high_mode=high)
            row.notes += ([note] if note else []) + ([claim.note] if claim.note else [])
            row.notes += _short_curves(sub, claim, stat)
            row.listed = (expset.label, expset.names) if expset.label else None
            row.digits = claim.digits if claim.digits is not None else 3 if stat == "ood" else 1
            row.by_design = claim.paired
            metric = metric_column(stat)
            if claim.test == "queries":
                report.rows.append(queries(sub, claim, metric, row))
            elif claim.test == "runner-up":
                report.rows.append(runner_up(sub, claim, metric, row))
            else:
                report.rows.append(compare(sub, claim.x, claim.y, metric, row, claim.labels))
    for claim in claims.claims:
        if claim.test == "dose-response":
            expset, sub, _, _ = chosen[claim.sets]
            report.doses += dose_response(sub, claim, expset.shown, high)
    return report


# --------------------------------------------------------------------------- output
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


def _by_seed(r: Row) -> str:
    """Each seed's x − y, per dataset where the row has several."""
    many = len(r.pairs) > 1
    return "; ".join(
        (f"{name}: " if many else "") + ", ".join(f"s{s} {d:+.{r.digits}f}" for s, d in zip(seeds, diffs, strict=True))
        for name, (seeds, diffs) in r.pairs.items()
    )


def _n_pairs(r: Row) -> int:
    return sum(len(d) for _, d in r.pairs.values())


def _sign_flip(r: Row) -> str:
    """The sign-flip p with how it was found: every sign assignment, or a seeded draw of them."""
    n = _n_pairs(r)
    if not np.isfinite(r.paired_p):
        return "–"
    how = f"exact: all 2^{n} = {2**n:,}" if stats.sign_flip_exact(n) else f"{stats.N_RESAMPLES:,} random"
    return f"{r.paired_p:.3g} ({how} assignments)"


def format_by_design(rows: Sequence[Row]) -> list[str]:
    """Lines of the paired-verdict section: the rows of claims paired by design (``paired: true``)."""
    sel = [r for r in rows if r.by_design]
    if not sel:
        return []
    lines = [
        "### Paired verdicts (seed-matched by design)",
        "",
        "The claims file marks these comparisons `paired: true`: both arms were run at the same seeds "
        "to be compared seed by seed, so their verdict is the paired one (the unpaired verdict above "
        "stands beside it). Runs of one seed start from the same PRNG keys and share that seed's reward "
        "model. Per seed both arms ran: x − y; n pairs; their mean (per dataset, averaged over datasets) "
        "with its 95% CI (stratified bootstrap over seeds); the two-sided sign-flip p over the sign "
        "assignments of the n differences (under no difference each is as likely to carry either sign); "
        f"*supported* (*not supported*) where p < {ALPHA:g} and the mean is above (below) 0, else "
        f"*inconclusive*, and *too few seeds* below {MIN_SEEDS} pairs on a dataset. Seeds that only one "
        "arm ran are left out.",
        "",
        "| # | claim | comparison | statistic | pairs | x − y by seed | mean x − y [95% CI] | sign-flip p | verdict |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sel:
        if r.paired is None:
            verdict = "no runs" if r.effect is None else r.paired_verdict
            lines.append(f"| {r.claim} | {r.text} | {r.comparison} | {r.stat} | 0 | – | – | – | {verdict} |")
            continue
        lines.append(
            f"| {r.claim} | {r.text} | {r.comparison} | {r.stat} | {_n_pairs(r)} | {_by_seed(r)} "
            f"| {r.paired.text(r.digits)} | {_sign_flip(r)} | {r.paired_verdict} |"
        )
    return [*lines, ""]


def format_paired(rows: Sequence[Row]) -> list[str]:
    """Lines of the seed-matched section: per row with pairs (not paired by design), each seed's x − y,
    their mean over datasets with its CI, and the reading it gives (not the verdict: that stays the
    unpaired one)."""
    sel = [r for r in rows if r.paired is not None and not r.by_design]
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
        lines.append(
            f"| {r.claim} | {r.comparison} | {r.stat} | {_by_seed(r)} | {r.paired.text(r.digits)} | {_n_pairs(r)} "
            f"| {r.paired_p:.3g} | {r.paired_verdict} |"
        )
    return [*lines, ""]


def format_left_out(left: Sequence[dict[str, str]]) -> list[str]:
    """Lines of the section listing the runs of the sets read that no row counts, and why."""
    if not left:
        return []
    lines = [
        "### Runs left out",
        "",
        "Runs of the experiment sets read above that no row counts (`spot.results.select.finished`): "
        "runs that did not finish (FAILED, KILLED, still RUNNING) and finished runs replaced by a later "
        "re-run of the same config, dataset and seed.",
        "",
        "| run | experiment | method | dataset | seed | why |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| `{r['run']}` | {r['experiment']} | {r['method']} | {r['dataset']} | {r['seed']} | {r['why']} |"
        for r in left
    ]
    return [*lines, ""]


def _plan_number(value: float, digits: int, inf: str) -> str:
    if np.isnan(value):
        return "–"
    return inf if np.isinf(value) else f"{value:,.{digits}f}"


def still_to_do(row: Row) -> str:
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
    (:func:`spot.results.stats.power_plan`)."""
    sel = [
        r for r in rows if r.plan is not None and r.effect is not None and r.stat != "best" and last_k(r.stat) is None
    ]
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
        lines.append(
            f"| {r.claim} | {r.comparison} | {r.stat} | {_plan_n(r)} | {_plan_number(r.plan.sd, r.digits, '–')} "
            f"| {_plan_number(r.plan.mde, r.digits, '∞')} | {r.effect.value:+.{r.digits}f} "
            f"| {_plan_number(r.plan.runs, 0, f'> {stats.MAX_PLAN:,}')} | {still_to_do(r)} |"
        )
    return [*lines, ""]


def format_rows(rows: Sequence[Row]) -> list[str]:
    """Lines of the verdict tables: one per statistic, in the rows' order."""
    parts = []
    for stat in dict.fromkeys(r.stat for r in rows):
        sel = [r for r in rows if r.stat == stat]
        parts += [
            f"### {title(stat)}",
            "",
            "| # | claim | comparison | experiment | effect [95% CI] | P(x > y) [95% CI] | means x / y | n | perm. p "
            "| verdict |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in sel:
            eff = r.effect.text(r.digits) if r.effect else "–"
            poi = r.poi.text(2) if r.poi else "–"
            means = f"{r.means[0]:.{r.digits}f} / {r.means[1]:.{r.digits}f}" if r.means else "–"
            perm = f"{r.perm_p:.2g}" if np.isfinite(r.perm_p) else "–"
            verdict = r.verdict
            if r.by_design and r.effect is not None:
                verdict += f" (unpaired; paired by design: {r.paired_verdict}, below)"
            parts.append(
                f"| {r.claim} | {r.text} | {r.comparison} | {r.experiment} | {eff} | {poi} | {means} | {_n(r)} "
                f"| {perm} | {verdict} |"
            )
        parts.append("")
    return parts


def format_report(report: Report) -> str:
    """The report as Markdown: the verdict tables, the high-mode counts, the paired verdicts, the
    seed-matched differences, the runs a verdict would need, the dose-and-response sections, the
    runs left out, the labelled experiment sets, then the notes."""
    rows = report.rows
    parts = format_rows(rows) + format_high(rows) + format_by_design(rows) + format_paired(rows) + format_plan(rows)
    parts += [line for dose in report.doses for line in format_dose(dose)]
    parts += format_left_out(report.left_out)
    sets = sorted({r.listed for r in rows if r.listed})
    if sets:
        parts += ["Experiment sets:", *[f"- {label}: {names}" for label, names in sets], ""]
    notes = sorted({f"claim {r.claim} ({r.comparison}, {r.experiment}): {n}" for r in rows for n in r.notes})
    if notes:
        parts += ["Notes:", *[f"- {n}" for n in notes]]
    return "\n".join(parts).rstrip() + "\n"
