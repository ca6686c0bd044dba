"""Sweeps: a YAML file of axes over run configs -> Ray Tune trials -> one MLflow run per (config, seed).

A sweep file (``sweeps/*.yaml``, format in docs/sweeps.md) holds a ``base`` run config, cartesian
``grid`` axes and paired ``zip`` axes over dotted config keys, ``seeds``, the per-trial
``resources`` and a ``smoke`` block that shrinks it. :func:`load` validates the file and resolves
every trial's config with :func:`spot.config.resolve` before anything starts.

:func:`run_sweep` (``spot sweep FILE``) runs the trials with Ray Tune: one function trainable,
:func:`_trainable`, gets a trial's override dict, resolves the config, runs
:func:`spot.pipeline.run` for each of its seeds and ``tune.report``s the scores. MLflow is the
record: the driver creates the experiment and a parent run; each (config, seed) is a child run
tagged with the sweep id, the Ray trial id, a ``trial_key`` (hash of the override dict and seed)
and one ``axis.<key>`` tag per axis. With no tracking URI the driver serves a SQLite store through
a loopback ``mlflow server`` (:mod:`spot.mlflow_server`), so no trial writes SQLite itself.

Resume and failures: ``--resume`` restores the Ray experiment (``Tuner.restore``) after closing
the runs an interrupted launch left RUNNING (they become KILLED). A trial first looks in MLflow
for a FINISHED run with its sweep id and trial key and reports that instead of running again, so a
trial that Ray re-runs after a crash is not duplicated: every (config, seed) ends with exactly one
FINISHED run. A trial that raises is marked FAILED with its ``failure_reason``, the others go on,
and the summary lists it.
"""

from __future__ import annotations

import contextlib
import difflib
import fcntl
import hashlib
import itertools
import json
import logging
import os
import re
import secrets
import sys
import tempfile
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from spot import SpotError
from spot import config as config_lib

SWEEP_KEYS = ("name", "base", "grid", "zip", "seeds", "seed_mode", "resources", "max_concurrent", "table", "smoke")
TABLES = (1, 2, 3, 4, 7, 8)
SMOKE_KEYS = ("base", "grid", "zip", "seeds", "max_concurrent", "resources")
SEED_MODES = ("trials", "vmap")
RESOURCE_KEYS = ("cpu", "gpu")
# Set by the sweep itself: seeds come from `seeds:`, the tracking store and experiment from the launch.
RESERVED_KEYS = ("seed", "tracking.uri", "tracking.experiment")
DEFAULT_STORAGE = Path("spot_runs") / "ray"
RUN_METRICS = ("eval/score_final", "eval/score_best", "time/total_s")

RunFn = Callable[..., dict[str, Any]]
Report = Callable[[dict[str, Any]], None]


# --------------------------------------------------------------------------- file format
@dataclass(frozen=True)
class Trial:
    """One Ray trial: a config (base + axis values) and the seeds it runs (one, or all with vmap)."""

    axes: dict[str, Any]
    overrides: dict[str, Any]
    seeds: tuple[int, ...]

    @property
    def label(self) -> str:
        return " ".join(f"{k}={_tag_value(v)}" for k, v in self.axes.items()) or "(base)"

    def to_config(self) -> dict[str, Any]:
        """The Ray trial config: all a trial needs to rebuild its run configs."""
        return {"overrides": dict(self.overrides), "axes": dict(self.axes), "seeds": list(self.seeds)}


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
    """Paper table printed (ours beside the paper's) when the launch ends; see spot.tables."""

    @property
    def experiment(self) -> str:
        """MLflow experiment name: the sweep name, with ``-smoke`` for smoke launches."""
        return f"{self.name}-smoke" if self.smoke else self.name

    @property
    def axis_keys(self) -> tuple[str, ...]:
        return (*self.grid, *self.zip)

    def configs(self) -> list[dict[str, Any]]:
        """The axis values of every config: grid (first axis slowest) x zip rows."""
        grid_rows = [dict(zip(self.grid, combo, strict=True)) for combo in itertools.product(*self.grid.values())]
        n_zip = len(next(iter(self.zip.values()))) if self.zip else 1
        zip_rows = [{k: v[i] for k, v in self.zip.items()} for i in range(n_zip)]
        return [{**g, **z} for g in grid_rows for z in zip_rows]

    def trials(self) -> list[Trial]:
        """Expand configs x seeds. Seeds vary slowest, so an interrupted sweep has whole seed columns."""
        configs = self.configs()
        if self.seed_mode == "vmap":
            return [Trial(c, {**self.base, **c}, self.seeds) for c in configs]
        return [Trial(c, {**self.base, **c}, (s,)) for s in self.seeds for c in configs]

    def runs(self) -> list[tuple[Trial, int]]:
        """Every (trial, seed) pair: one MLflow run each."""
        return [(t, s) for t in self.trials() for s in t.seeds]

    def spec_hash(self) -> str:
        """Identifies the expanded trial list; a resumed launch must expand to the same list."""
        spec = {"trials": [t.to_config() for t in self.trials()], "resources": self.resources}
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]


def _err(where: str, key: str, msg: str) -> SpotError:
    return SpotError(f"{where}: '{key}': {msg}")


def _check_known(data: dict[str, Any], allowed: tuple[str, ...], where: str, prefix: str) -> None:
    for key in data:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=2, cutoff=0.5)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise _err(where, f"{prefix}{key}", f"unknown key{hint} (expected {', '.join(allowed)})")


def _flatten(data: Any, where: str, section: str, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        raise _err(where, section, f"expected a mapping, got {type(data).__name__}")
    flat: dict[str, Any] = {}
    for k, v in data.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten(v, where, section, key + "."))
        else:
            flat[key] = v
    return flat


def _config_keys(flat: dict[str, Any], where: str, section: str) -> dict[str, Any]:
    keys = config_lib.valid_keys()
    for key in flat:
        if key in RESERVED_KEYS:
            what = "give seeds in 'seeds:'" if key == "seed" else "set by the sweep (name: / --tracking-uri)"
            raise _err(where, f"{section}.{key}", f"may not be set here: {what}")
        if key not in keys:
            close = difflib.get_close_matches(key, keys, n=3, cutoff=0.5)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise _err(where, f"{section}.{key}", f"unknown config key{hint} (see `spot config keys`)")
    return flat


def _axes(data: Any, where: str, section: str) -> dict[str, list[Any]]:
    """Axes of a grid or zip block: dotted config keys -> non-empty lists (a grid's without repeats)."""
    axes = _config_keys(_flatten(data, where, section), where, section)
    for key, values in axes.items():
        if not isinstance(values, list) or not values:
            raise _err(where, f"{section}.{key}", f"expected a non-empty list of values, got {values!r}")
        seen = [json.dumps(v, sort_keys=True) for v in values]
        if section.endswith("grid") and len(set(seen)) != len(seen):
            raise _err(where, f"{section}.{key}", f"repeats a value: {values!r}")
    return axes


def _replace_axes(axes: dict[str, list[Any]], new: dict[str, list[Any]], where: str, section: str) -> dict[str, list[Any]]:
    for key in new:
        if key not in axes:
            raise _err(where, f"smoke.{section}.{key}", f"is not an axis of '{section}' (axes: {', '.join(axes) or 'none'})")
    return {k: new.get(k, v) for k, v in axes.items()}


def _seeds(value: Any, where: str, key: str) -> tuple[int, ...]:
    if (not isinstance(value, list) or not value
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value)):
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
        if not isinstance(v, (int, float)) or isinstance(v, bool) or v < 0:
            raise _err(where, f"resources.{key}", f"expected a non-negative number, got {v!r}")
        out[key] = float(v)
    if out["cpu"] <= 0:
        raise _err(where, "resources.cpu", "must be > 0")
    if out["gpu"] > 1 and not out["gpu"].is_integer():
        raise _err(where, "resources.gpu", f"fractions are only for sharing one GPU (<= 1), got {out['gpu']}")
    return out


def _check_trial(trial: Trial, where: str) -> None:
    """Resolve the trial's config (and check its dataset name) or raise naming the trial."""
    from spot.data import registry

    try:
        cfg = config_lib.resolve(trial.overrides, {"seed": trial.seeds[0]})
        name = cfg.data.name
        if cfg.data.source == "file" and not Path(name).exists():
            raise SpotError(f"data.source=file but data file '{name}' does not exist")
        if cfg.data.source != "file" and not Path(name).exists():
            registry.entry(name)
    except SpotError as e:
        raise SpotError(f"{where}: trial {trial.label}: {e}") from None


def prebuild_datasets(sweep: Sweep) -> list[Path]:
    """Build every registry dataset the sweep's runs need, here on the driver, before trials start.

    A build uses all the driver's cores, where inside a trial it would be pinned to the trial's
    CPUs while the other trials wait on its lock. Files given as paths are left alone. On a
    cluster whose nodes do not share ``$SPOT_DATA_DIR`` the trials still build what they miss.
    """
    from spot.data import registry

    wanted = []
    for trial, seed in sweep.runs():
        cfg = config_lib.resolve(trial.overrides, {"seed": seed})
        key = (cfg.data.name, cfg.data.size, cfg.data.build_seed)
        if cfg.data.source != "file" and not Path(cfg.data.name).exists() and key not in wanted:
            wanted.append(key)
    paths = []
    for name, size, seed in wanted:
        print(f"dataset {name} (size {size}, seed {seed}): building if not cached", flush=True)
        paths.append(registry.build(name, size, seed))
    return paths


def load(path: str | Path, *, smoke: bool = False) -> Sweep:
    """Read and validate a sweep file; with ``smoke`` apply its ``smoke:`` block.

    Raises SpotError naming the file and key for format errors, and the trial's axis values for a
    config that does not resolve.
    """
    path = Path(path)
    where = f"sweep file '{path}'"
    if not path.is_file():
        raise SpotError(f"{where} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SpotError(f"{where}: not valid YAML ({e})") from None
    if not isinstance(data, dict):
        raise SpotError(f"{where}: expected a mapping with keys {', '.join(SWEEP_KEYS)}")
    _check_known(data, SWEEP_KEYS, where, "")
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
        raise _err(where, "name", f"expected letters, digits, '_', '.', '-', got {name!r}")
    base = _config_keys(_flatten(data.get("base", {}), where, "base"), where, "base")
    grid = _axes(data.get("grid", {}), where, "grid")
    zipped = _axes(data.get("zip", {}), where, "zip")
    seeds = _seeds(data.get("seeds", [0]), where, "seeds")
    seed_mode = data.get("seed_mode", "trials")
    if seed_mode not in SEED_MODES:
        raise _err(where, "seed_mode", f"expected one of {', '.join(SEED_MODES)}, got {seed_mode!r}")
    resources = _resources(data.get("resources", {}), where)
    max_concurrent = _max_concurrent(data.get("max_concurrent"), where, "max_concurrent")

    block = data.get("smoke", {})
    if not isinstance(block, dict):
        raise _err(where, "smoke", f"expected a mapping, got {type(block).__name__}")
    _check_known(block, SMOKE_KEYS, where, "smoke.")
    smoke_base = _config_keys(_flatten(block.get("base", {}), where, "smoke.base"), where, "smoke.base")
    smoke_grid = _replace_axes(grid, _axes(block.get("grid", {}), where, "smoke.grid"), where, "grid")
    smoke_zip = _replace_axes(zipped, _axes(block.get("zip", {}), where, "smoke.zip"), where, "zip")
    smoke_seeds = _seeds(block["seeds"], where, "smoke.seeds") if "seeds" in block else seeds
    smoke_mc = _max_concurrent(block.get("max_concurrent", max_concurrent), where, "smoke.max_concurrent")
    if smoke:
        if "smoke" not in data:
            raise SpotError(f"{where}: --smoke needs a 'smoke:' block (see docs/sweeps.md)")
        base, grid, zipped = {**base, **smoke_base}, smoke_grid, smoke_zip
        seeds, max_concurrent = smoke_seeds, smoke_mc
        # Smoke runs are tiny CPU checks: no GPU unless the smoke block asks for one.
        resources = (_resources(block["resources"], f"{where} smoke") if "resources" in block
                     else {**resources, "gpu": 0.0})

    lengths = {k: len(v) for k, v in zipped.items()}
    if len(set(lengths.values())) > 1:
        raise _err(where, "zip", f"paired axes need lists of equal length, got {lengths}")
    for key in grid:
        if key in zipped:
            raise _err(where, f"zip.{key}", "is also a grid axis")
    for key in (*grid, *zipped):
        if key in base:
            raise _err(where, f"base.{key}", "is also an axis; give it in one place")

    table = data.get("table")
    if table is not None and table not in TABLES:
        raise _err(where, "table", f"expected one of {', '.join(map(str, TABLES))}, got {table!r}")
    sweep = Sweep(path=path, name=name, smoke=smoke, base=base, grid=grid, zip=zipped, seeds=seeds,
                  seed_mode=seed_mode, resources=resources, max_concurrent=max_concurrent, table=table)
    seen: set[str] = set()
    for axes in sweep.configs():
        trial = Trial(axes, {**base, **axes}, seeds)
        key = config_key(trial.overrides)
        if key in seen:
            raise SpotError(f"{where}: trial {trial.label} occurs twice (repeated zip row)")
        seen.add(key)
        _check_trial(trial, where)
    return sweep


# --------------------------------------------------------------------------- keys and tags
def _canonical(obj: dict[str, Any]) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=list)


def config_key(overrides: dict[str, Any]) -> str:
    """Hash of a trial's override dict (without the seed): the same for all its seeds."""
    return hashlib.sha256(_canonical(overrides).encode()).hexdigest()[:16]


def run_key(overrides: dict[str, Any], seed: int) -> str:
    """Hash of the override dict with the seed: identifies one (config, seed) run of a sweep."""
    return hashlib.sha256(_canonical({**overrides, "seed": seed}).encode()).hexdigest()[:16]


def _tag_value(value: Any) -> str:
    return json.dumps(value) if isinstance(value, (list, tuple, dict)) else str(value)


@dataclass(frozen=True)
class SweepContext:
    """What every trial of one launch needs besides its own overrides (small; passed through Ray)."""

    sweep_id: str
    sweep_name: str
    experiment_name: str
    experiment_id: str
    parent_run_id: str
    tracking_uri: str
    axis_keys: tuple[str, ...]


# --------------------------------------------------------------------------- one trial
@contextlib.contextmanager
def cpu_slots(n: int) -> Iterator[list[int]]:
    """Claim ``n`` CPUs of this node for the trial and pin the whole process to them.

    Slots are ``flock``s on files in ``$TMPDIR/spot-cpu-slots`` (released at the end of the block
    or when the process dies, however it dies), so concurrent trials on one node get disjoint
    CPUs. XLA sizes its CPU thread pools from the affinity mask, which makes this the thread-count
    setting that works (an ``intra_op_parallelism_threads`` token in XLA_FLAGS is ignored by
    jaxlib 0.10). If ``n`` slots are not free (fractional CPUs, a trial as large as the node),
    nothing is claimed or pinned. Yields the pinned CPUs (empty if none).
    """
    allowed = sorted(os.sched_getaffinity(0))
    folder = Path(tempfile.gettempdir()) / "spot-cpu-slots"
    folder.mkdir(exist_ok=True)
    held: list[tuple[int, Any]] = []
    try:
        for cpu in allowed:
            if len(held) == n:
                break
            f = open(folder / f"cpu{cpu}", "a")  # held (locked) for the trial's lifetime
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                f.close()
                continue
            held.append((cpu, f))
        if len(held) < n or n >= len(allowed):
            for _, f in held:
                f.close()
            held = []
        cpus = [c for c, _ in held]
        if cpus:
            for tid in os.listdir("/proc/self/task"):
                with contextlib.suppress(OSError):
                    os.sched_setaffinity(int(tid), cpus)
        yield cpus
    finally:
        for _, f in held:
            f.close()


def configure_process(cpus: int, gpus: float) -> None:
    """XLA and JAX settings for a trial's share of the node; must run before jax is imported.

    One CPU: ``--xla_cpu_multi_thread_eigen=false`` (jax #4290). A fractional GPU: memory fraction
    ``0.9 * gpu`` (JAX preallocates 75% otherwise, so two trials on one GPU would run out).
    ``JAX_COMPILATION_CACHE_DIR`` defaults to a node-local cache shared by the node's trials.
    """
    if "jax" in sys.modules:
        warnings.warn("jax was imported before the trial configured XLA; XLA_FLAGS and the GPU memory "
                      "fraction of this trial do not apply", RuntimeWarning, stacklevel=2)
    flags = os.environ.get("XLA_FLAGS", "")
    if cpus <= 1 and "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_multi_thread_eigen=false".strip()
    if 0 < gpus < 1:
        fraction = f"{0.9 * gpus:.3f}"
        os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", fraction)
        os.environ.setdefault("XLA_CLIENT_MEM_FRACTION", fraction)
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path.home() / ".cache" / "spot" / "jax"))


def _search_all(client: Any, experiment_id: str, filter_string: str) -> list[Any]:
    runs: list[Any] = []
    token = None
    while True:
        page = client.search_runs([experiment_id], filter_string, max_results=1000, page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            return runs


def _finished_run(client: Any, ctx: SweepContext, key: str) -> Any | None:
    found = client.search_runs(
        [ctx.experiment_id],
        f"tags.sweep_id = '{ctx.sweep_id}' and tags.trial_key = '{key}' and attributes.status = 'FINISHED'",
        max_results=1)
    return found[0] if found else None


def _record_failure(client: Any, ctx: SweepContext, cfg: config_lib.ExperimentConfig,
                    tags: dict[str, str], error: BaseException) -> None:
    """Make sure a failed attempt has a FAILED run (the pipeline makes one unless it failed before)."""
    from mlflow.entities import Param

    from spot import tracking

    if client.search_runs([ctx.experiment_id], f"tags.attempt = '{tags['attempt']}'", max_results=1):
        return
    all_tags = tracking.run_tags(cfg, {"name": cfg.data.name}, tags)
    all_tags.update({"mlflow.parentRunId": ctx.parent_run_id,
                     "failure_reason": f"{type(error).__name__}: {error}"[:4000]})
    run = client.create_run(ctx.experiment_id, run_name=f"{cfg.method}-{cfg.data.name}-s{cfg.seed}", tags=all_tags)
    params = [Param(k, str(list(v) if isinstance(v, tuple) else v)) for k, v in config_lib.to_flat(cfg).items()]
    client.log_batch(run.info.run_id, params=params)
    client.set_terminated(run.info.run_id, "FAILED")


def run_trial(overrides: dict[str, Any], seeds: list[int] | tuple[int, ...], ctx: SweepContext, *,
              trial_id: str, report: Report, run_fn: RunFn | None = None) -> list[dict[str, Any]]:
    """Run (or find already finished) each seed of one trial; report scores; raise if any seed failed.

    Args:
      overrides: the trial's flat config overrides (base + axis values), without the seed.
      seeds: the seeds to run, one after another (``seed_mode: vmap`` gives several).
      ctx: the launch's sweep context (MLflow experiment, parent run, tracking URI).
      trial_id: Ray's trial id, logged as the ``trial_id`` tag.
      report: called with intermediate (``score``) and final (``score_final``) metrics.
      run_fn: :func:`spot.pipeline.run` unless given (tests pass another).

    Returns:
      One final-metrics dict per seed.
    """
    from mlflow.tracking import MlflowClient

    if run_fn is None:
        from spot import pipeline

        run_fn = pipeline.run
    os.environ["MLFLOW_TRACKING_URI"] = ctx.tracking_uri
    client = MlflowClient(ctx.tracking_uri)
    axis_tags = {f"axis.{k}": _tag_value(overrides[k]) for k in ctx.axis_keys}
    finals: list[dict[str, Any]] = []
    failures: list[tuple[int, BaseException]] = []
    for seed in seeds:
        key = run_key(overrides, seed)
        done = _finished_run(client, ctx, key)
        if done is not None:
            m = done.data.metrics
            final = {"seed": seed, "run_id": done.info.run_id, "skipped": 1,
                     "score_final": m.get("eval/score_final"), "score_best": m.get("eval/score_best")}
            report(final)
            finals.append(final)
            continue
        cfg = config_lib.resolve(overrides, {"seed": seed, "tracking.experiment": ctx.experiment_name})
        tags = {"sweep_id": ctx.sweep_id, "sweep_name": ctx.sweep_name, "trial_id": trial_id,
                "trial_key": key, "config_key": config_key(overrides), "attempt": uuid.uuid4().hex, **axis_tags}

        def on_eval(m: dict[str, float], seed: int = seed) -> None:
            report({"seed": seed, "score": m["score"], "iql_step": m["step"]})

        try:
            out = run_fn(cfg, progress=False, parent_run_id=ctx.parent_run_id, extra_tags=tags, on_eval=on_eval)
        except Exception as e:  # noqa: BLE001 - recorded, reported by Ray after the other seeds ran
            _record_failure(client, ctx, cfg, tags, e)
            failures.append((seed, e))
            continue
        final = {"seed": seed, "run_id": out["run_id"], "skipped": 0, "score_final": out["eval/score_final"],
                 "score_best": out["eval/score_best"], "run_time_s": out.get("time/total_s")}
        report(final)
        finals.append(final)
    if len(failures) == 1 and len(seeds) == 1:
        raise failures[0][1]
    if failures:
        raise RuntimeError("; ".join(f"seed {s}: {type(e).__name__}: {e}" for s, e in failures))
    return finals


def _trainable(config: dict[str, Any], ctx: SweepContext, run_fn: RunFn | None = None) -> None:
    """The Ray Tune function trainable: one trial = ``config['trial']`` (:meth:`Trial.to_config`).

    The per-trial process settings are made here, first: Tune starts every trial in a fresh actor
    process (``reuse_actors=False``) and nothing before this line imports jax.
    """
    from ray import tune

    context = tune.get_context()
    need = context.get_trial_resources().required_resources
    cpus = max(1, int(need.get("CPU", 1)))
    with cpu_slots(cpus):
        configure_process(cpus, float(need.get("GPU", 0.0)))
        run_trial(config["trial"]["overrides"], config["trial"]["seeds"], ctx, trial_id=context.get_trial_id(),
                  report=tune.report, run_fn=run_fn)


def _trial_dirname(trial: Any) -> str:
    return str(trial.trial_id)


# --------------------------------------------------------------------------- driver
@dataclass(frozen=True)
class Row:
    """One (config, seed) line of the summary."""

    axes: dict[str, Any]
    seed: int
    key: str
    status: str
    score_final: float | None
    reason: str
    run_id: str
    finished_runs: int


@dataclass(frozen=True)
class _Store:
    uri: str
    how_to_open: str
    wait_ready: Callable[[], None]


@contextlib.contextmanager
def _tracking_store(uri: str | None, root: Path) -> Iterator[_Store]:
    """The tracking store of a launch; a SQLite store is served by a loopback server.

    The server starts here but is only waited for by ``wait_ready()``, so that Ray can start
    meanwhile.
    """
    from spot import mlflow_server

    uri = uri or os.environ.get("MLFLOW_TRACKING_URI", "")
    if uri.startswith("file:") or (uri and "://" not in uri and not uri.startswith("sqlite:")):
        raise SpotError(f"tracking URI '{uri}': file stores cannot take concurrent trials; give "
                        "sqlite:///path.db (spot serves it) or http(s)://host:port of a tracking server")
    if uri and not uri.startswith("sqlite:"):
        yield _Store(uri, f"MLflow: {uri}", lambda: None)
        return
    db = Path(uri[len("sqlite:///"):]) if uri else root / "mlflow.db"
    db.parent.mkdir(parents=True, exist_ok=True)
    backend = mlflow_server.sqlite_uri(db)
    artifacts = db.resolve().parent / "artifacts"
    server = mlflow_server.MlflowServer(backend, artifacts, log_path=db.resolve().parent / "mlflow-server.log")
    print(f"starting mlflow server on {server.uri} (store {backend})", flush=True)
    server.start(wait=False)
    try:
        yield _Store(server.uri, f"open the runs with: {mlflow_server.ui_command(backend, artifacts)}",
                     server.wait_ready)
    finally:
        server.stop()


def _init_ray(address: str | None) -> bool:
    """Start local Ray (all CPUs, no dashboard) or connect to ``address``; False if already up."""
    import ray

    if ray.is_initialized():
        return False
    env_vars = {"RAY_CHDIR_TO_TRIAL_DIR": "0",  # trials keep the driver's working dir (relative paths)
                "MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT": "true"}  # no "View run" lines in the progress view
    env_vars.update({k: os.environ[k] for k in ("SPOT_DATA_DIR", "SPOT_CACHE_DIR") if k in os.environ})
    if address:
        ray.init(address=address, runtime_env={"env_vars": env_vars}, logging_level=logging.WARNING)
    else:
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # loopback-only local cluster, no token
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, runtime_env={"env_vars": env_vars},
                 logging_level=logging.WARNING)
    return True


def _close_orphans(client: Any, experiment_id: str, sweep_id: str, parent_run_id: str, reason: str) -> int:
    """Mark this sweep's child runs that are still RUNNING (their process is gone) as KILLED."""
    orphans = [r for r in _search_all(client, experiment_id,
                                      f"tags.sweep_id = '{sweep_id}' and attributes.status = 'RUNNING'")
               if r.info.run_id != parent_run_id]
    for r in orphans:
        client.set_tag(r.info.run_id, "failure_reason", reason)
        client.set_terminated(r.info.run_id, "KILLED")
    return len(orphans)


def _check_gpus(sweep: Sweep) -> None:
    """Stop before any run is opened if trials ask for a GPU the Ray cluster does not have
    (Tune would otherwise wait for it forever)."""
    import ray

    if sweep.resources["gpu"] > 0 and float(ray.cluster_resources().get("GPU", 0.0)) == 0:
        raise SpotError(
            f"sweep file '{sweep.path}': resources.gpu = {sweep.resources['gpu']:g} per trial, but the Ray "
            "cluster has no GPU; set resources: {gpu: 0} (--smoke uses no GPU unless its block asks), or "
            "give --address of a cluster with GPUs")


def _fit(sweep: Sweep, ctx: SweepContext, exp_dir: Path, *, resume: bool, retry_errored: bool,
         max_concurrent: int | None, run_fn: RunFn | None) -> tuple[dict[str, str], bool]:
    """Run (or restore) the Tune experiment.

    Returns ``{run_key: error}`` for each seed of errored trials, and whether the launch was
    interrupted (Ctrl-C: Tune stops and returns with trials left unfinished).
    """
    from ray import tune

    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # use the CLIReporter below
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
    trials = sweep.trials()
    trainable = tune.with_resources(tune.with_parameters(_trainable, ctx=ctx, run_fn=run_fn),
                                    {"cpu": sweep.resources["cpu"], "gpu": sweep.resources["gpu"]})
    param_space = {"trial": tune.grid_search([t.to_config() for t in trials])}
    if resume and tune.Tuner.can_restore(str(exp_dir)):
        tuner = tune.Tuner.restore(str(exp_dir), trainable=trainable, param_space=param_space,
                                   resume_unfinished=True, resume_errored=False, restart_errored=retry_errored)
    else:
        reporter = tune.CLIReporter(
            parameter_columns={**{f"trial/axes/{k}": k for k in sweep.axis_keys}, "trial/seeds": "seeds"},
            metric_columns={"iql_step": "step", "score": "score", "score_final": "final", "seed": "seed"},
            max_report_frequency=30, sort_by_metric=False)
        tuner = tune.Tuner(
            trainable, param_space=param_space,
            tune_config=tune.TuneConfig(max_concurrent_trials=max_concurrent, reuse_actors=False,
                                        trial_dirname_creator=_trial_dirname),
            run_config=tune.RunConfig(name=exp_dir.name, storage_path=str(exp_dir.parent),
                                      progress_reporter=reporter, verbose=1,
                                      failure_config=tune.FailureConfig(max_failures=0, fail_fast=False)))
    tuner.fit()
    errors: dict[str, str] = {}
    # ExperimentAnalysis, not the ResultGrid: a Result of a restored trial that never reported lacks
    # its config. Its warnings about trials that never started ("no metrics") are noise here.
    quiet = logging.getLogger("ray.tune.analysis.experiment_analysis")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        trials = tune.ExperimentAnalysis(str(exp_dir)).trials
    finally:
        quiet.setLevel(level)
    for trial in trials:
        error = (trial.get_pickled_error() or trial.get_error()) if trial.status == "ERROR" else None
        if error is not None:
            lines = [ln for ln in str(error).splitlines() if ln.strip()]
            for seed in trial.config["trial"]["seeds"]:
                errors[run_key(trial.config["trial"]["overrides"], seed)] = lines[-1] if lines else repr(error)
    return errors, any(t.status not in ("TERMINATED", "ERROR") for t in trials)


def summarize(sweep: Sweep, client: Any, experiment_id: str, sweep_id: str,
              ray_errors: dict[str, str] | None = None) -> list[Row]:
    """One :class:`Row` per (config, seed) from the sweep's MLflow runs (and Ray's trial errors)."""
    by_key: dict[str, list[Any]] = {}
    for r in _search_all(client, experiment_id, f"tags.sweep_id = '{sweep_id}'"):
        if "trial_key" in r.data.tags:
            by_key.setdefault(r.data.tags["trial_key"], []).append(r)
    rows = []
    for trial, seed in sweep.runs():
        key = run_key(trial.overrides, seed)
        runs = by_key.get(key, [])
        finished = [r for r in runs if r.info.status == "FINISHED"]
        if finished:
            r = finished[0]
            rows.append(Row(trial.axes, seed, key, "FINISHED", r.data.metrics.get("eval/score_final"), "",
                            r.info.run_id, len(finished)))
        elif runs:
            r = max(runs, key=lambda r: r.info.start_time or 0)
            rows.append(Row(trial.axes, seed, key, r.info.status, None, r.data.tags.get("failure_reason", ""),
                            r.info.run_id, 0))
        else:
            error = (ray_errors or {}).get(key)
            rows.append(Row(trial.axes, seed, key, "ERROR" if error else "NOT RUN", None, error or "", "", 0))
    return rows


def format_summary(rows: list[Row], axis_keys: tuple[str, ...], width: int = 70) -> str:
    """A plain-text table: axis values, seed, score_final, status, failure reason."""
    header = [*axis_keys, "seed", "score_final", "status", "reason"]
    body = [[*(_tag_value(r.axes[k]) for k in axis_keys), str(r.seed),
             "" if r.score_final is None else f"{r.score_final:.2f}", r.status,
             (r.reason.splitlines() or [""])[0][:width]] for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
    lines = ["  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip()
             for line in (header, *body)]
    return "\n".join([lines[0], "  ".join("-" * w for w in widths), *lines[1:]])


def _state_path(storage: Path, sweep: Sweep) -> Path:
    return storage / f"{sweep.experiment}.json"


def run_sweep(path: str | Path, *, smoke: bool = False, resume: bool = False, retry_errored: bool = False,
              address: str | None = None, max_concurrent: int | None = None,
              tracking_uri: str | None = None, storage: str | Path = DEFAULT_STORAGE,
              workdir: str | Path | None = None, run_fn: RunFn | None = None) -> list[Row]:
    """Run a sweep file end to end (``spot sweep``); return the summary rows.

    Args:
      path: sweep YAML file.
      smoke: apply the file's ``smoke:`` block (experiment ``<name>-smoke``).
      resume: continue the last launch of this sweep (same sweep id, same parent run).
      retry_errored: with ``resume``, run errored trials again (their FAILED runs stay).
      address: Ray cluster address; default: a local Ray with all CPUs.
      max_concurrent: trials at once (default: the file's ``max_concurrent``, else as resources allow).
      tracking_uri: MLflow URI; default ``$MLFLOW_TRACKING_URI``, else a loopback server on
        ``<workdir>/spot_runs/mlflow.db``. A ``sqlite:`` URI is served the same way.
      storage: Ray Tune storage folder (the launch's experiment is ``<storage>/<sweep id>``).
      workdir: where ``spot_runs/`` goes (default: the current directory).
      run_fn: the per-seed run function (default :func:`spot.pipeline.run`).
    """
    from mlflow.entities import Metric
    from mlflow.tracking import MlflowClient

    from spot import tracking

    if retry_errored and not resume:
        raise SpotError("--retry-errored goes with --resume")
    sweep = load(path, smoke=smoke)
    root = Path(workdir or Path.cwd()).resolve() / "spot_runs"
    storage = Path(storage).resolve()
    state_file = _state_path(storage, sweep)
    if resume:
        if not state_file.is_file():
            raise SpotError(f"nothing to resume: no launch of sweep '{sweep.experiment}' under {storage}; "
                            "start it without --resume")
        state = json.loads(state_file.read_text())
        if state["spec_hash"] != sweep.spec_hash():
            raise SpotError(f"sweep file '{path}' expands to other trials than the launch {state['sweep_id']} "
                            "being resumed; Ray cannot change a sweep's trials: start a new launch without --resume")
        if max_concurrent is not None:
            print("note: --max-concurrent is ignored on --resume (the restored launch keeps its setting)")
    else:
        state = {"sweep_id": f"{sweep.experiment}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(2)}",
                 "spec_hash": sweep.spec_hash(), "file": str(Path(path).resolve())}
    sweep_id = state["sweep_id"]
    runs = sweep.runs()
    print(f"sweep '{sweep.experiment}' ({sweep_id}): {len(sweep.trials())} trials, {len(runs)} runs "
          f"(seed_mode {sweep.seed_mode}, {sweep.resources['cpu']:g} CPU / {sweep.resources['gpu']:g} GPU per trial)",
          flush=True)
    if address and not tracking_uri and not os.environ.get("MLFLOW_TRACKING_URI"):
        print("note: trials on other nodes cannot reach the loopback MLflow server; pass "
              "--tracking-uri http://<host>:<port> of a server every node can reach", flush=True)

    if run_fn is None:
        prebuild_datasets(sweep)
    with _tracking_store(tracking_uri, root) as store:
        started_ray = _init_ray(address)
        parent_id = None
        crashed = True
        try:
            _check_gpus(sweep)
            store.wait_ready()
            client = MlflowClient(store.uri)
            exp_id = tracking.experiment_id(sweep.experiment, store.uri)
            parent_id = _open_parent(client, exp_id, sweep, state, resume=resume)
            if not resume:
                storage.mkdir(parents=True, exist_ok=True)
                state_file.write_text(json.dumps(state, indent=2))
            ctx = SweepContext(sweep_id, sweep.name, sweep.experiment, exp_id, parent_id, store.uri, sweep.axis_keys)
            print(f"MLflow experiment '{sweep.experiment}' (id {exp_id}) at {store.uri}; parent run {parent_id}\n"
                  f"Ray storage {storage / sweep_id}; if interrupted: spot sweep {path}"
                  f"{' --smoke' if smoke else ''} --resume", flush=True)
            errors, interrupted = _fit(sweep, ctx, storage / sweep_id, resume=resume, retry_errored=retry_errored,
                                       max_concurrent=max_concurrent or sweep.max_concurrent, run_fn=run_fn)
            crashed = False
        finally:
            if started_ray:
                import ray

                ray.shutdown()  # every trial process is gone after this: RUNNING runs are orphans
            if crashed and parent_id is not None:
                _close_orphans(client, exp_id, sweep_id, parent_id, "launch interrupted")
                client.set_terminated(parent_id, "KILLED")
        _close_orphans(client, exp_id, sweep_id, parent_id, "launch interrupted" if interrupted
                       else "trial process ended without closing its run")
        rows = summarize(sweep, client, exp_id, sweep_id, errors)
        table = format_summary(rows, sweep.axis_keys)
        n_done = sum(r.status == "FINISHED" for r in rows)
        now = int(time.time() * 1000)
        client.log_batch(parent_id, metrics=[Metric(k, v, now, 0) for k, v in (
            ("sweep/runs_total", len(rows)), ("sweep/runs_finished", n_done),
            ("sweep/runs_failed", len(rows) - n_done))])
        client.log_text(parent_id, table + "\n", "summary.txt")
        client.set_terminated(parent_id, "KILLED" if interrupted else "FINISHED" if n_done == len(rows) else "FAILED")
        paper_table = _paper_table(sweep, store.uri, sweep_id) if sweep.table and n_done else ""
    resume_hint = "" if n_done == len(rows) else (
        f"\nto run what is missing: spot sweep {path}{' --smoke' if smoke else ''} --resume "
        "(add --retry-errored to run failed trials again)")
    print(f"\n{table}\n\n{n_done}/{len(rows)} runs finished. Experiment '{sweep.experiment}', "
          f"filter: tags.sweep_id = '{sweep_id}'\n{store.how_to_open}{resume_hint}", flush=True)
    if paper_table:
        print(f"\n{paper_table}", flush=True)
    return rows


def _paper_table(sweep: Sweep, uri: str, sweep_id: str) -> str:
    """The sweep's paper table (ours beside the paper's) from this launch's finished runs."""
    from spot import tables

    runs = tables.load_runs(uri, [sweep.experiment], sweep_id=sweep_id)
    try:
        return tables.format_table(tables.build_table(runs, sweep.table), "md")
    except SpotError as e:  # e.g. a sweep whose runs do not form that table
        return f"(no Table {sweep.table}: {e})"


def _open_parent(client: Any, experiment_id: str, sweep: Sweep, state: dict[str, Any], *, resume: bool) -> str:
    """Create the launch's parent run (recorded in ``state``), or reopen it on resume."""
    from spot import tracking

    if resume:
        parent_id = state["parent_run_id"]
        n = _close_orphans(client, experiment_id, state["sweep_id"], parent_id,
                           "process ended during an interrupted launch")
        print(f"resuming {state['sweep_id']}: {n} run(s) left RUNNING by the interrupted launch marked KILLED",
              flush=True)
        client.update_run(parent_id, status="RUNNING")
        client.set_tag(parent_id, "resumed_at", time.strftime("%Y-%m-%d %H:%M:%S"))
        return parent_id
    parent = client.create_run(experiment_id, run_name=f"sweep {state['sweep_id']}", tags={
        "sweep_id": state["sweep_id"], "sweep_name": sweep.name, "spot.role": "sweep", "smoke": str(sweep.smoke),
        "sweep_file": str(sweep.path.resolve()), "git_commit": tracking.git_commit()})
    parent_id = parent.info.run_id
    client.log_text(parent_id, sweep.path.read_text(), "sweep.yaml")
    client.log_dict(parent_id, [t.to_config() for t in sweep.trials()], "trials.json")
    client.log_batch(parent_id, params=_parent_params(sweep))
    state["parent_run_id"] = parent_id
    return parent_id


def _parent_params(sweep: Sweep) -> list[Any]:
    from mlflow.entities import Param

    params = {"sweep.trials": len(sweep.trials()), "sweep.runs": len(sweep.runs()),
              "sweep.seeds": list(sweep.seeds), "sweep.seed_mode": sweep.seed_mode,
              "sweep.cpu": sweep.resources["cpu"], "sweep.gpu": sweep.resources["gpu"],
              **{f"grid.{k}": v for k, v in sweep.grid.items()}, **{f"zip.{k}": v for k, v in sweep.zip.items()},
              **{f"base.{k}": v for k, v in sweep.base.items()}}
    return [Param(k, _tag_value(v)[:6000]) for k, v in params.items()]
