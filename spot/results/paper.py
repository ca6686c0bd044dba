"""The paper's numbers (``spot/paper_tables.csv``) and its dataset names.

``paper_tables.csv`` (columns ``table, dataset, method, setting, mean, std, note``) holds the
numbers of Tables 1, 2, 3, 4, 7 and 8 as transcribed from the paper; :func:`paper_tables` reads it
and :func:`spot.results.tables.paper_cells` keys it like our cells. :func:`paper_dataset_name` maps
our dataset names onto the paper's rows, which the run loader writes as ``paper_dataset``.
"""

from __future__ import annotations

import re
from functools import cache
from importlib import resources

import pandas as pd

from spot import SpotError

AVERAGE_ROW = "average"


@cache
def paper_tables() -> pd.DataFrame:
    """The paper's numbers: columns table, dataset, method, setting, mean, std, note."""
    with resources.files("spot").joinpath("paper_tables.csv").open("r", encoding="utf-8") as fh:
        df = pd.read_csv(fh)
    for col in ("setting", "note"):
        df[col] = df[col].fillna("").astype(str)
    return df


@cache
def paper_datasets() -> tuple[str, ...]:
    """The paper's dataset rows, in its order (the average row left out)."""
    names = paper_tables()["dataset"]
    return tuple(dict.fromkeys(n for n in names if n != AVERAGE_ROW))


def paper_dataset_name(name: str) -> str:
    """Our dataset name -> the paper's row name where one matches, else ``name`` unchanged.

    ``hopper-medium-replay-v2`` -> ``hopper-medium-replay``; ``lift_mh_low_dim`` -> ``lift-mh``.
    """
    n = str(name).strip().lower().replace("_", "-")
    n = re.sub(r"-v\d+$", "", n)
    n = re.sub(r"-low-dim$", "", n)
    return n if n in paper_datasets() else str(name)


def setting(text: str, key: str) -> str:
    """The value of ``key`` in a paper row's ``setting`` (``"shaping=cosine; lambda=1"``)."""
    for part in text.split(";"):
        k, _, v = part.partition("=")
        if k.strip() == key:
            return v.strip()
    raise SpotError(f"paper table setting {text!r} has no {key!r}")


def note_seconds(note: str, what: str) -> float:
    """The seconds a Table 8 row's note gives for ``what`` (``offline RL``, ``total``); nan if none."""
    m = re.search(rf"{what} (\d+) s", note)
    return float(m.group(1)) if m else float("nan")
