"""The term added to the reward per step against the final score (a claims file's ``dose-response``).

Over the runs of PT and SPOT's arms (the claim's ``among``), per dataset and per arm: the mean term
SPOT adds to the learned reward per step (``shaping/r_final_mean − shaping/r_model_mean``; 0 for
PT) and the final score; over the dataset's runs, Spearman's ρ between the two with its
paired-bootstrap CI. ρ > 0 (CI above 0) says the score rises with the size of the added term,
whatever the term is made of. A description of the runs, not a claim of the paper.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from spot.results import stats
from spot.results.claims import STATS, Claim
from spot.results.compare import HIGH_MODE, digest_spread, high_mode
from spot.results.select import dataset_column, finished, most_queries

ADDED = ("metrics.shaping/r_final_mean", "metrics.shaping/r_model_mean")  # their difference: the term added
LENGTH = "metrics.eval/length"  # the last evaluation's mean episode length (runs before the metric have none)


@dataclass
class Dose:
    """The term added to the learned reward per step against the final score, over the runs of
    SPOT and its variants and PT (whose added term is 0) of one experiment set, on one dataset."""

    experiment: str  # the set as shown
    variant: str | None
    dataset: str
    arms: list[dict] = field(default_factory=list)  # label, runs, added, score (stats.cell), high, length
    rho: stats.Estimate | None = None
    notes: list[str] = field(default_factory=list)


def arm_label(run: pd.Series) -> str:
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


def dose_response(sub: pd.DataFrame, claim: Claim, shown: str, high: float = HIGH_MODE) -> list[Dose]:
    """Per dataset (scores of different datasets are never ranked together) and per arm of
    ``claim.among``, the mean term added per step and the final score, from ``sub`` (the runs of the
    experiment set shown as ``shown``) at their dataset's most queries."""
    done, note = most_queries(finished(sub))
    done = done[claim.among(done)] if len(done) else done
    if done.empty:
        return []
    doses = [_dose(g, shown, claim.variant, str(ds), high) for ds, g in done.groupby(dataset_column(done), sort=True)]
    for dose in doses:
        dose.notes += [note] if note else []
    return doses


def _dose(done: pd.DataFrame, experiment: str, variant: str | None, dataset: str, high: float) -> Dose:
    """:func:`dose_response` on one dataset's finished runs."""
    dose = Dose(experiment, variant, dataset)
    added = done[ADDED[0]] - done[ADDED[1]] if all(c in done for c in ADDED) else pd.Series(np.nan, done.index)
    score = pd.to_numeric(done[STATS["last"]], errors="coerce") if STATS["last"] in done else np.nan
    done = done.assign(added=added, score=score)
    if lost := len(done) - len(done.dropna(subset=["added", "score"])):
        dose.notes.append(f"{lost} finished runs without the shaping metrics or a final score left out")
    done = done.dropna(subset=["added", "score"])
    if done.empty:
        return dose
    done = done.assign(arm=done.apply(arm_label, axis=1))
    dose.notes += digest_spread(done)
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
    where = f"variant {dose.variant}, {dose.experiment}" if dose.variant else dose.experiment
    lines = [
        f"### The term added to the reward per step vs the final score on {dose.dataset} ({where})",
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
