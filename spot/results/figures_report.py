"""The claims report as pictures: an interval plot of the claims' effects, and one HTML page.

* :func:`draw_claims`: per statistic (last, best, ood...) a panel with one row per claim and
  comparison: the effect (:attr:`spot.results.compare.Row.effect`, mean difference over datasets)
  as a point and its 95 % stratified bootstrap CI as a bar, coloured by the verdict; a line at 0.
  The points are the report's rows, not a recomputation.
* :func:`html_page`: ``spot report --html``: one self-contained page (no external links, scripts or
  fonts): the report's tables (the Markdown of :func:`spot.results.report.format_report`, from the
  same rows, as HTML tables) after the interval plot, the evaluation curves per method and the
  performance profile (:mod:`spot.results.figures_curves`), each a base64 PNG. Every text taken
  from the claims file or the runs is HTML-escaped.
"""

from __future__ import annotations

import base64
import html
import io
import re
from collections.abc import Sequence

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from spot import SpotError
from spot.results import figures_curves, stats
from spot.results.compare import Row
from spot.results.report import Report, format_report, title

COLOURS = {stats.SUPPORTED: "tab:green", stats.NOT_SUPPORTED: "tab:red"}
EFFECT_GID = "effect"  # the gid of each plotted effect (tests read the points back by it)


def claim_rows(rows: Sequence[Row]) -> list[Row]:
    """The rows with an effect (a comparison that had runs)."""
    return [r for r in rows if r.effect is not None]


def draw_claims(rows: Sequence[Row]) -> Figure:
    """One panel per statistic: each row's effect and 95 % CI, coloured by its verdict."""
    sel = claim_rows(rows)
    if not sel:
        raise SpotError("no claim has runs to plot (every comparison is 'no runs')")
    stat_names = list(dict.fromkeys(r.stat for r in sel))
    counts = [sum(r.stat == s for r in sel) for s in stat_names]
    fig = Figure(figsize=(9, 0.3 * sum(counts) + 1.1 * len(stat_names) + 0.4), layout="constrained")
    axes = fig.subplots(len(stat_names), 1, squeeze=False, gridspec_kw={"height_ratios": counts})[:, 0]
    for ax, stat in zip(axes, stat_names, strict=True):
        mine = [r for r in sel if r.stat == stat]
        ax.axvline(0.0, color="0.4", lw=0.8)
        for y, r in enumerate(mine):
            assert r.effect is not None
            est = r.effect
            colour = COLOURS.get(r.verdict.split(" (")[0], "0.45")
            err = None if np.isnan(est.low) else [[est.value - est.low], [est.high - est.value]]
            bars = ax.errorbar([est.value], [y], xerr=err, fmt="o", color=colour, ms=4, capsize=2)
            bars.lines[0].set_gid(EFFECT_GID)
        ax.set_yticks(range(len(mine)), [f"{r.claim}: {r.comparison} ({r.experiment})"[:60] for r in mine], fontsize=7)
        ax.set_ylim(len(mine) - 0.5, -0.5)
        ax.set_xlabel("effect x − y (mean over datasets), 95% CI", fontsize=8)
        ax.set_title(title(stat).replace("`", ""), fontsize=8)
        ax.grid(axis="x", alpha=0.3)
    fig.suptitle("claims: green supported, red not supported, grey otherwise", fontsize=8)
    return fig


def plotted_effects(fig: Figure) -> list[list[float]]:
    """Per panel, the x of every effect point :func:`draw_claims` drew, top to bottom."""
    return [[float(ln.get_xdata()[0]) for ln in ax.lines if ln.get_gid() == EFFECT_GID] for ax in fig.axes]


# --------------------------------------------------------------------------- HTML
def png_data(fig: Figure, dpi: int = 110) -> str:
    """``fig`` as a ``data:image/png;base64,...`` URI."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _inline(text: str) -> str:
    out = html.escape(text, quote=False)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", out)


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split(" | ")]


def markdown_html(text: str) -> str:
    """The report's Markdown (headings, pipe tables, bullet lists, paragraphs) as HTML."""
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")), 6)
            out.append(f"<h{level}>{_inline(line.lstrip('#').strip())}</h{level}>")
        elif line.startswith("|"):
            block = []
            while i < len(lines) and lines[i].startswith("|"):
                block.append(lines[i])
                i += 1
            body = [b for b in block[1:] if not set(b) <= set("|-: ")]
            head = "".join(f"<th>{_inline(c)}</th>" for c in _cells(block[0]))
            rows = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in _cells(b)) + "</tr>" for b in body)
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
            continue
        elif line.startswith("- "):
            items = []
            while i < len(lines) and lines[i].startswith("- "):
                items.append(f"<li>{_inline(lines[i][2:])}</li>")
                i += 1
            out.append("<ul>" + "".join(items) + "</ul>")
            continue
        elif line.strip():
            out.append(f"<p>{_inline(line)}</p>")
        i += 1
    return "\n".join(out)


STYLE = (
    "body{font-family:sans-serif;max-width:1400px;margin:1em auto;padding:0 1em;color:#222}"
    "table{border-collapse:collapse;margin:0.5em 0 1.5em;font-size:0.8em}"
    "th,td{border:1px solid #bbb;padding:2px 6px;text-align:left;vertical-align:top;overflow-wrap:anywhere}"
    "th{background:#eee}img{max-width:100%;border:1px solid #ddd}figure{margin:1em 0}"
    "figcaption{font-size:0.85em;color:#555}"
)


CAPTIONS = {
    "claims": "Each claim's effect with its 95% CI (the rows of the tables below).",
    "curves": "Evaluation curves per method, all runs: mean over seeds, 95% bootstrap CI band.",
    "profile": "Performance profile of the final scores, all runs (95% stratified bootstrap band).",
}


def _figures(runs: pd.DataFrame, report: Report) -> list[tuple[str, str]]:
    """``(caption, data URI)`` of the page's figures; a figure the runs cannot give is left out."""
    figs: list[tuple[str, str]] = []
    if claim_rows(report.rows):
        figs.append((CAPTIONS["claims"], png_data(draw_claims(report.rows))))
    try:
        summary = figures_curves.summarize_curves(figures_curves.curve_points(runs))
        figs.append((CAPTIONS["curves"], png_data(figures_curves.draw_curves(summary))))
    except SpotError:
        pass  # runs without exported curves: no curves figure
    try:
        prof = figures_curves.profile(figures_curves.final_scores(runs))
        figs.append((CAPTIONS["profile"], png_data(figures_curves.draw_profile(prof))))
    except SpotError:
        pass  # no final scores, or no dataset every method ran
    return figs


def html_page(runs: pd.DataFrame, report: Report, title: str = "spot report") -> str:
    """The report as one self-contained HTML page: tables, then the figures as inline PNGs."""
    figs = "\n".join(
        f'<figure><img alt="{html.escape(cap)}" src="{uri}"><figcaption>{html.escape(cap)}</figcaption></figure>'
        for cap, uri in _figures(runs, report)
    )
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{STYLE}</style></head><body>\n<h1>{html.escape(title)}</h1>\n"
        f"<p>{len(runs)} runs. Figures first, then the report's tables.</p>\n{figs}\n"
        f"{markdown_html(format_report(report))}\n</body></html>\n"
    )
