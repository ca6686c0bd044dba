"""The sweep file: YAML -> a validated :class:`Sweep` -> :class:`Trial` s, and the keys that name them.

A sweep file (``sweeps/*.yaml``, format in docs/sweeps.md) holds a ``base`` run config, cartesian
``grid`` axes and paired ``zip`` axes over dotted config keys, ``seeds``, the per-trial
``resources`` and a ``smoke`` block that shrinks it. :func:`load` validates the file and resolves
every trial's config with :func:`spot.config.resolve` before anything starts. The config blocks
are flattened and their keys checked by the config's own :func:`spot.config.flatten_yaml` and
:func:`spot.config.check_keys`.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import itertools
import json
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from spot import SpotError
from spot import config as config_lib
from spot.sweep import search as search_lib

SWEEP_KEYS = (
    "name",
    "base",
    "grid",
    "zip",
    "seeds",
    "seed_mode",
    "resources",
    "max_concurrent",
    "table",
    "store",
    "fast_compile",
    "smoke",
    *("metric", "mode", "search", "scheduler"),  # search and early stopping: spot.sweep.search
)
SMOKE_KEYS = ("base", "grid", "zip", "seeds", "max_concurrent", "resources", "fast_compile", "search", "scheduler")
SEED_MODES = ("trials", "sequential", "vmap")
RESOURCE_KEYS = ("cpu", "gpu")
# Set by the sweep itself: seeds come from `seeds:`, the tracking store and experiment from the launch.
RESERVED_KEYS = ("seed", "tracking.uri", "tracking.experiment", "tracking.record")
MAX_RUNS = 10_000
"""Most (config, seed) runs a sweep file may expand to: each config is resolved and checked before
anything starts (about 1 ms each), and each run is an MLflow run; a larger grid is refused with its
size before it is expanded. Split a larger study into several sweep files."""
PROGRESS_FROM = 500
"""Configs from which checking them shows a progress bar (on a terminal's standard error)."""
MAX_NAME = 200
"""Longest sweep name (the MLflow experiment's)."""


# --------------------------------------------------------------------------- keys and tags
def _canonical(obj: dict[str, Any]) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=list)


def config_key(overrides: dict[str, Any]) -> str:
    """Hash of a trial's override dict (without the seed): the same for all its seeds."""
    return hashlib.sha256(_canonical(overrides).encode()).hexdigest()[:16]


def run_key(overrides: dict[str, Any], seed: int) -> str:
    """Hash of the override dict with the seed: identifies one (config, seed) run of a sweep."""
    return hashlib.sha256(_canonical({**overrides, "seed": seed}).encode()).hexdigest()[:16]


def tag_value(value: Any) -> str:
    """An axis value as an MLflow tag or summary cell (lists and dicts as JSON)."""
    return json.dumps(value) if isinstance(value, (list, tuple, dict)) else str(value)


# --------------------------------------------------------------------------- the spec
@dataclass(frozen=True)
class Trial:
    """One Ray trial: a config (base + axis values) and the seeds it runs (one; or all of them,
    one after another (``seed_mode: sequential``) or IQL vmapped over them (``vmap``))."""

    axes: dict[str, Any]
    overrides: dict[str, Any]
    seeds: tuple[int, ...]
    vmap: bool = False

    @property
    def label(self) -> str:
        return " ".join(f"{k}={tag_value(v)}" for k, v in self.axes.items()) or "(base)"

    def to_config(self) -> dict[str, Any]:
        """The Ray trial config: all a trial needs to rebuild its run configs."""
        out = {"overrides": dict(self.overrides), "axes": dict(self.axes), "seeds": list(self.seeds)}
        return {**out, "vmap": True} if self.vmap else out  # trials and sequential: as before vmap existed


@dataclass(frozen=True)
class Sweep:
    """A validated sweep file (with the smoke block applied when ``smoke``)."""

    path: Path
    name: str
    smoke: bool
    base: dict[str, Any]
    grid: dict[str, list[Any]]
    zip: dict[str, list[Any]]
    seeds: tuple[int, ...]
    seed_mode: str
    resources: dict[str, float]
    max_concurrent: int | None
    table: int | None = None
    """Paper table printed (ours beside the paper's) when the launch ends; see spot.results.tables."""
    store: str | None = None
    """URI of the store every node shares datasets and stage entries through (spot.store); None:
    ``$SPOT_STORE``, else nothing shared."""
    store_options: tuple[tuple[str, str], ...] = ()
    """Store options (``endpoint_url``), as pairs."""
    fast_compile: bool = False
    """Trials compile with XLA's optimisations off (``SPOT_FAST_COMPILE``, :mod:`spot.runtime`):
    for smoke launches, whose programs compile for longer than they run."""
    metric: str | None = None  # what search: and scheduler: act on, and its mode (max, min)
    mode: str | None = None
    search: search_lib.Search | None = None  # a searcher's space instead of grid/zip (spot.sweep.search)
    scheduler: search_lib.Scheduler | None = None  # early stopping on the metric

    @property
    def experiment(self) -> str:
        """MLflow experiment name: the sweep name, with ``-smoke`` for smoke launches."""
        return f"{self.name}-smoke" if self.smoke else self.name

    @property
    def axis_keys(self) -> tuple[str, ...]:
        return (*self.grid, *self.zip, *(self.search.space if self.search else ()))

    def configs(self) -> list[dict[str, Any]]:
        """The axis values of every config: grid (first axis slowest) x zip rows."""
        grid_rows = [dict(zip(self.grid, combo, strict=True)) for combo in itertools.product(*self.grid.values())]
        n_zip = len(next(iter(self.zip.values()))) if self.zip else 1
        zip_rows = [{k: v[i] for k, v in self.zip.items()} for i in range(n_zip)]
        return [{**g, **z} for g in grid_rows for z in zip_rows]

    def trials(self) -> list[Trial]:
        """Expand configs x seeds. Seeds vary slowest, so an interrupted sweep has whole seed columns."""
        configs = self.configs()
        if self.search is not None:  # the template each proposed config completes (spot.sweep.tune)
            return [Trial({}, dict(self.base), self.seeds, self.seed_mode == "vmap")]
        if self.seed_mode in ("sequential", "vmap"):
            return [Trial(c, {**self.base, **c}, self.seeds, self.seed_mode == "vmap") for c in configs]
        return [Trial(c, {**self.base, **c}, (s,)) for s in self.seeds for c in configs]

    def runs(self) -> list[tuple[Trial, int]]:
        """Every (trial, seed) pair: one MLflow run each."""
        return [(t, s) for t in self.trials() for s in t.seeds]

    def spec_hash(self) -> str:
        """Identifies the expanded trial list; a resumed launch must expand to the same list."""
        spec = {"trials": [t.to_config() for t in self.trials()], "resources": self.resources}
        if self.metric is not None:  # (unchanged hashes for grid sweeps)
            spec["search"] = [repr(self.search), repr(self.scheduler), self.metric, self.mode]
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- validation
def _err(where: str, key: str, msg: str) -> SpotError:
    return SpotError(f"{where}: '{key}': {msg}")


def _check_known(data: dict[str, Any], allowed: tuple[str, ...], where: str, prefix: str) -> None:
    """The sweep file's own keys (top level, smoke, resources); config keys go to the config's check."""
    for key in data:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=2, cutoff=0.5)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise _err(where, f"{prefix}{key}", f"unknown key{hint} (expected {', '.join(allowed)})")


def _config_keys(data: Any, where: str, section: str) -> dict[str, Any]:
    """A config block (nested or dotted keys) -> flat dict of valid config keys the sweep may set."""
    at = f"{where}: '{section}'"
    flat = config_lib.check_keys(config_lib.flatten_yaml(data, at), at)
    for key in flat:
        if key in RESERVED_KEYS:
            what = {
                "seed": "give seeds in 'seeds:'",
                "tracking.record": "a sweep logs to MLflow, where --resume finds its runs (record single runs with "
                "'spot run --record')",
            }.get(key, "set by the sweep (name: / --tracking-uri)")
            raise _err(where, f"{section}.{key}", f"may not be set here: {what}")
    return flat


def _axes(data: Any, where: str, section: str) -> dict[str, list[Any]]:
    """Axes of a grid or zip block: dotted config keys -> non-empty lists (a grid's without repeats)."""
    axes = _config_keys(data, where, section)
    for key, values in axes.items():
        if not isinstance(values, list) or not values:
            raise _err(where, f"{section}.{key}", f"expected a non-empty list of values, got {values!r}")
        seen = [json.dumps(v, sort_keys=True) for v in values]
        if section.endswith("grid") and len(set(seen)) != len(seen):
            raise _err(where, f"{section}.{key}", f"repeats a value: {values!r}")
    return axes


def _replace_axes(
    axes: dict[str, list[Any]], new: dict[str, list[Any]], where: str, section: str
) -> dict[str, list[Any]]:
    for key in new:
        if key not in axes:
            raise _err(
                where, f"smoke.{section}.{key}", f"is not an axis of '{section}' (axes: {', '.join(axes) or 'none'})"
            )
    return {k: new.get(k, v) for k, v in axes.items()}


def _seeds(value: Any, where: str, key: str) -> tuple[int, ...]:
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value)
    ):
        raise _err(where, key, f"expected a non-empty list of non-negative integers, got {value!r}")
    if len(set(value)) != len(value):
        raise _err(where, key, f"repeats a seed: {value!r}")
    return tuple(value)


def _max_concurrent(value: Any, where: str, key: str) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise _err(where, key, f"expected a positive integer, got {value!r}")
    return value


def _resources(value: Any, where: str) -> dict[str, float]:
    if not isinstance(value, dict):
        raise _err(where, "resources", f"expected a mapping like {{cpu: 1, gpu: 0}}, got {value!r}")
    _check_known(value, RESOURCE_KEYS, where, "resources.")
    out = {"cpu": 1.0, "gpu": 0.0}
    for key, v in value.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
            # NaN passes every comparison: Ray then waits for resources no node has, for ever
            raise _err(where, f"resources.{key}", f"expected a finite non-negative number, got {config_lib.shown(v)}")
        out[key] = float(v)
    if out["cpu"] <= 0:
        raise _err(where, "resources.cpu", "must be > 0")
    if out["gpu"] > 1 and not out["gpu"].is_integer():
        raise _err(where, "resources.gpu", f"fractions are only for sharing one GPU (<= 1), got {out['gpu']}")
    return out


def _bool(value: Any, where: str, key: str) -> bool:
    if not isinstance(value, bool):
        raise _err(where, key, f"expected true or false, got {value!r}")
    return value


def _table(value: Any, where: str) -> int | None:
    from spot.results.tables import TABLES

    if value is not None and value not in TABLES:
        raise _err(where, "table", f"expected one of {', '.join(map(str, TABLES))}, got {value!r}")
    return value


def _store(value: Any, where: str) -> tuple[str | None, tuple[tuple[str, str], ...]]:
    """``store: URI`` or ``store: {uri: URI, endpoint_url: URL}`` -> (uri, options)."""
    from spot import store as store_lib

    if value is None:
        return None, ()
    if isinstance(value, dict):
        rest = {k: v for k, v in value.items() if k != "uri"}
        if "uri" not in value:
            raise _err(where, "store.uri", "missing (the store's folder path or s3://bucket/prefix)")
        options = store_lib.check_options(rest, f"{where}: 'store'")
        return store_lib.check_uri(value["uri"], f"{where}: 'store.uri'"), tuple(sorted(options.items()))
    return store_lib.check_uri(value, f"{where}: 'store'"), ()


def _read(path: Path, where: str) -> dict[str, Any]:
    data = config_lib.read_yaml(path, where)  # size-bounded, UTF-8, no aliases, no duplicate keys
    if not isinstance(data, dict):
        raise SpotError(f"{where}: expected a mapping with keys {', '.join(SWEEP_KEYS)}")
    _check_known(data, SWEEP_KEYS, where, "")
    return data


def _fields(data: dict[str, Any], where: str) -> dict[str, Any]:
    """The full (non-smoke) sweep: the :class:`Sweep` fields but path and smoke."""
    name = data.get("name")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise _err(where, "name", f"expected letters, digits, '_', '.', '-', got {config_lib.shown(name)}")
    if len(name) > MAX_NAME:
        raise _err(where, "name", f"{len(name)} characters; expected at most {MAX_NAME}")
    seed_mode = data.get("seed_mode", "trials")
    if seed_mode not in SEED_MODES:
        raise _err(where, "seed_mode", f"expected one of {', '.join(SEED_MODES)}, got {seed_mode!r}")
    return {
        "name": name,
        "base": _config_keys(data.get("base", {}), where, "base"),
        "grid": _axes(data.get("grid", {}), where, "grid"),
        "zip": _axes(data.get("zip", {}), where, "zip"),
        "seeds": _seeds(data.get("seeds", [0]), where, "seeds"),
        "seed_mode": seed_mode,
        "resources": _resources(data.get("resources", {}), where),
        "max_concurrent": _max_concurrent(data.get("max_concurrent"), where, "max_concurrent"),
        "table": _table(data.get("table"), where),
        "fast_compile": _bool(data.get("fast_compile", False), where, "fast_compile"),
        **dict(zip(("store", "store_options"), _store(data.get("store"), where), strict=True)),
    }


def smoke_base(base: dict[str, Any], smoke: dict[str, Any]) -> dict[str, Any]:
    """The base of a smoke launch: ``base`` updated with the smoke block's ``base``, where a smoke
    ``budget`` also wins over the base's settings of the keys its preset sets.

    A key set in ``base`` beats a budget preset (file settings come after presets), so without this
    the quickstart's ``iql.steps: 10000`` would override the tiny budget's 200 updates. When the
    smoke block names a budget, every base key of that budget's preset
    (:data:`spot.config.BUDGET_PRESETS`) is dropped; a key the smoke block sets itself is kept.
    """
    out = dict(base)
    if "budget" in smoke:
        for key in config_lib.BUDGET_PRESETS.get(smoke["budget"], {}):
            out.pop(key, None)
    return {**out, **smoke}


def _smoke_fields(data: dict[str, Any], full: dict[str, Any], where: str) -> dict[str, Any]:
    """``full`` with the ``smoke:`` block applied (checked even when not applied)."""
    block = data.get("smoke", {})
    if not isinstance(block, dict):
        raise _err(where, "smoke", f"expected a mapping, got {type(block).__name__}")
    _check_known(block, SMOKE_KEYS, where, "smoke.")
    # Smoke runs are tiny CPU checks: no GPU unless the smoke block asks for one.
    resources = (
        _resources(block["resources"], f"{where} smoke") if "resources" in block else {**full["resources"], "gpu": 0.0}
    )
    return {
        **full,
        "base": smoke_base(full["base"], _config_keys(block.get("base", {}), where, "smoke.base")),
        "grid": _replace_axes(full["grid"], _axes(block.get("grid", {}), where, "smoke.grid"), where, "grid"),
        "zip": _replace_axes(full["zip"], _axes(block.get("zip", {}), where, "smoke.zip"), where, "zip"),
        "seeds": _seeds(block["seeds"], where, "smoke.seeds") if "seeds" in block else full["seeds"],
        "max_concurrent": _max_concurrent(
            block.get("max_concurrent", full["max_concurrent"]), where, "smoke.max_concurrent"
        ),
        "resources": resources,
        "fast_compile": _bool(block.get("fast_compile", full["fast_compile"]), where, "smoke.fast_compile"),
    }


def _check_axes(fields: dict[str, Any], where: str) -> None:
    lengths = {k: len(v) for k, v in fields["zip"].items()}
    if len(set(lengths.values())) > 1:
        raise _err(where, "zip", f"paired axes need lists of equal length, got {lengths}")
    for key in fields["grid"]:
        if key in fields["zip"]:
            raise _err(where, f"zip.{key}", "is also a grid axis")
    for key in (*fields["grid"], *fields["zip"]):
        if key in fields["base"]:
            raise _err(where, f"base.{key}", "is also an axis; give it in one place")


def _check_size(fields: dict[str, Any], where: str) -> None:
    """Refuse, before expanding it, a sweep of more than :data:`MAX_RUNS` (config, seed) runs,
    naming its size and the longest axis."""
    axes = {f"grid.{k}": len(v) for k, v in fields["grid"].items()}
    n_zip = len(next(iter(fields["zip"].values()))) if fields["zip"] else 1
    runs = math.prod(axes.values()) * n_zip * len(fields["seeds"])
    if runs <= MAX_RUNS:
        return
    axes.update({"zip": n_zip, "seeds": len(fields["seeds"])})
    longest = max(axes, key=axes.__getitem__)
    factors = " x ".join(f"{n:,} ({k})" for k, n in axes.items())
    raise _err(
        where,
        longest,
        f"the sweep expands to {runs:,} runs = {factors}; expected at most {MAX_RUNS:,} "
        "(spot.sweep.spec.MAX_RUNS): split it into several sweep files",
    )


def _check_trial(trial: Trial, where: str) -> config_lib.ExperimentConfig:
    """Resolve the trial's config (and check its dataset name) or raise naming the trial."""
    from spot.data import registry

    try:
        cfg = config_lib.resolve(trial.overrides, {"seed": trial.seeds[0]})
        name = cfg.data.name
        if cfg.data.source == "file" and not Path(name).exists():
            raise SpotError(f"data.source=file but data file '{name}' does not exist")
        if cfg.data.source != "file" and not Path(name).exists():
            registry.entry(name)
        if trial.vmap:  # only IQL's policy stage is vmapped over seeds (IPL is refused)
            from spot.run import multiseed

            multiseed.check([cfg])
    except SpotError as e:
        raise SpotError(f"{where}: trial {trial.label}: {e}") from None
    return cfg


def _identity(cfg: config_lib.ExperimentConfig) -> config_lib.ExperimentConfig:
    """What makes two resolved configs the same run: the config, with a registry dataset under its
    canonical name (``hopper-medium-replay-v2`` is ``hopper-medium-replay``)."""
    from spot.data import registry

    name = cfg.data.name
    if cfg.data.source != "file" and not Path(name).exists():
        name = registry.canonical(name)
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, name=name))


def _check_trials(sweep: Sweep, where: str, progress: bool | None = None) -> None:
    """Resolve every config; refuse one that repeats another, as written or once resolved (``1e3``
    and ``1000``, ``[64, 64]`` and ``"64, 64"``, a ``-v2`` dataset name). ``progress``: a bar on
    standard error (None: for :data:`PROGRESS_FROM` configs or more, on a terminal)."""
    from tqdm.auto import tqdm

    configs = sweep.configs()
    seen: set[str] = set()
    resolved: dict[config_lib.ExperimentConfig, str] = {}
    disable = (None if len(configs) >= PROGRESS_FROM else True) if progress is None else not progress
    bar = tqdm(
        configs, desc=f"checking {sweep.path.name}", unit="config", file=sys.stderr, leave=False, disable=disable
    )
    with bar:
        for axes in bar:
            trial = Trial(axes, {**sweep.base, **axes}, sweep.seeds, sweep.seed_mode == "vmap")
            key = config_key(trial.overrides)
            if key in seen:
                raise SpotError(f"{where}: trial {trial.label} occurs twice (repeated zip row)")
            seen.add(key)
            same = _identity(_check_trial(trial, where))
            written = " ".join(f"{k}={config_lib.shown(v)}" for k, v in axes.items()) or "(base)"
            if same in resolved:
                raise SpotError(
                    f"{where}: trials {resolved[same]} and {written} resolve to the same config; expected "
                    "grid points and zip rows that differ once resolved (1e3 is 1000, '64, 64' is [64, 64])"
                )
            resolved[same] = written


def load(path: str | Path, *, smoke: bool = False, progress: bool | None = None) -> Sweep:
    """Read and validate a sweep file; with ``smoke`` apply its ``smoke:`` block.

    Raises SpotError naming the file and key for format errors, a sweep of more than
    :data:`MAX_RUNS` runs (before expanding it), the trial's axis values for a config that does not
    resolve, and both trials' for two that resolve to the same config. ``progress``: see
    :func:`_check_trials`.
    """
    path = Path(path)
    where = f"sweep file '{path}'"
    return _validated(_read(path, where), path, where, smoke, progress)


def load_dict(data: Any, *, smoke: bool = False, progress: bool | None = None) -> Sweep:
    """A sweep given as a mapping (a sweep file's content, ``name`` included), validated exactly as
    :func:`load` validates a file: the mapping is written as YAML text and parsed back by the same
    strict reader (in memory: nothing is written to disk). ``path`` is ``<name>.yaml``, not a file."""
    try:  # what a file of this content would hold; a value YAML cannot hold is refused
        text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    except yaml.YAMLError as e:
        raise SpotError(f"sweep (a dict): not writable as YAML ({str(e).splitlines()[0]})") from None
    name = data.get("name") if isinstance(data, dict) else None
    where = f"sweep '{name}' (a dict)"
    if len(text.encode()) > config_lib.MAX_YAML_BYTES:
        raise SpotError(f"{where}: larger than {config_lib.MAX_YAML_BYTES} bytes as YAML")
    parsed = yaml.load(text, Loader=config_lib.StrictLoader)  # noqa: S506 - a SafeLoader subclass
    if not isinstance(parsed, dict):
        raise SpotError(f"{where}: expected a mapping with keys {', '.join(SWEEP_KEYS)}")
    _check_known(parsed, SWEEP_KEYS, where, "")
    if "name" not in parsed:  # a file's default, its stem, has no counterpart here
        raise _err(where, "name", "missing (the sweep's name: its MLflow experiment)")
    return _validated(parsed, Path(f"{name}.yaml"), where, smoke, progress)


def _validated(data: dict[str, Any], path: Path, where: str, smoke: bool, progress: bool | None) -> Sweep:
    """:func:`load` and :func:`load_dict` after reading: the fields, the smoke block, the trials."""
    full = _fields({"name": path.stem, **data}, where)
    fields = _smoke_fields(data, full, where)  # checks the smoke block of every file
    if smoke and "smoke" not in data:
        raise SpotError(f"{where}: --smoke needs a 'smoke:' block (see docs/sweeps.md)")
    if not smoke:
        fields = full
    _check_axes(fields, where)
    fields.update(search_lib.check(data, fields, where, RESERVED_KEYS, smoke))
    _check_size(fields, where)
    sweep = Sweep(path=path, smoke=smoke, **fields)
    _check_trials(sweep, where, progress)
    search_lib.check_trials(sweep, where, _check_trial, Trial)  # the searched space's ends; a reward metric's method
    return sweep
