"""One trial, inside its Ray worker process: CPU slots and XLA settings, then each seed's run.

:func:`_trainable` is the Ray Tune function trainable. It claims the trial's CPUs, its threads
following the free ones (:func:`spot.sweep.cpus.trial_cpus`), makes spot's process settings
(:func:`spot.runtime.configure`) and sets XLA/JAX for the trial's share of the node
(:func:`configure_process`), before anything imports jax, and calls :func:`run_trial`, which
looks each seed up in MLflow (a FINISHED run with the sweep id and trial key is reported instead
of running again), runs the others with
:func:`spot.pipeline.run` one after another, or together with :func:`spot.run.multiseed.run` (IQL
vmapped over the seeds) for a ``seed_mode: vmap`` trial, and records a FAILED run for a seed that
failed before the pipeline opened its own. Nothing here imports jax at module level.

Tune reuses a trial's actor process for the next trial (``reuse_actors=True``: every trial of a
sweep asks for the same resources), so the imports, the XLA client, jit's in-memory caches and the
opened dataset carry over; the process settings are made once per process (:func:`_configure_once`).

Each trial is timed by phase (:mod:`spot.phases`: start-up, dataset, compile, train, evaluate,
tracking, other) and the breakdown is logged to every run the trial ran as ``time/trial_<phase>_s``,
``time/trial_wall_s``, ``time/trial_cpu_s`` (CPU seconds of the trial's process, all threads),
``time/trial_cpus`` (the CPUs it had, :func:`_cpus_had`) and the tags ``spot.trial_device`` (``jax.devices()``) and
``spot.trial_process`` (``new`` or ``reused``). ``spot sweep`` prints the totals at the end,
``spot bench sweep`` each trial's row (:func:`spot.sweep.summary.format_breakdown`).

A trial whose tracking server stops answering (its MLflow requests have deadlines,
:mod:`spot.tracking.limits`) ends with :class:`spot.tracking.TrackingUnreachable`, one line naming
the server and the request, instead of a FAILED run it could not record; ``--resume`` runs such a
trial again (it was cut off, not failed).
"""

from __future__ import annotations

import contextlib
import os
import resource
import sys
import time
import uuid
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from spot import config as config_lib
from spot.sweep.cpus import trial_cpus
from spot.sweep.reports import Reports, StoppedEarly, evaluated, mark_stopped
from spot.sweep.signals import quiet_ray_sigterm
from spot.sweep.spec import config_key, run_key, tag_value

RunFn = Callable[..., dict[str, Any]]
Report = Callable[[dict[str, Any]], None]


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
    fast_compile: bool = False  # the sweep file's fast_compile: SPOT_FAST_COMPILE=1 in the trial processes
    metric: str | None = None  # the metric of search:/scheduler: (reports without it are not sent to Tune)
    stopper: str = ""  # who stops trials early (ASHA, median stopping): named in a stopped run's failure_reason
    created_at: float = field(default_factory=time.time)  # when the driver set the launch up (start-up's origin)


def _cpus_had(share: Any, cpus: int, cpu_s: float, wall_s: float) -> float:
    """The CPUs a trial had, averaged over its time: its slots (and borrowed ones,
    :meth:`spot.sweep.cpus.Share.mean_cpus`); for a trial that held no slot and shared the node's
    cores with other trials as the OS scheduled them (a fraction of a CPU asked, or no slot free),
    the CPU seconds it used over its wall time: the node's cores are not all its own."""
    if share.shares_node(cpus):
        return cpu_s / max(wall_s, 1e-9)
    return share.mean_cpus()


# --------------------------------------------------------------------------- process setup
def configure_process(cpus: int, gpus: float) -> None:
    """XLA and JAX settings for a trial's share of the node; must run before jax is imported.

    One CPU: ``--xla_cpu_multi_thread_eigen=false`` (jax #4290). A fractional GPU: memory fraction
    ``0.9 * gpu`` (JAX preallocates 75% otherwise, so two trials on one GPU would run out).
    The persistent compilation cache the node's trials share is set by
    :func:`spot.runtime.configure`, called just before.
    """
    if "jax" in sys.modules:
        warnings.warn(
            "jax was imported before the trial configured XLA; XLA_FLAGS and the GPU memory "
            "fraction of this trial do not apply",
            RuntimeWarning,
            stacklevel=2,
        )
    flags = os.environ.get("XLA_FLAGS", "")
    if cpus <= 1 and "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_multi_thread_eigen=false".strip()
    if 0 < gpus < 1:
        fraction = f"{0.9 * gpus:.3f}"
        os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", fraction)
        os.environ.setdefault("XLA_CLIENT_MEM_FRACTION", fraction)


# --------------------------------------------------------------------------- the runs of a trial
def _finished(run: Any, seed: int) -> dict[str, Any]:
    m = run.data.metrics
    return {
        "seed": seed,
        "run_id": run.info.run_id,
        "skipped": 1,
        "score_final": m.get("eval/score_final"),
        "score_best": m.get("eval/score_best"),
    }


def _finished_metrics(run: Any) -> dict[str, float]:
    """What a search or scheduler reads of a run found FINISHED (a resumed launch reports it):
    its final score as ``eval/score`` and its reward model's held-out metrics."""
    m = run.data.metrics
    out = {k: m[k] for k in ("reward/best_eval_acc", "reward/best_eval_loss") if k in m}
    return {**out, "eval/score": m["eval/score_final"]} if "eval/score_final" in m else out


def _run_seed(
    client: Any,
    overrides: dict[str, Any],
    seed: int,
    ctx: SweepContext,
    tags: dict[str, str],
    report: Report,
    run_fn: RunFn,
) -> dict[str, Any]:
    """Run one seed with ``run_fn``; a failure is recorded as a FAILED run and raised."""

    cfg = config_lib.resolve(overrides, {"seed": seed, "tracking.experiment": ctx.experiment_name})
    try:
        out = run_fn(
            cfg, progress=False, parent_run_id=ctx.parent_run_id, extra_tags=tags, on_eval=evaluated(seed, report)
        )
    except StoppedEarly as stop:
        mark_stopped(client, ctx, [tags["attempt"]], stop)
        raise
    except Exception as e:
        _record_failure(client, ctx, cfg, tags, e, seed)
        raise
    return {
        "seed": seed,
        "run_id": out["run_id"],
        "skipped": 0,
        "score_final": out["eval/score_final"],
        "score_best": out["eval/score_best"],
        "run_time_s": out.get("time/total_s"),
    }


def _record_failure(
    client: Any, ctx: SweepContext, cfg: config_lib.ExperimentConfig, tags: dict[str, str], error: Exception, seed: int
) -> None:
    """Record the failed attempt as a FAILED run (:func:`spot.tracking.record_failure`), unless the
    failure is that the tracking server did not answer: then there is nothing to record it in, and
    the trial ends with :class:`spot.tracking.TrackingUnreachable` (also if the server stops
    answering while the failure is recorded)."""
    from spot import tracking
    from spot.tracking import limits

    lost = limits.unreachable(error, ctx.tracking_uri, f"running seed {seed}")
    if lost is not None:
        raise lost from None
    with limits.waiting_on(ctx.tracking_uri, f"recording the failure of seed {seed}"):
        tracking.record_failure(client, ctx.experiment_id, cfg, tags, error, parent_run_id=ctx.parent_run_id)


def _seed_tags(overrides: dict[str, Any], key: str, ctx: SweepContext, trial_id: str) -> dict[str, str]:
    """A seed's run tags, bare names (MLflow's: ``spot.sweep_id``, ..., :mod:`spot.tracking.tagnames`)."""
    from spot.tracking.processes import process_tags

    return {
        "sweep_id": ctx.sweep_id,
        "sweep_name": ctx.sweep_name,
        "trial_id": trial_id,
        "trial_key": key,
        "config_key": config_key(overrides),
        "attempt": uuid.uuid4().hex,
        **{f"axis.{k}": tag_value(overrides[k]) for k in ctx.axis_keys},
        **process_tags(),  # this worker's host and pid: a later command closes the run if it dies
    }


def _run_vmapped(
    client: Any,
    overrides: dict[str, Any],
    pending: dict[int, dict[str, str]],
    ctx: SweepContext,
    report: Report,
    run_fn: Callable[..., list[dict[str, Any]]],
) -> list[dict[str, Any]]:
    """Run the ``pending`` seeds (seed -> tags) together with ``run_fn`` (:func:`spot.run.multiseed.run`);
    a failure is recorded as a FAILED run for each seed and raised."""

    seeds = list(pending)
    cfgs = [config_lib.resolve(overrides, {"seed": s, "tracking.experiment": ctx.experiment_name}) for s in seeds]
    try:
        outs = run_fn(
            cfgs,
            progress=False,
            parent_run_id=ctx.parent_run_id,
            extra_tags=[pending[s] for s in seeds],
            on_eval=[evaluated(s, report) for s in seeds],
        )
    except StoppedEarly as stop:
        mark_stopped(client, ctx, [pending[s]["attempt"] for s in seeds], stop)
        raise
    except Exception as e:
        for cfg, seed in zip(cfgs, seeds, strict=True):
            _record_failure(client, ctx, cfg, pending[seed], e, seed)
        raise
    return [
        {
            "seed": seed,
            "run_id": out["run_id"],
            "skipped": 0,
            "score_final": out["eval/score_final"],
            "score_best": out["eval/score_best"],
            "run_time_s": out.get("time/total_s"),
        }
        for seed, out in zip(seeds, outs, strict=True)
    ]


def _open_data(overrides: dict[str, Any], seed: int, ctx: SweepContext) -> None:
    """Open the trial's dataset (:func:`spot.pipeline.open_dataset`, kept open for this process's
    later runs) as the ``data`` phase; an error is left to the run, which records it."""
    from spot import phases, pipeline

    with phases.phase("data"), contextlib.suppress(Exception):
        pipeline.open_dataset(config_lib.resolve(overrides, {"seed": seed, "tracking.experiment": ctx.experiment_name}))


def run_trial(
    overrides: dict[str, Any],
    seeds: list[int] | tuple[int, ...],
    ctx: SweepContext,
    *,
    trial_id: str,
    report: Report,
    run_fn: RunFn | None = None,
    vmap: bool = False,
) -> list[dict[str, Any]]:
    """Run (or find already finished) each seed of one trial; report scores; raise if any seed failed.

    Args:
      overrides: the trial's flat config overrides (base + axis values), without the seed.
      seeds: the seeds to run (``seed_mode: sequential`` and ``vmap`` give several).
      ctx: the launch's sweep context (MLflow experiment, parent run, tracking URI).
      trial_id: Ray's trial id, logged as the ``trial_id`` tag.
      report: called with intermediate (``score``) and final (``score_final``) metrics.
      run_fn: :func:`spot.pipeline.run` unless given (tests pass another); with ``vmap``,
        :func:`spot.run.multiseed.run` unless given.
      vmap: run the seeds not finished yet together, IQL vmapped over them (one MLflow run per
        seed still); otherwise one after another.

    Returns:
      One final-metrics dict per seed.
    """
    from mlflow.tracking import MlflowClient

    from spot import phases, tracking

    os.environ["MLFLOW_TRACKING_URI"] = ctx.tracking_uri
    client = phases.timed_calls(MlflowClient(ctx.tracking_uri))
    finals: list[dict[str, Any]] = []
    failures: list[tuple[int, BaseException]] = []
    pending: dict[int, dict[str, str]] = {}
    for seed in seeds:
        key = run_key(overrides, seed)
        done = tracking.finished_run(client, ctx.experiment_id, {"sweep_id": ctx.sweep_id, "trial_key": key})
        if done is not None:
            finals.append(_finished(done, seed))
            report({**finals[-1], **(_finished_metrics(done) if ctx.metric else {})})
        else:
            pending[seed] = _seed_tags(overrides, key, ctx, trial_id)
    if pending and run_fn is None:
        _open_data(overrides, next(iter(pending)), ctx)
    if vmap and pending:
        if run_fn is None:
            from spot.run import multiseed

            run_fn = multiseed.run
        try:
            with phases.phase("train"):  # the runs: what is not data, compile, evaluate or tracking
                vmapped = _run_vmapped(client, overrides, pending, ctx, report, run_fn)
            for final in vmapped:
                report(final)
                finals.append(final)
        except Exception as e:  # noqa: BLE001 - every seed failed with it
            failures.extend((seed, e) for seed in pending)
        pending = {}
    if run_fn is None:
        from spot import pipeline

        run_fn = pipeline.run
    for seed, tags in pending.items():
        try:
            with phases.phase("train"):
                final = _run_seed(client, overrides, seed, ctx, tags, report, run_fn)
        except Exception as e:  # noqa: BLE001 - recorded, reported by Ray after the other seeds ran
            failures.append((seed, e))
            continue
        report(final)
        finals.append(final)
    if len(failures) == 1 and len(seeds) == 1:
        raise failures[0][1]
    if failures:
        raise RuntimeError("; ".join(f"seed {s}: {type(e).__name__}: {e}" for s, e in failures))
    return sorted(finals, key=lambda f: list(seeds).index(f["seed"]))


# --------------------------------------------------------------------------- the trainable
def trial_overrides(config: dict[str, Any]) -> dict[str, Any]:
    """A Tune trial config's overrides: the trial's, with a searcher's proposed values (``search``,
    as plain Python values: HyperOpt proposes numpy scalars) over them."""
    searched = {k: v.item() if hasattr(v, "item") else v for k, v in config.get("search", {}).items()}
    return {**config["trial"]["overrides"], **searched}


_PROCESS: dict[str, Any] = {"settings": None, "last_end": None}  # this process's trial settings, last trial's end


def _configure_once(cpus: int, gpus: float, fast_compile: bool = False) -> None:
    """spot's and the trial's process settings (:func:`spot.runtime.configure`,
    :func:`configure_process`), once per process: a reused actor already made them for the same
    resources and sweep (a sweep's trials all ask for the same), and XLA has read them."""
    from spot import runtime

    quiet_ray_sigterm()  # Ray's SIGTERM at the sweep's end: no "Exception ignored ... SystemExit" lines
    if _PROCESS["settings"] == (cpus, gpus, fast_compile):
        return
    if _PROCESS["settings"] is not None and _PROCESS["settings"][2] != fast_compile and "jax" in sys.modules:
        from spot import SpotError

        raise SpotError(
            f"fast_compile: this process compiled with fast_compile={_PROCESS['settings'][2]}; XLA's flags "
            f"cannot change once jax started (a trial of another launch in a reused process?)"
        )
    # explicit either way: the sweep file decides, not a SPOT_FAST_COMPILE the driver's shell had
    os.environ[runtime.FAST_COMPILE_SWITCH] = "1" if fast_compile else "0"
    runtime.configure()  # spot's XLA flags, MUJOCO_GL and the compilation cache
    configure_process(cpus, gpus)
    _PROCESS["settings"] = (cpus, gpus, fast_compile)


def _process_started() -> float:
    """When this process started (``time.time()`` scale), from ``/proc``; 0 where unknown."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(ln for ln in Path("/proc/stat").read_text().splitlines() if ln.startswith("btime"))
        return float(boot.split()[1]) + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return 0.0


def _startup_s(ctx: SweepContext, called_at: float) -> float:
    """Seconds before the trial function was called: since the end of the previous trial in this
    process (a reused actor), else since the process started or the launch was set up, whichever
    is later (Ray may start worker processes before the launch needs them)."""
    last = _PROCESS["last_end"]
    since = last if last is not None else max(_process_started(), ctx.created_at)
    return max(0.0, called_at - since)


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _log_breakdown(
    ctx: SweepContext, finals: list[dict[str, Any]], values: dict[str, float], tags: dict[str, str]
) -> None:
    """The trial's breakdown, logged to each run it ran (not to runs found finished)."""
    from mlflow.entities import Metric, RunTag
    from mlflow.tracking import MlflowClient

    from spot.tracking import limits, tagnames

    client = MlflowClient(ctx.tracking_uri)
    now = int(time.time() * 1000)
    for final in finals:
        if not final.get("skipped"):
            with limits.waiting_on(ctx.tracking_uri, "logging the trial's time breakdown"):
                client.log_batch(
                    final["run_id"],
                    metrics=[Metric(k, float(v), now, 0) for k, v in values.items()],
                    tags=[RunTag(k, v) for k, v in tagnames.stored_tags(tags).items()],
                )


def _trainable(config: dict[str, Any], ctx: SweepContext, run_fn: RunFn | None = None) -> None:
    """The Ray Tune function trainable: one trial = ``config['trial']`` (:meth:`Trial.to_config`).

    The process settings are made first (once per process, :func:`_configure_once`): nothing
    before this line imports jax. The trial is timed by phase (module docstring).
    """
    called_at = time.time()
    from ray import tune

    from spot import phases

    context = tune.get_context()
    need = context.get_trial_resources().required_resources
    asked = float(need.get("CPU", 1))
    cpus, gpus = max(1, int(asked)), float(need.get("GPU", 0.0))
    startup, cpu0 = _startup_s(ctx, called_at), _cpu_s()
    reused = _PROCESS["settings"] is not None
    try:
        with phases.measure("other") as clock, trial_cpus(cpus, claim_slots=asked.is_integer()) as share:
            with phases.phase("startup"):
                _configure_once(share.xla_cpus(cpus), gpus, ctx.fast_compile)
                if run_fn is None:  # the pipeline's imports, timed as start-up
                    import jax  # noqa: F401
                    import mlflow  # noqa: F401

                    from spot import pipeline  # noqa: F401
                if "jax" in sys.modules:  # (a run_fn given by a test may not use jax at all)
                    phases.listen_to_compiles()
            clock.add("startup", startup)
            try:
                finals = run_trial(
                    trial_overrides(config),
                    list(config["trial"]["seeds"]),
                    ctx,
                    trial_id=context.get_trial_id(),
                    report=Reports(tune.report, ctx.metric, ctx.stopper),
                    run_fn=run_fn,
                    vmap=bool(config["trial"].get("vmap", False)),
                )
            except StoppedEarly:  # its runs are closed (KILLED); Ray ends a stopped trial's thread so
                raise SystemExit(0) from None
            cpu_s, spent = _cpu_s() - cpu0, clock.read()
            values = {f"time/trial_{k}_s": v for k, v in spent.items()}
            values.update(
                {
                    "time/trial_wall_s": startup + clock.read_wall,
                    "time/trial_cpu_s": cpu_s,
                    "time/trial_cpus": _cpus_had(share, cpus, cpu_s, clock.read_wall),
                }
            )
            values["trial/cpu_util"] = cpu_s / max(clock.read_wall * values["time/trial_cpus"], 1e-9)
            values.update({"trial/compiles": clock.compiles, "trial/compile_cache_hits": clock.cache_hits})
            device = phases.devices() if "jax" in sys.modules else "jax not used"
            tags = {"trial_device": device, "trial_process": "reused" if reused else "new"}
        _log_breakdown(ctx, finals, values, tags)
    finally:
        _PROCESS["last_end"] = time.time()
