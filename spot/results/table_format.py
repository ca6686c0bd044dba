"""Paper tables as text: Markdown, LaTeX, CSV or a compact terminal table (``spot tables --format``).

:func:`format_table` renders a :func:`spot.results.tables.build_table` frame; :func:`across_datasets`
is Table 1's summary over datasets (IQM and P(SPOT > method) with their CIs) that ``spot tables
--table 1`` prints under the Markdown table; :func:`write_out` writes a table to ``--out``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from spot import SpotError
from spot.results import stats
from spot.results.select import by_dataset, finished

FORMATS = ("md", "latex", "csv", "text")
MIN_RUNS = 2
"""Fewest runs a cell needs to be bolded, and each arm per dataset to get a P(SPOT > method): one
run has no spread, so neither a 'best' nor a probability of improvement means anything there."""
METHOD_LABELS = {"oracle": "Oracle", "mr": "MR", "pt": "PT", "ipl": "IPL", "hpl": "HPL", "spot": "SPOT"}


def _num(x: float, kind: str) -> str:
    if kind == "time":
        return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.1f}"
    return f"{x:.2f}"


def _pm(mean: float, std: float, kind: str, pm: str) -> str:
    return _num(mean, kind) + (f" {pm} {_num(std, kind)}" if np.isfinite(std) else "")


def _cell_text(c: pd.Series, kind: str, fmt: str) -> str:
    pm, delta = ("$\\pm$", "$\\Delta$") if fmt == "latex" else ("±", "Δ")
    parts = []
    if np.isfinite(c["mean"]):
        ours = _pm(c["mean"], c["std"], kind, pm)
        if c["best"] and c["n"] >= MIN_RUNS:
            ours = f"\\textbf{{{ours}}}" if fmt == "latex" else f"**{ours}**"
        parts.append(f"{ours} ({int(c['n'])})")
        if np.isfinite(c.get("ci_low", np.nan)):
            dash = "--" if fmt == "latex" else "–"
            parts.append(f"CI {_num(c['ci_low'], kind)}{dash}{_num(c['ci_high'], kind)}")
    elif np.isfinite(c["paper"]):
        parts.append("--" if fmt == "latex" else "–")
    if np.isfinite(c["paper"]):
        paper = _pm(c["paper"], c["paper_std"], kind, pm)
        if np.isfinite(c["diff"]):
            sign = "+" if c["diff"] >= 0 else "-"
            paper += f", {delta} {sign}{_num(abs(c['diff']), kind)}"
        parts.append(f"{{\\scriptsize [{paper}]}}" if fmt == "latex" else f"[{paper}]")
    return " ".join(parts)


def _col_label(col: str, value: Any) -> str:
    if col == "method":
        return METHOD_LABELS.get(value, str(value))
    if col == "shaping.weight":
        return f"λ={value:g}"
    return str(value)


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}
_LATEX_UNICODE = {
    "±": r"$\pm$",
    "Δ": r"$\Delta$",
    "λ": r"$\lambda$",
    "≥": r"$\geq$",
    "−": "-",
    "–": "--",
    "ĝ": r"$\hat g$",
}


def _latex(text: str) -> str:
    out = "".join(_LATEX_SPECIAL.get(ch, ch) for ch in str(text))
    return "".join(_LATEX_UNICODE.get(ch, ch) for ch in out)


def format_table(table: pd.DataFrame, fmt: str = "md", width: int = 120) -> str:
    """Render a :func:`build_table` frame: ``md`` (Markdown with notes), ``latex`` (tabular + notes),
    ``csv``, or ``text`` (a compact plain table for a terminal of ``width`` columns).

    CSV has one line per row, the row keys first and then ``<column>/<field>`` numbers.
    """
    if fmt not in FORMATS:
        raise SpotError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    a = table.attrs
    rows, col, kind = a["rows"], a["col"], a["kind"]
    if fmt == "csv":
        flat = table.copy()
        flat.columns = [f"{c}/{f}" for c, f in flat.columns]
        return flat.reset_index().to_csv(index=False)
    col_values = list(dict.fromkeys(table.columns.get_level_values(0)))
    if fmt == "text":
        return _text_table(table, col_values, width)
    header = [*rows, *(_col_label(col, v) for v in col_values)]
    body = []
    for key, line in table.iterrows():
        key = key if isinstance(key, tuple) else (key,)
        cells = [_cell_text(line[v], kind, fmt) for v in col_values]
        body.append([*map(str, key), *cells])
    title = f"{a['title']} (metric {a['metric']})" if kind == "score" else a["title"]
    if fmt == "md":
        lines = [f"**{title}**", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in body]
        lines += [""] + [f"- {n}" for n in a["notes"]]
        return "\n".join(lines) + "\n"
    esc_body = [[_latex(x) for x in r[: len(rows)]] + r[len(rows) :] for r in body]
    lines = [
        f"% {_latex(title)}",
        "\\begin{tabular}{" + "l" * len(rows) + "|" + "c" * len(col_values) + "}",
        "\\hline",
        " & ".join(_latex(h) for h in header) + " \\\\",
        "\\hline",
    ]
    lines += [" & ".join(r) + " \\\\" for r in esc_body]
    lines += ["\\hline", "\\end{tabular}", ""]
    lines += [f"\\par{{\\footnotesize {_latex(n)}}}" for n in a["notes"]]
    return "\n".join(lines) + "\n"


def _text_cell(c: pd.Series, kind: str) -> str:
    """``ours±std (paper)`` with one decimal (times: :func:`_num`), ``*`` for the paper's bold rule."""

    def num(x: float) -> str:
        return _num(x, kind) if kind == "time" else f"{x:.1f}"

    ours = "–"
    if np.isfinite(c["mean"]):
        ours = num(c["mean"]) + (f"±{num(c['std'])}" if np.isfinite(c["std"]) and kind != "time" else "")
    ours += "*" if c["best"] else ""
    return ours + (f" ({num(c['paper'])})" if np.isfinite(c["paper"]) else "")


def _text_table(table: pd.DataFrame, col_values: list[Any], width: int) -> str:
    """Plain fixed-width columns, split into blocks of columns so that no line exceeds ``width``."""
    a = table.attrs
    keys = [" ".join(map(str, k if isinstance(k, tuple) else (k,))) for k in table.index]
    cols = [
        [_col_label(a["col"], v), *(_text_cell(table.loc[k, v], a["kind"]) for k in table.index)] for v in col_values
    ]
    key_w = max(len(k) for k in ["", *keys])
    widths = [max(map(len, c)) for c in cols]
    blocks, cur, used = [], [], key_w
    for i, w in enumerate(widths):
        if cur and used + 2 + w > width:
            blocks.append(cur)
            cur, used = [], key_w
        cur.append(i)
        used += 2 + w
    blocks.append(cur)
    title = f"{a['title']} (metric {a['metric']})" if a["kind"] == "score" else a["title"]
    lines = [title, "ours mean±std over seeds (paper); * = the paper's bold rule; full table: --format md"]
    for block in blocks:
        lines.append("")
        for r in range(len(keys) + 1):
            left = "" if r == 0 else keys[r - 1]
            lines.append((left.ljust(key_w) + "".join("  " + cols[i][r].rjust(widths[i]) for i in block)).rstrip())
    return "\n".join(lines) + "\n"


def check_out(path: str | Path) -> None:
    """:class:`SpotError` unless ``--out`` names a file that can be written: its folder exists and
    it is not a folder itself."""
    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise SpotError(f"--out {path}: folder '{folder}' does not exist; expected a file in an existing folder")
    if out.is_dir():
        raise SpotError(f"--out {path}: is a folder; expected a file name")


def write_out(path: str | Path, text: str) -> None:
    """Write a table to ``path`` (checked with :func:`check_out`); an OS error is a :class:`SpotError`."""
    check_out(path)
    try:
        Path(path).write_text(text)
    except OSError as err:
        raise SpotError(f"--out {path}: cannot write it ({err.strerror})") from None


# --------------------------------------------------------------------------- across datasets
def aggregate(runs: pd.DataFrame, metric: str = "metrics.eval/score_final", reference: str = "spot") -> pd.DataFrame:
    """Per method over the datasets every method has: IQM [CI] and P(reference > method) [CI]."""
    done = finished(runs)
    per = {m: by_dataset(g, metric) for m, g in done.groupby("method")}
    if not per:
        raise SpotError("no finished runs to aggregate")
    shared = sorted(set.intersection(*(set(v) for v in per.values())))
    out = []
    for m, by in sorted(per.items()):
        strata = [by[d] for d in shared]
        iqm = stats.estimate(strata, stats.iqm, checks=0) if shared else None
        poi, note = None, ""
        if reference in per and m != reference and shared:
            ref = [per[reference][d] for d in shared]
            if any(len(s) < MIN_RUNS for s in (*ref, *strata)):
                note = f"– (n < {MIN_RUNS})"
            else:
                poi = stats.estimate([*ref, *strata], stats.probability_of_improvement, checks=0)
        out.append(
            {
                "method": m,
                "datasets": len(shared),
                "runs": sum(map(len, strata)),
                "iqm": iqm.text() if iqm else "",
                f"P({reference} > method)": poi.text(2) if poi else note,
            }
        )
    return pd.DataFrame(out)


def across_datasets(runs: pd.DataFrame, metric: str) -> str:
    """Table 1's methods across datasets: IQM and P(SPOT > method), each with its 95 % CI (empty
    without finished runs)."""
    try:
        agg = aggregate(runs, f"metrics.{metric}")
    except SpotError:
        return ""
    lines = [
        "",
        "**Across datasets** (the datasets every method has; 95% stratified-bootstrap CIs)",
        "",
        "| method | datasets | runs | IQM [CI] | P(SPOT > method) [CI] |",
        "|---|---|---|---|---|",
    ]
    for _, r in agg.iterrows():
        lines.append(f"| {r['method']} | {r['datasets']} | {r['runs']} | {r['iqm']} | {r['P(spot > method)']} |")
    return "\n".join(lines) + "\n"
