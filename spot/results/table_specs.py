"""What each paper table is made of: its rows, columns and the runs it takes (:data:`SPECS`), the
paper's cells keyed like ours (:func:`paper_cells`), and the order rows and columns are shown in.
:mod:`spot.results.tables` builds the tables from these."""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import pandas as pd

from spot import SpotError
from spot.config import METHODS
from spot.results.paper import AVERAGE_ROW, note_seconds, paper_datasets, paper_tables, setting
from spot.results.select import required_param

TABLES = (1, 2, 3, 4, 7, 8)
METHOD_ORDER = METHODS  # the config's method order: columns of Table 1, curves of Fig. 2
SOURCE_ORDER = ("recipe", "file")
SHAPING_ORDER = ("neg_distance", "potential", "cosine", "?")
CVAE_LOSS_ORDER = ("mse", "mse_cos")
CVAE_LOSS_FROM_PAPER = {"mse": "mse", "mse+cosine": "mse_cos"}
TIME_COLUMNS = ("reward_model_s", "offline_rl_s", "total_s", "wall_s")
# The MLflow experiment each table's sweep writes (sweeps/paper/<name>.yaml; `--smoke` adds "-smoke").
SWEEP_EXPERIMENTS = {
    1: "table1",
    2: "table2_topk",
    3: "table3_shaping",
    4: "table4_queries",
    7: "table7_cvae_loss",
    8: "table1",
}


# --------------------------------------------------------------------------- table specs
def _param(runs: pd.DataFrame, key: str, table: int) -> pd.Series:
    return required_param(runs, key, f"table {table}")


def _shaped(runs: pd.DataFrame, table: int) -> pd.Series:
    return _param(runs, "shaping.kind", table) != "none"


def _group_label(group: str, top_k: float) -> str:
    k = f"{top_k:g}"
    k2 = f"{2 * top_k:g}"
    return {"top": f"top-{k}", "top_next": f"top-{k}-{k2}", "bottom_next": f"bottom-{k}-{k2}", "bottom": f"bottom-{k}"}[
        group
    ]


@dataclass(frozen=True)
class Spec:
    number: int
    title: str
    rows: tuple[str, ...]
    col: str
    kind: str  # "score" | "time"
    best: str  # "row" | "col" | "none"
    select: Callable[[pd.DataFrame, int], pd.Series] | None
    keys: Callable[[pd.DataFrame, int], dict[str, pd.Series]]


SPECS = {
    1: Spec(
        1,
        "Table 1: score per dataset and method",
        ("dataset",),
        "method",
        "score",
        "row",
        None,
        lambda r, t: {"dataset": r["paper_dataset"], "method": r["method"]},
    ),
    2: Spec(
        2,
        "Table 2: score per Top-K% percentile group (SPOT)",
        ("group",),
        "dataset",
        "score",
        "col",
        _shaped,
        lambda r, t: {
            "group": pd.Series(
                [
                    _group_label(g, float(k))
                    for g, k in zip(_param(r, "subgoal.group", t), _param(r, "subgoal.top_k", t), strict=True)
                ],
                index=r.index,
            ),
            "dataset": r["paper_dataset"],
        },
    ),
    3: Spec(
        3,
        "Table 3: score per shaping kind and weight λ",
        ("dataset", "shaping.kind"),
        "shaping.weight",
        "score",
        "row",
        _shaped,
        lambda r, t: {
            "dataset": r["paper_dataset"],
            "shaping.kind": _param(r, "shaping.kind", t),
            "shaping.weight": _param(r, "shaping.weight", t).astype(float),
        },
    ),
    4: Spec(
        4,
        "Table 4: score per number of preference queries",
        ("dataset", "method", "labels.num_queries"),
        "metric",
        "score",
        "none",
        None,
        lambda r, t: {
            "dataset": r["paper_dataset"],
            "method": r["method"],
            "labels.num_queries": _param(r, "labels.num_queries", t).astype(int),
            "metric": pd.Series("score", index=r.index),
        },
    ),
    7: Spec(
        7,
        "Table 7: score per CVAE loss (SPOT)",
        ("dataset",),
        "cvae.loss",
        "score",
        "row",
        _shaped,
        lambda r, t: {"dataset": r["paper_dataset"], "cvae.loss": _param(r, "cvae.loss", t)},
    ),
    8: Spec(
        8,
        "Table 8: wall time per stage, seconds",
        ("method", "dataset"),
        "time",
        "time",
        "none",
        None,
        lambda r, t: {"method": r["method"], "dataset": r["paper_dataset"]},
    ),
}


def table_spec(table: int) -> Spec:
    if table not in SPECS:
        raise SpotError(f"unknown table {table}; the paper's tables here are {', '.join(map(str, TABLES))}")
    return SPECS[table]


# --------------------------------------------------------------------------- ordering
def _group_rank(label: str) -> int:
    for rank, pattern in enumerate(
        (r"top-[\d.]+$", r"top-[\d.]+-[\d.]+$", r"bottom-[\d.]+-[\d.]+$", r"bottom-[\d.]+$")
    ):
        if re.fullmatch(pattern, str(label)):
            return rank
    return 99


def sort_key(name: str, value: Any) -> tuple:
    if name == "dataset":
        order = paper_datasets()
        if value == AVERAGE_ROW:
            return (2, 0, "")
        return (0, order.index(value), "") if value in order else (1, 0, str(value))
    orders: dict[str, Sequence[Any]] = {
        "method": METHOD_ORDER,
        "source": SOURCE_ORDER,
        "shaping.kind": SHAPING_ORDER,
        "cvae.loss": CVAE_LOSS_ORDER,
        "time": TIME_COLUMNS,
    }
    if name in orders:
        order = orders[name]
        return (0, list(order).index(value), "") if value in order else (1, 0, str(value))
    if name == "group":
        return (_group_rank(value), 0, str(value))
    if name == "labels.num_queries":
        return (0, -int(value), "")
    if name == "shaping.weight":
        return (0, float(value), "")
    return (0, 0, str(value))


def sorted_frame(df: pd.DataFrame, names: Sequence[str]) -> pd.DataFrame:
    keys = [
        tuple(sort_key(n, v) for n, v in zip(names, row, strict=True))
        for row in df[list(names)].itertuples(index=False)
    ]
    order = sorted(range(len(df)), key=lambda i: keys[i])
    return df.iloc[order].reset_index(drop=True)


# --------------------------------------------------------------------------- the paper's numbers
def paper_cells(table: int) -> pd.DataFrame:
    """The paper's cells of ``table`` keyed like :func:`build_table`'s cells (row keys + column)."""
    spec = table_spec(table)
    p = paper_tables()
    p = p[(p["table"] == table) & (p["dataset"] != AVERAGE_ROW)]
    out = pd.DataFrame({"paper": p["mean"].astype(float), "paper_std": p["std"].astype(float)})
    if table == 1:
        out["dataset"], out[spec.col] = p["dataset"], p["method"]
    elif table == 2:
        out["group"], out[spec.col] = p["setting"], p["dataset"]
    elif table == 3:
        out["dataset"] = p["dataset"]
        out["shaping.kind"] = [setting(s, "shaping") for s in p["setting"]]
        out[spec.col] = [float(setting(s, "lambda")) for s in p["setting"]]
    elif table == 4:
        out["dataset"], out["method"] = p["dataset"], p["method"]
        out["labels.num_queries"] = [int(setting(s, "queries")) for s in p["setting"]]
        out[spec.col] = "score"
    elif table == 7:
        out["dataset"] = p["dataset"]
        out[spec.col] = [CVAE_LOSS_FROM_PAPER[setting(s, "cvae_loss")] for s in p["setting"]]
    else:  # table 8: reward-model seconds in `mean`, the rest in `note`
        rows = []
        for _, r in p.iterrows():
            values = {
                "reward_model_s": float(r["mean"]),
                "offline_rl_s": note_seconds(r["note"], "offline RL"),
                "total_s": note_seconds(r["note"], "total"),
            }
            rows += [
                {"method": r["method"], "dataset": r["dataset"], spec.col: k, "paper": v, "paper_std": float("nan")}
                for k, v in values.items()
            ]
        out = pd.DataFrame(rows)
    return out.reset_index(drop=True)
