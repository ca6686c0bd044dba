"""The claims report (``spot report``): a claims file's questions answered from runs, as Markdown.

:func:`build` reads each claim's experiment set from the runs (the first of its sets that has
runs), picks the runs its test looks at (every test but ``queries`` at their dataset's most
queries), and fills one :class:`~spot.results.compare.Row` per claim and metric (tests in
:mod:`spot.results.compare` and :mod:`spot.results.designs`); ``dose-response`` entries give the
sections of :mod:`spot.results.dose`. :func:`format_report` writes, in this order: one table per
statistic (last evaluation, best evaluation, the OOD error, then any other metric), the high-mode
counts, the seed-matched differences, the runs a verdict would need, the dose-and-response
sections, the labelled experiment sets and the notes. Both the last evaluation
(``eval/score_final``) and the best (``eval/score_best``) are reported, in separate tables,
because the paper does not say which it reports; verdicts are read from the last.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spot.results import stats
from spot.results.claims import METRICS, ClaimsFile
from spot.results.compare import ALPHA, HIGH_MODE, MIN_SEEDS, POWER, Row, compare
from spot.results.designs import queries, runner_up
from spot.results.dose import Dose, dose_response, format_dose
from spot.results.select import experiment_set, most_queries

TITLES = {
    "last": "Last evaluation (`eval/score_final`): verdicts",
    "best": "Best evaluation (`eval/score_best`), for comparison",
    "ood": "Fig. 2: out-of-distribution extrapolation error (last)",
}


@dataclass
class Report:
    """The rows of a claims file's comparisons and its dose-and-response sections."""

    rows: list[Row] = field(default_factory=list)
    doses: list[Dose] = field(default_factory=list)


def _stat_order(claims: ClaimsFile) -> list[str]:
    """The statistics in report order: last, best, ood, then other metrics as first named."""
    named = [m for c in claims.claims if c.test != "dose-response" for m in c.metrics]
    return [s for s in TITLES if s in named] + list(dict.fromkeys(m for m in named if m not in TITLES))


def build(runs: pd.DataFrame, claims: ClaimsFile, high: float = HIGH_MODE) -> Report:
    """Every claim's rows, statistic by statistic (each in the file's claim order), and the dose
    sections; ``high`` is the score that counts an evaluation as in the high mode."""
    chosen = {}  # each claim's set, read once
    for claim in claims.claims:
        if claim.sets not in chosen:
            alternatives = claims.alternatives(claim)
            i, sub = experiment_set(runs, [s.experiments for s in alternatives])
            chosen[claim.sets] = (alternatives[i], sub, *most_queries(sub))
    report = Report()
    for stat in _stat_order(claims):
        for claim in claims.claims:
            if claim.test == "dose-response" or stat not in claim.metrics:
                continue
            expset, sub, at_most, note = chosen[claim.sets]
            sub, note = (sub, None) if claim.test == "queries" else (at_most, note)
            row = Row(claim.id, claim.text, claim.comparison, expset.shown, stat, high_mode=high)
            row.notes += [note] if note else []
            row.listed = (expset.label, expset.names) if expset.label else None
            row.digits = claim.digits if claim.digits is not None else 3 if stat == "ood" else 1
            metric = METRICS.get(stat, f"metrics.{stat}")
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
        many = len(r.pairs) > 1
        by_seed = "; ".join(
            (f"{name}: " if many else "")
            + ", ".join(f"s{s} {d:+.{r.digits}f}" for s, d in zip(seeds, diffs, strict=True))
            for name, (seeds, diffs) in r.pairs.items()
        )
        n = sum(len(d) for _, d in r.pairs.values())
        lines.append(
            f"| {r.claim} | {r.comparison} | {r.stat} | {by_seed} | {r.paired.text(r.digits)} | {n} "
            f"| {r.paired_p:.3g} | {r.paired_verdict} |"
        )
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
    sel = [r for r in rows if r.plan is not None and r.effect is not None and r.stat != "best"]
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
            f"### {TITLES.get(stat, f'`{stat}`')}",
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
            parts.append(
                f"| {r.claim} | {r.text} | {r.comparison} | {r.experiment} | {eff} | {poi} | {means} | {_n(r)} "
                f"| {perm} | {r.verdict} |"
            )
        parts.append("")
    return parts


def format_report(report: Report) -> str:
    """The report as Markdown: the verdict tables, the high-mode counts, the seed-matched
    differences, the runs a verdict would need, the dose-and-response sections, the labelled
    experiment sets, then the notes."""
    rows = report.rows
    parts = format_rows(rows) + format_high(rows) + format_paired(rows) + format_plan(rows)
    parts += [line for dose in report.doses for line in format_dose(dose)]
    sets = sorted({r.listed for r in rows if r.listed})
    if sets:
        parts += ["Experiment sets:", *[f"- {label}: {names}" for label, names in sets], ""]
    notes = sorted({f"claim {r.claim} ({r.comparison}, {r.experiment}): {n}" for r in rows for n in r.notes})
    if notes:
        parts += ["Notes:", *[f"- {n}" for n in notes]]
    return "\n".join(parts).rstrip() + "\n"
