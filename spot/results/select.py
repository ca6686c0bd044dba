"""The one run selector: which runs count, which experiments a set reads, which runs make an arm.

``spot tables`` and ``spot report`` both select runs here:

* :func:`finished`: FINISHED runs only; a re-run of a (config, seed) on the same dataset replaces the
  earlier run (the later start counts). FAILED, KILLED and unfinished runs never count; :func:`not_finished` lists
  them with their failure reason.
* :func:`experiment_set`: the runs of an experiment set, the first of several alternatives that has
  runs.
* :func:`compile_filter`: an arm (or any group of runs) from a claims file's filter mapping, on
  the runs' method, fidelity variant, dataset and params (:func:`param_text`, :func:`param_numbers`).
* :func:`most_queries`: every comparison but the query-count one reads the runs at their dataset's
  largest ``labels.num_queries``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from spot import SpotError

Filter = Callable[[pd.DataFrame], pd.Series]
DEFAULT_VARIANT = "spot"  # runs logged before the `variant` key ran this package's defaults
QUERIES = "params.labels.num_queries"
FILTER_KEYS = ("method", "variant", "dataset", "params", "all", "any", "none")
CONDITIONS = ("not", "in", "other_than")


# --------------------------------------------------------------------------- which runs count
RUN_KEY = ("config_hash", "dataset", "dataset_source", "seed")  # a re-run repeats all four


def finished(runs: pd.DataFrame) -> pd.DataFrame:
    """FINISHED runs, one per (config, dataset, dataset source, seed): a re-run replaces the earlier
    run (stable order by ``start_time``, the last kept). The config hash covers every param, the
    dataset's among them; the dataset columns keep runs apart whose params do not name it."""
    out = runs[runs["status"] == "FINISHED"]
    if "start_time" in out:
        out = out.sort_values("start_time", kind="stable")
    return out.drop_duplicates([c for c in RUN_KEY if c in out], keep="last")


def not_finished(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs that are not FINISHED (FAILED, KILLED, still RUNNING), with the failure reason."""
    out = runs[runs["status"] != "FINISHED"]
    cols = ["run_id", "experiment", "method", "dataset", "seed", "status"]
    reason = out["tags.failure_reason"] if "tags.failure_reason" in out else pd.Series("", index=out.index)
    return out[cols].assign(failure_reason=reason.fillna("")).reset_index(drop=True)


def experiment_set(runs: pd.DataFrame, alternatives: Sequence[Sequence[str]]) -> tuple[int, pd.DataFrame]:
    """``(index of the first alternative with runs, its runs)``; each alternative is a list of
    experiment names read together. None with runs: ``(0, no runs)``."""
    for i, names in enumerate(alternatives):
        sub = runs[runs["experiment"].isin(list(names))]
        if len(sub):
            return i, sub
    return 0, runs.iloc[0:0]


def dataset_column(runs: pd.DataFrame) -> str:
    """The column that names a run's dataset: the paper's name where the results have it."""
    return "paper_dataset" if "paper_dataset" in runs else "dataset"


def by_dataset(runs: pd.DataFrame, metric: str) -> dict[str, np.ndarray]:
    """Per dataset (sorted), the finite values of ``metric`` (a column) of ``runs``."""
    if metric not in runs:
        return {}
    out = {}
    for name, g in runs.groupby(dataset_column(runs), sort=True):
        v = pd.to_numeric(g[metric], errors="coerce").to_numpy(np.float64)
        v = v[np.isfinite(v)]
        if len(v):
            out[str(name)] = v
    return out


def most_queries(runs: pd.DataFrame) -> tuple[pd.DataFrame, str | None]:
    """The runs at the largest query count of their dataset (runs without the key count as at it),
    and a note naming what was left out: every comparison but the query-count one compares arms at
    one query count, so the fewer-query runs of claim 4's arms (in the same experiment set) never
    enter claim 1's arms."""
    if runs.empty or QUERIES not in runs:
        return runs, None
    q = pd.to_numeric(runs[QUERIES], errors="coerce")
    keep = q.isna() | (q == q.groupby(runs[dataset_column(runs)].astype(str)).transform("max"))
    if keep.all():
        return runs, None
    counts = ", ".join(f"{int(n)} at {int(v)}" for v, n in q[~keep].value_counts().sort_index().items())
    return runs[keep], f"runs at fewer queries than their dataset's most left out ({counts}; claim 4's arms)"


# --------------------------------------------------------------------------- params
def param_text(runs: pd.DataFrame, key: str) -> pd.Series | None:
    """``params.<key>`` as text (``None`` where no run logged the key)."""
    col = f"params.{key}"
    return runs[col].astype(str) if col in runs else None


def param_numbers(runs: pd.DataFrame, key: str) -> pd.Series:
    """``params.<key>`` as numbers (nan where a run did not log it or logged text)."""
    col = f"params.{key}"
    return pd.to_numeric(runs[col], errors="coerce") if col in runs else pd.Series(np.nan, index=runs.index)


def required_param(runs: pd.DataFrame, key: str, what: str) -> pd.Series:
    """``params.<key>`` of every run; a :class:`SpotError` naming ``what`` needs it if a run lacks it."""
    col = f"params.{key}"
    if col not in runs or runs[col].isna().any():
        raise SpotError(f"{what} needs the param {key!r}, which some runs do not have")
    return runs[col]


def variant_of(runs: pd.DataFrame) -> pd.Series:
    """Each run's fidelity variant; runs logged before the key count as :data:`DEFAULT_VARIANT`."""
    if "params.variant" not in runs:
        return pd.Series(DEFAULT_VARIANT, index=runs.index)
    return runs["params.variant"].fillna(DEFAULT_VARIANT)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _equal(key: str, value: Any) -> Filter:
    """Runs that logged ``key`` as ``value``: as numbers for a number, else as text."""
    if _number(value):
        return lambda df: param_numbers(df, key) == value

    def select(df: pd.DataFrame) -> pd.Series:
        text = param_text(df, key)
        return pd.Series(False, index=df.index) if text is None else text == str(value)

    return select


def _other_than(key: str, default: Any) -> Filter:
    """Runs that logged ``key`` as something other than ``default`` (runs without it: the default)."""
    if _number(default):
        return lambda df: param_numbers(df, key).notna() & (param_numbers(df, key) != default)
    col = f"params.{key}"
    return lambda df: df[col].notna() & (df[col].astype(str) != str(default)) if col in df else _none(df)


def _none(df: pd.DataFrame) -> pd.Series:
    return pd.Series(False, index=df.index)


def _any_of(filters: Sequence[Filter]) -> Filter:
    def select(df: pd.DataFrame) -> pd.Series:
        out = _none(df)
        for f in filters:
            out = out | f(df)
        return out

    return select


def _all_of(filters: Sequence[Filter]) -> Filter:
    def select(df: pd.DataFrame) -> pd.Series:
        out = pd.Series(True, index=df.index)
        for f in filters:
            out = out & f(df)
        return out

    return select


# --------------------------------------------------------------------------- filters from a claims file
def _condition(key: str, cond: Any, where: str) -> Filter:
    """One ``params`` entry: ``VALUE`` (equal), ``{not: VALUE}``, ``{in: [VALUES]}``, ``{other_than: VALUE}``."""
    if isinstance(cond, Mapping):
        if len(cond) != 1 or next(iter(cond)) not in CONDITIONS:
            raise SpotError(f"{where}.params.{key}: expected a value or one of {{{', '.join(CONDITIONS)}}}: VALUE")
        ((kind, value),) = cond.items()
        if kind == "in":
            if not isinstance(value, list) or not value:
                raise SpotError(f"{where}.params.{key}.in: expected a non-empty list of values")
            return _any_of([_equal(key, v) for v in value])
        _scalar(value, f"{where}.params.{key}.{kind}")
        return _other_than(key, value) if kind == "other_than" else (lambda df, eq=_equal(key, value): ~eq(df))
    _scalar(cond, f"{where}.params.{key}")
    return _equal(key, cond)


def _scalar(value: Any, where: str) -> None:
    if not isinstance(value, (str, int, float, bool)):
        raise SpotError(f"{where}: expected a text, number or true/false, got {type(value).__name__}")


def _names(value: Any, where: str) -> list[str]:
    items = value if isinstance(value, list) else [value]
    if not items or not all(isinstance(v, str) and v for v in items):
        raise SpotError(f"{where}: expected a name or a list of names")
    return items


def compile_filter(spec: Any, named: Mapping[str, Any], where: str, _seen: tuple[str, ...] = ()) -> Filter:
    """A :data:`Filter` from a claims file's filter: a name from ``named`` (the file's ``filters``),
    or a mapping whose entries must all hold: ``method``, ``dataset`` and ``variant`` (a name or a
    list; runs without the ``variant`` key count as :data:`DEFAULT_VARIANT`), ``params`` (key ->
    condition, see :func:`_condition`), and ``all`` / ``any`` / ``none`` (lists of filters).
    ``where`` names the place in the file for errors."""
    if isinstance(spec, str):
        if spec not in named:
            raise SpotError(f"{where}: no filter named {spec!r} (the file's filters: {', '.join(named) or 'none'})")
        if spec in _seen:
            raise SpotError(f"{where}: filter {spec!r} refers to itself")
        return compile_filter(named[spec], named, f"{where} (filters.{spec})", (*_seen, spec))
    if not isinstance(spec, Mapping) or not spec:
        raise SpotError(f"{where}: expected a filter name or a mapping of {', '.join(FILTER_KEYS)}")
    unknown = [k for k in spec if k not in FILTER_KEYS]
    if unknown:
        raise SpotError(f"{where}: unknown key {unknown[0]!r}; a filter takes {', '.join(FILTER_KEYS)}")
    parts: list[Filter] = []
    if "method" in spec:
        methods = _names(spec["method"], f"{where}.method")
        parts.append(lambda df: df["method"].isin(methods))
    if "variant" in spec:
        variants = _names(spec["variant"], f"{where}.variant")
        parts.append(lambda df: variant_of(df).isin(variants))
    if "dataset" in spec:
        datasets = _names(spec["dataset"], f"{where}.dataset")
        parts.append(lambda df: df[dataset_column(df)].astype(str).isin(datasets))
    params = spec.get("params", {})
    if not isinstance(params, Mapping):
        raise SpotError(f"{where}.params: expected a mapping of param key -> condition")
    parts += [_condition(str(k), v, where) for k, v in params.items()]
    for key in ("all", "any", "none"):
        if key not in spec:
            continue
        if not isinstance(spec[key], list) or not spec[key]:
            raise SpotError(f"{where}.{key}: expected a non-empty list of filters")
        subs = [compile_filter(s, named, f"{where}.{key}[{i}]", _seen) for i, s in enumerate(spec[key])]
        parts.append(_all_of(subs) if key == "all" else _any_of(subs) if key == "any" else _not(_any_of(subs)))
    return _all_of(parts)


def _not(f: Filter) -> Filter:
    return lambda df: ~f(df)


def both(a: Filter, b: Filter) -> Filter:
    """Runs in ``a`` and in ``b``."""
    return _all_of([a, b])


def everything(df: pd.DataFrame) -> pd.Series:
    """The filter that keeps every run."""
    return pd.Series(True, index=df.index)
