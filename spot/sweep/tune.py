"""Ray and the Tune run of a launch: a local Ray on loopback (or a cluster's address), the resources
check, the Tune experiment over :func:`spot.sweep.trial._trainable` (new, or restored on
``--resume``), and the errors its trials ended with.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import secrets
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.sweep import search as search_lib
from spot.sweep.order import trial_order
from spot.sweep.spec import Sweep, run_key
from spot.sweep.summary import log_fit_cpu
from spot.sweep.tracking_store import watching_server
from spot.sweep.trial import RunFn, SweepContext, _trainable, trial_overrides
from spot.sweep.uris import LOOPBACK


def _local_ray_env() -> dict[str, str]:
    """Environment of a local Ray cluster bound to loopback, with token authentication.

    Ray 2.60 replaces a loopback ``_node_ip_address`` by the host's routable address (and its
    servers then listen on every interface) unless ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, which
    makes the node address 127.0.0.1: GCS, raylet, object manager, workers, the runtime-env agent
    and the autoscaler monitor then listen on loopback only. Token authentication
    (``RAY_AUTH_MODE=token``) with a fresh random token per launch, passed in the environment (so
    nothing is written to ``~/.ray``), keeps other local users off the cluster too; a
    ``RAY_AUTH_MODE`` or token the user set is kept.
    """
    env = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    if "RAY_AUTH_MODE" not in os.environ:
        env["RAY_AUTH_MODE"] = "token"
        if not (os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")):
            env["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    return env


def init_ray(address: str | None) -> bool:
    """Start local Ray on loopback (all CPUs, no dashboard) or connect to ``address``; False if Ray
    is already up in this process."""
    if not address:
        os.environ.update(_local_ray_env())  # before Ray starts: its processes inherit it
    import ray

    if ray.is_initialized():
        return False
    env_vars = {
        "RAY_CHDIR_TO_TRIAL_DIR": "0",  # trials keep the driver's working dir (relative paths)
        "MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT": "true",
        # a reused actor waits this long for a trial stopped early to close its runs (Ray's default: 2 s)
        "TUNE_FUNCTION_THREAD_TIMEOUT_S": os.environ.get("TUNE_FUNCTION_THREAD_TIMEOUT_S", "60"),
    }  # no "View run" lines in the progress view
    from spot import store as store_lib
    from spot.tracking import limits

    env_vars.update(limits.http_deadlines())  # every trial's MLflow requests have deadlines, on every node
    shared = {k: os.environ[k] for k in (store_lib.ENV_URI, store_lib.ENV_OPTIONS) if k in os.environ}
    env_vars.update(shared)  # every node reads and writes the same store
    if not (address and shared):  # with a shared store, each node of a cluster keeps its own local dirs
        env_vars.update({k: os.environ[k] for k in ("SPOT_DATA_DIR", "SPOT_CACHE_DIR") if k in os.environ})
    if address:
        _check_ray_address(address)
        try:
            ray.init(address=address, runtime_env={"env_vars": env_vars}, logging_level=logging.WARNING)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise SpotError(f"cannot connect to the Ray cluster at --address {address}: {e}") from e
        return True
    from ray._private import ray_constants, services

    # The constant is read when ray is imported; a process that imported ray before the
    # environment was set still gets the loopback node address.
    ray_constants.ENABLE_RAY_CLUSTER = False
    ray.init(
        num_cpus=os.cpu_count(),
        include_dashboard=False,
        _node_ip_address=LOOPBACK,
        runtime_env={"env_vars": env_vars},
        logging_level=logging.WARNING,
    )
    node_ip = services.get_node_ip_address()
    if node_ip != LOOPBACK:
        ray.shutdown()
        raise SpotError(
            f"local Ray came up on {node_ip}, not on loopback; refusing to run a sweep on a "
            "cluster other hosts can reach (see docs/sweeps.md, 'What is exposed')"
        )
    return True


def _check_ray_address(address: str) -> None:
    """A ``host:port`` address must accept a TCP connection within 5 s (``ray.init`` would retry
    for minutes); ``auto`` and ``ray://`` addresses are left to Ray."""
    host, sep, port = address.rpartition(":")
    if "://" in address or not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
    except OSError as e:
        raise SpotError(
            f"nothing answers at the Ray address {address} ({e.strerror or e}); start the cluster, "
            "or check --address / RAY_ADDRESS"
        ) from None


def check_gpus(sweep: Sweep) -> None:
    """Stop before any run is opened if trials ask for more GPUs or CPUs than the Ray cluster has
    (Tune would otherwise wait for them forever)."""
    import ray

    have = ray.cluster_resources()
    if sweep.resources["gpu"] > 0 and float(have.get("GPU", 0.0)) == 0:
        raise SpotError(
            f"sweep file '{sweep.path}': resources.gpu = {sweep.resources['gpu']:g} per trial, but the Ray "
            "cluster has no GPU; set resources: {gpu: 0} (--smoke uses no GPU unless its block asks), or "
            "give --address of a cluster with GPUs"
        )
    nodes_cpus = [float(n.get("Resources", {}).get("CPU", 0.0)) for n in ray.nodes() if n.get("Alive")]
    most = max(nodes_cpus, default=float(have.get("CPU", 0.0)))
    if sweep.resources["cpu"] > most:
        raise SpotError(
            f"sweep file '{sweep.path}': resources.cpu = {sweep.resources['cpu']:g} per trial, but the largest "
            f"node of the Ray cluster has {most:g} CPUs; ask for at most {most:g}"
        )


def _reporter_class() -> type:
    from ray import tune

    class Reporter(tune.CLIReporter):
        """Tune's status table without the ``Result logdir`` line it repeats in every report (the
        launch prints its storage folder once, at the start)."""

        def report(self, trials: Any, done: bool, *sys_info: str) -> None:
            text = self._progress_str(trials, done, *sys_info)
            self._print("\n".join(ln for ln in text.splitlines() if not ln.startswith("Result logdir:")))

    return Reporter


def _Reporter(**kwargs: Any) -> Any:  # noqa: N802 (a class, built on first use so Ray imports lazily)
    return _reporter_class()(**kwargs)


def _trial_dirname(trial: Any) -> str:
    return str(trial.trial_id)


def _trial_name(trial: Any) -> str:
    """A readable trial name for Tune's output: ``method=spot,seed=0`` (axes, then seeds)."""
    cfg = trial.config.get("trial", {}) if isinstance(trial.config, dict) else {}
    searched = trial.config.get("search", {}) if isinstance(trial.config, dict) else {}
    parts = [
        f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in {**cfg.get("axes", {}), **searched}.items()
    ]
    seeds = cfg.get("seeds", [])
    parts.append(f"seed={seeds[0]}" if len(seeds) == 1 else f"seeds={','.join(map(str, seeds))}")
    return ",".join(parts)


def _param_space(sweep: Sweep) -> dict[str, Any]:
    """Tune's param space: the grid of trials, or (``search:``) the template trial and the searched
    keys' domains under ``search`` (:func:`spot.sweep.trial._trainable` merges them)."""
    from ray import tune

    if sweep.search is None:
        return {"trial": tune.grid_search([t.to_config() for t in trial_order(sweep.trials())])}  # what overlaps does
    return {"trial": sweep.trials()[0].to_config(), "search": search_lib.space(sweep.search)}


def _search_config(sweep: Sweep) -> dict[str, Any]:
    """The TuneConfig fields of ``search:`` and ``scheduler:`` (none for a plain grid)."""
    if sweep.metric is None:
        return {}
    out: dict[str, Any] = {"metric": sweep.metric, "mode": sweep.mode}
    if sweep.search is not None:
        out.update(search_alg=search_lib.searcher(sweep.search), num_samples=sweep.search.num_samples)
    if sweep.scheduler is not None:
        out["scheduler"] = search_lib.scheduler(sweep.scheduler)
    return out


def _tuner(
    sweep: Sweep, trainable: Any, exp_dir: Path, *, resume: bool, retry_errored: bool, max_concurrent: int | None
) -> Any:
    """A new Tune experiment over the sweep's trials, or the restored one with ``resume``."""
    from ray import tune

    param_space = _param_space(sweep)
    if resume and tune.Tuner.can_restore(str(exp_dir)):
        died, raised = _errored_trials(exp_dir)
        if died and not retry_errored:
            # Trials whose process was killed with the launch (a SIGTERM to the process group can
            # reach a worker before the driver) were cut off, not failed: they run again. Tune
            # restarts errored trials all together, so failed ones then run again too.
            print(
                f"note: {died} trial(s) whose process died with the interrupted launch run again"
                + (f", and with them {raised} failed trial(s) (as with --retry-errored)" if raised else ""),
                flush=True,
            )
        return tune.Tuner.restore(
            str(exp_dir),
            trainable=trainable,
            param_space=param_space,
            resume_unfinished=True,
            resume_errored=False,
            restart_errored=retry_errored or died > 0,
        )
    reporter = _Reporter(
        parameter_columns={
            **{
                f"{'search' if sweep.search and k in sweep.search.space else 'trial/axes'}/{k}": k
                for k in sweep.axis_keys
            },
            "trial/seeds": "seeds",
        },
        metric_columns={
            "iql_step": "step",
            "score": "score",
            "score_final": "final",
            "seed": "seed",
            **({sweep.metric: sweep.metric} if sweep.metric in search_lib.OFFLINE_SAFE else {}),
        },
        max_report_frequency=30,
        sort_by_metric=False,
    )
    return tune.Tuner(
        trainable,
        param_space=param_space,
        tune_config=tune.TuneConfig(
            **_search_config(sweep),
            max_concurrent_trials=max_concurrent,
            reuse_actors=True,  # the trials ask for the same resources: the next trial reuses an actor's process
            trial_dirname_creator=_trial_dirname,
            trial_name_creator=_trial_name,
        ),
        run_config=tune.RunConfig(
            name=exp_dir.name,
            storage_path=str(exp_dir.parent),
            progress_reporter=reporter,
            verbose=1,
            failure_config=tune.FailureConfig(max_failures=0, fail_fast=False),
        ),
    )


def _analysis_trials(exp_dir: Path) -> list[Any]:
    """The trials of the Tune experiment in ``exp_dir`` as saved."""
    from ray import tune

    # ExperimentAnalysis, not the ResultGrid: a Result of a restored trial that never reported lacks
    # its config. Its warnings about trials that never started ("no metrics") are noise here.
    quiet = logging.getLogger("ray.tune.analysis.experiment_analysis")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        return list(tune.ExperimentAnalysis(str(exp_dir)).trials)
    finally:
        quiet.setLevel(level)


_CUT_OFF = "TrackingUnreachable"  # the class name in a trial's error text (spot.tracking.limits)


def _errored_trials(exp_dir: Path) -> tuple[int, int]:
    """``(died, raised)``: errored trials cut off (their process died: Ray's actor/worker/node death
    errors; or their tracking server did not answer, :class:`spot.tracking.TrackingUnreachable`, so
    their runs could not even be recorded), and errored trials whose own code raised."""
    from ray import exceptions

    kinds = tuple(
        getattr(exceptions, name)
        for name in ("RayActorError", "WorkerCrashedError", "NodeDiedError", "LocalRayletDiedError")
        if hasattr(exceptions, name)
    )
    died = raised = 0
    for trial in _analysis_trials(exp_dir):
        if trial.status != "ERROR":
            continue
        error = trial.get_pickled_error() or trial.get_error()
        text = str(error)
        if isinstance(error, kinds) or any(k in text for k in ("ActorDiedError", "The actor died", _CUT_OFF)):
            died += 1
        else:
            raised += 1
    return died, raised


def _trial_errors(exp_dir: Path) -> tuple[dict[str, str], bool]:
    """``{run_key: error}`` for each seed of the errored trials, and whether some trial is unfinished."""
    trials = _analysis_trials(exp_dir)
    errors: dict[str, str] = {}
    for trial in trials:
        error = (trial.get_pickled_error() or trial.get_error()) if trial.status == "ERROR" else None
        if error is not None:
            lines = [ln for ln in str(error).splitlines() if ln.strip()]
            for seed in trial.config["trial"]["seeds"]:
                errors[run_key(trial_overrides(trial.config), seed)] = lines[-1] if lines else repr(error)
    return errors, any(t.status not in ("TERMINATED", "ERROR") for t in trials)


def fit(
    sweep: Sweep,
    ctx: SweepContext,
    exp_dir: Path,
    *,
    resume: bool,
    retry_errored: bool,
    max_concurrent: int | None,
    run_fn: RunFn | None,
    died: Callable[[], str] = lambda: "",
) -> tuple[dict[str, str], bool]:
    """Run (or restore) the Tune experiment; ``died`` tells whether the launch's MLflow server died
    (:func:`watching_server` stops Tune then).

    Returns ``{run_key: error}`` for each seed of errored trials, and whether the launch was
    interrupted (Ctrl-C, or the server's death: Tune stops and returns with trials left unfinished).
    """
    from ray import tune

    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")  # use the CLIReporter of _tuner
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
    trainable = tune.with_resources(
        # A partial, not tune.with_parameters: that ray.put()s its arguments, objects the driver owns in
        # the node's object store, and when the node dies under a SIGTERM Ray's core worker tries to
        # recover them, fails to reach the store and ends the driver with exit code 1 (_Exit in C++)
        # before its handler can close the runs. ctx and run_fn are small; Tune ships a partial as it is.
        functools.partial(_trainable, ctx=ctx, run_fn=run_fn),
        {"cpu": sweep.resources["cpu"], "gpu": sweep.resources["gpu"]},
    )
    from mlflow.tracking import MlflowClient

    from spot import phases

    with phases.CpuMeter() as cpu, watching_server(died):  # the sweep's CPU utilisation, printed at the end
        _tuner(
            sweep, trainable, exp_dir, resume=resume, retry_errored=retry_errored, max_concurrent=max_concurrent
        ).fit()
    if sweep.scheduler is not None and not died():  # before the launch closes what is left as orphans
        from spot.sweep.reports import close_stopped

        close_stopped(MlflowClient(ctx.tracking_uri), ctx, _analysis_trials(exp_dir))
    with contextlib.suppress(Exception):  # a measurement: never the reason a launch fails
        if not died():
            log_fit_cpu(MlflowClient(ctx.tracking_uri), ctx.parent_run_id, cpu)
    return _trial_errors(exp_dir)
