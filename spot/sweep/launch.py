"""The driver of a launch (``spot sweep FILE``): store, Ray, parent run, Tune, summary.

:func:`run_sweep` validates the file, builds the datasets the runs need, serves a SQLite store
through a loopback ``mlflow server`` (:mod:`spot.mlflow_server`) unless given a server's URI,
starts Ray, creates the experiment and the parent run, runs one Tune experiment over
:func:`spot.sweep.trial._trainable`, closes the runs it left RUNNING, and logs and prints the
summary. ``--resume`` restores the Ray experiment recorded in ``<storage>/<experiment>.json``.

Hangs and deadlines (issue 43): while Tune runs, a thread polls the MLflow server the launch started
(:func:`_watching_server`); if it dies, the launch stops its trials as Ctrl-C does, closes the runs
through the SQLite store itself and ends with one error naming the server. A SIGTERM's cleanup runs
in steps, each with its own deadline and message (:func:`_sigterm_cleanup`), and closes the runs
through the store directly when the server is gone or does not answer.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import json
import logging
import os
import secrets
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spot import SpotError
from spot import config as config_lib
from spot.sweep.spec import Sweep, load, run_key, tag_value
from spot.sweep.summary import Row, breakdown_text, format_summary, log_fit_cpu, paper_table, summarize
from spot.sweep.trial import RunFn, SweepContext, _trainable

DEFAULT_STORAGE = Path("spot_runs") / "ray"


def prebuild_datasets(sweep: Sweep) -> list[Path]:
    """Build every registry dataset the sweep's runs need, here on the driver, before trials start.

    A build uses all the driver's cores, where inside a trial it would be pinned to the trial's
    CPUs while the other trials wait on its lock. Files given as paths are left alone. With a
    store (:mod:`spot.store`) each build is uploaded, and trials on other nodes download it; on a
    cluster without one whose nodes do not share ``$SPOT_DATA_DIR`` the trials build what they miss.
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


# --------------------------------------------------------------------------- store and Ray
@dataclass(frozen=True)
class _Store:
    """The launch's store: ``uri()`` (a served store's port may change while it starts, see
    :meth:`spot.mlflow_server.MlflowServer.wait_ready`), how to open it, and its server's
    ``wait_ready``/``stop``."""

    get_uri: Callable[[], str]
    how_to_open: str
    wait_ready: Callable[[], None]
    stop: Callable[..., None] = lambda timeout=30.0: None  # (the served store's: SIGKILL after timeout s)
    link_base: str = ""  # where the UI answers, for the link to the sweep's runs table
    backend: str = ""  # the SQLite store spot serves ("" for a server given by URI)
    died: Callable[[], str] = lambda: ""  # "" while spot's server runs; else what happened to it
    log_path: str = ""  # the served store's server log

    @property
    def uri(self) -> str:
        return self.get_uri()


LOOPBACK = "127.0.0.1"
_SWEEP_SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql", "databricks", "databricks-uc")


def _check_tracking_uri(uri: str) -> str:
    """``uri`` if a sweep can log there (``""``: the default store); SpotError otherwise."""
    from spot import mlflow_server, tracking

    if uri and mlflow_server.is_local_store(uri) and not uri.startswith("sqlite:"):
        raise SpotError(
            f"tracking URI '{uri}': file stores cannot take concurrent trials; give "
            "sqlite:///path.db (spot serves it) or http(s)://host:port of a tracking server"
        )
    scheme = uri.split("://", 1)[0].split("+", 1)[0].lower() if "://" in uri else ""
    if uri and (scheme not in _SWEEP_SCHEMES or (scheme == "sqlite" and tracking.sqlite_path(uri) is None)):
        raise SpotError(
            f"tracking URI '{uri}': a sweep logs to sqlite:///path.db (spot serves it), an "
            "http(s)://host:port tracking server, or a database MLflow supports "
            "(postgresql://, mysql://, mssql://) or databricks://"
        )
    return uri


def _check_tracking_host(host: str | None, address: str | None, tracking_uri: str | None) -> None:
    """``--tracking-host`` is for the server spot starts for a cluster sweep."""
    from spot import tracking

    if host is None:
        return
    if not address:
        raise SpotError(
            f"--tracking-host {host}: only for a cluster sweep (--address); a local sweep's server stays on loopback"
        )
    uri = tracking.given_uri(tracking_uri)
    if uri and not uri.startswith("sqlite:"):
        raise SpotError(
            f"--tracking-host {host}: spot starts no server for --tracking-uri {uri}; give one or the other"
        )
    if not host.strip() or any(c in host for c in "/ :[]"):
        raise SpotError(f"--tracking-host {host!r}: expected an IPv4 address or host name, e.g. 0.0.0.0")


def _advertised_host(host: str, address: str | None) -> str:
    """The address trials reach a server bound to ``host`` at: ``host`` itself, or for ``0.0.0.0``
    this machine's address on the route to the Ray head (``address``)."""
    if host != "0.0.0.0":
        return host
    peer, sep, port = (address or "").rpartition(":")
    with contextlib.suppress(OSError):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # no packet is sent
            s.connect((peer if sep and port.isdigit() else "10.255.255.255", int(port) if port.isdigit() else 1))
            return s.getsockname()[0]
    return socket.gethostbyname(socket.gethostname())


@contextlib.contextmanager
def _tracking_store(
    uri: str | None, root: Path, host: str | None = None, address: str | None = None
) -> Iterator[_Store]:
    """The tracking store of a launch; a SQLite store is served by a loopback server (bound to
    ``host`` instead, for a cluster sweep's ``--tracking-host``).

    The server starts here but is only waited for by ``wait_ready()``, so that Ray can start
    meanwhile.
    """
    from spot import mlflow_server, tracking

    uri = _check_tracking_uri(tracking.given_uri(uri))
    if uri and not uri.startswith("sqlite:"):
        if uri.startswith(("http://", "https://")):
            mlflow_server.check_reachable(uri)  # before Ray starts: a clear error within seconds
        link = uri if uri.startswith(("http://", "https://")) else ""
        yield _Store(lambda: uri, f"MLflow: {uri}", lambda: None, link_base=link)
        return
    db = tracking.sqlite_path(uri) if uri else root / "mlflow.db"
    db.parent.mkdir(parents=True, exist_ok=True)
    backend = mlflow_server.sqlite_uri(db)
    artifacts = db.resolve().parent / "artifacts"
    bind = host or LOOPBACK
    server = mlflow_server.MlflowServer(
        backend,
        artifacts,
        log_path=db.resolve().parent / "mlflow-server.log",
        host=bind,
        advertise=_advertised_host(bind, address),
    )
    print(f"starting mlflow server on {server.uri} (store {backend})", flush=True)
    if bind != LOOPBACK:
        print(
            f"WARNING: the MLflow server listens on {bind}:{server.port}, not on loopback (--tracking-host): "
            "anyone who can reach that port can read, change and delete the runs and artifacts (MLflow's "
            "server has no authentication). Keep it on a private network, firewalled to the cluster's "
            "nodes (docs/sweeps.md, 'Multi-node sweeps').",
            file=sys.stderr,
            flush=True,
        )
    server.start(wait=False)
    try:
        yield _Store(
            lambda: server.uri,
            f"open the runs with: {tracking.ui.ui_command(backend, artifacts)}",
            server.wait_ready,
            server.stop,
            link_base=tracking.ui.DEFAULT_URL,
            backend=backend,
            died=server.died,
            log_path=str(server.log_path),
        )
    finally:
        server.stop()


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


def _init_ray(address: str | None) -> bool:
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


def _check_gpus(sweep: Sweep) -> None:
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


# --------------------------------------------------------------------------- Tune
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
    parts = [f"{k}={v}" for k, v in cfg.get("axes", {}).items()]
    seeds = cfg.get("seeds", [])
    parts.append(f"seed={seeds[0]}" if len(seeds) == 1 else f"seeds={','.join(map(str, seeds))}")
    return ",".join(parts)


def _tuner(
    sweep: Sweep, trainable: Any, exp_dir: Path, *, resume: bool, retry_errored: bool, max_concurrent: int | None
) -> Any:
    """A new Tune experiment over the sweep's trials, or the restored one with ``resume``."""
    from ray import tune

    param_space = {"trial": tune.grid_search([t.to_config() for t in sweep.trials()])}
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
        parameter_columns={**{f"trial/axes/{k}": k for k in sweep.axis_keys}, "trial/seeds": "seeds"},
        metric_columns={"iql_step": "step", "score": "score", "score_final": "final", "seed": "seed"},
        max_report_frequency=30,
        sort_by_metric=False,
    )
    return tune.Tuner(
        trainable,
        param_space=param_space,
        tune_config=tune.TuneConfig(
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
                errors[run_key(trial.config["trial"]["overrides"], seed)] = lines[-1] if lines else repr(error)
    return errors, any(t.status not in ("TERMINATED", "ERROR") for t in trials)


def _fit(
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
    (:func:`_watching_server` stops Tune then).

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

    with phases.CpuMeter() as cpu, _watching_server(died):  # the sweep's CPU utilisation, printed at the end
        _tuner(
            sweep, trainable, exp_dir, resume=resume, retry_errored=retry_errored, max_concurrent=max_concurrent
        ).fit()
    with contextlib.suppress(Exception):  # a measurement: never the reason a launch fails
        if not died():
            log_fit_cpu(MlflowClient(ctx.tracking_uri), ctx.parent_run_id, cpu)
    return _trial_errors(exp_dir)


# --------------------------------------------------------------------------- the launch's records
def record_file(sweep: Sweep, storage: str | Path) -> Path:
    """``<storage>/<experiment>.json``: the record of the sweep's last launch with that storage."""
    return Path(storage).resolve() / f"{sweep.experiment}.json"


def lock_file(state_file: Path) -> Path:
    """The lock beside a launch record, ``<storage>/<experiment>.lock``: held while a launch runs."""
    return state_file.with_suffix(".lock")


def read_record(state_file: Path) -> dict[str, str]:
    """A launch record: sweep id, spec hash and parent run id; ValueError if it is damaged."""
    try:
        state = json.loads(state_file.read_text())
    except UnicodeDecodeError as e:
        raise ValueError(str(e)) from None
    if not (
        isinstance(state, dict)
        and all(isinstance(state.get(k), str) and state[k] for k in ("sweep_id", "spec_hash", "parent_run_id"))
    ):
        raise ValueError("expected an object with sweep_id, spec_hash and parent_run_id")
    return state


def _state(sweep: Sweep, path: str | Path, state_file: Path, *, resume: bool) -> dict[str, Any]:
    """The launch record: a new sweep id, or the one being resumed (checked to expand the same)."""
    if not resume:
        return {
            "sweep_id": f"{sweep.experiment}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(2)}",
            "spec_hash": sweep.spec_hash(),
            "file": str(Path(path).resolve()),
        }
    if not state_file.is_file():
        raise SpotError(
            f"nothing to resume: no launch of sweep '{sweep.experiment}' under {state_file.parent}; "
            "start it without --resume"
        )
    try:
        state = read_record(state_file)
    except ValueError as e:
        raise SpotError(
            f"launch record {state_file} is damaged ({e}); it cannot be resumed: start a new launch without --resume"
        ) from None
    if state["spec_hash"] != sweep.spec_hash():
        raise SpotError(
            f"sweep file '{path}' expands to other trials than the launch {state['sweep_id']} "
            "being resumed; Ray cannot change a sweep's trials: start a new launch without --resume"
        )
    return state


def _open_parent(client: Any, experiment_id: str, sweep: Sweep, state: dict[str, Any], *, resume: bool) -> str:
    """Create the launch's parent run (recorded in ``state``), or reopen it on resume."""
    from spot import tracking
    from spot.tracking.processes import process_tags

    if resume:
        parent_id = state["parent_run_id"]
        n = tracking.close_orphans(
            client,
            experiment_id,
            {"sweep_id": state["sweep_id"]},
            "process ended during an interrupted launch",
            keep=(parent_id,),
        )
        print(
            f"resuming {state['sweep_id']}: {n} run(s) left RUNNING by the interrupted launch marked KILLED", flush=True
        )
        client.update_run(parent_id, status="RUNNING")
        client.set_tag(parent_id, "resumed_at", time.strftime("%Y-%m-%d %H:%M:%S"))
        for key, value in process_tags().items():  # this driver owns the reopened run now
            client.set_tag(parent_id, key, value)
        return parent_id
    parent = client.create_run(
        experiment_id,
        run_name=f"sweep {state['sweep_id']}",
        tags={
            "sweep_id": state["sweep_id"],
            "sweep_name": sweep.name,
            "spot.role": "sweep",
            "smoke": str(sweep.smoke),
            "sweep_file": str(sweep.path.resolve()),
            "git_commit": tracking.git_commit(),
            **process_tags(),
        },
    )
    parent_id = parent.info.run_id
    client.log_text(parent_id, sweep.path.read_text(), "sweep.yaml")
    client.log_dict(parent_id, [t.to_config() for t in sweep.trials()], "trials.json")
    client.log_batch(parent_id, params=_parent_params(sweep))
    state["parent_run_id"] = parent_id
    return parent_id


def _parent_params(sweep: Sweep) -> list[Any]:
    from mlflow.entities import Param

    params = {
        "sweep.trials": len(sweep.trials()),
        "sweep.runs": len(sweep.runs()),
        "sweep.seeds": list(sweep.seeds),
        "sweep.seed_mode": sweep.seed_mode,
        "sweep.cpu": sweep.resources["cpu"],
        "sweep.gpu": sweep.resources["gpu"],
        **{f"grid.{k}": v for k, v in sweep.grid.items()},
        **{f"zip.{k}": v for k, v in sweep.zip.items()},
        **{f"base.{k}": v for k, v in sweep.base.items()},
    }
    return [Param(k, tag_value(v)[:6000]) for k, v in params.items()]


def _close_parent(client: Any, ctx: SweepContext, rows: list[Row], table: str, *, interrupted: bool) -> None:
    """Log the summary to the parent run and end it: FINISHED if every run finished, KILLED if
    interrupted, else FAILED."""
    from mlflow.entities import Metric

    n_done = sum(r.status == "FINISHED" for r in rows)
    now = int(time.time() * 1000)
    client.log_batch(
        ctx.parent_run_id,
        metrics=[
            Metric(k, v, now, 0)
            for k, v in (
                ("sweep/runs_total", len(rows)),
                ("sweep/runs_finished", n_done),
                ("sweep/runs_failed", len(rows) - n_done),
            )
        ],
    )
    client.log_text(ctx.parent_run_id, table + "\n", "summary.txt")
    client.set_terminated(
        ctx.parent_run_id, "KILLED" if interrupted else "FINISHED" if n_done == len(rows) else "FAILED"
    )


# --------------------------------------------------------------------------- signals
class Interrupted(Exception):  # noqa: N818 - a stop, not an error
    """The launch was stopped by SIGTERM or SIGINT; its runs are closed (KILLED) and Ray is shut down.

    ``exit_code`` is the shell's convention, 128 + the signal number (143 for SIGTERM, 130 for SIGINT).
    """

    def __init__(self, signum: int) -> None:
        self.signum = signum
        self.exit_code = 128 + signum
        super().__init__(f"sweep stopped by {signal.Signals(signum).name}")


SIGTERM_GRACE_S = 60.0  # the longest a SIGTERM's cleanup may take before the process exits anyway
_CLEANUP = {"step": ""}  # the step of a signal's cleanup now running (:func:`_cleanup_step`), for the watchdog


def _say(message: str) -> None:
    """A line on stderr from a signal handler: it must not raise, even when the handler interrupted a
    write to the same stream (a reentrant write raises ``RuntimeError``)."""
    with contextlib.suppress(Exception):
        print(message, file=sys.stderr, flush=True)


@contextlib.contextmanager
def _on_sigterm(stop: Callable[[], None], grace_s: float = SIGTERM_GRACE_S) -> Iterator[None]:
    """Within the block, SIGTERM runs ``stop()`` and ends the process with exit code 143.

    A SIGTERM to the sweep's process group (``timeout``, a batch scheduler) reaches Ray's GCS,
    raylet and workers too, and Tune's own cleanup would then wait forever on the dead cluster;
    so the driver does not unwind through Tune: ``stop()`` stops the trials, closes the runs in
    MLflow (the server runs in its own session and survives the signal), stops Ray and the server,
    and the process exits at once. The exit is certain: an exception from ``stop()`` is printed,
    a flush of a stream that raises cannot skip the exit, and a watchdog thread (started with the
    block, armed by the signal, so the handler starts no thread) ends the process with the same
    code if ``stop()`` has not returned after ``grace_s`` seconds. Further SIGTERMs are ignored
    meanwhile. The handler ``ray.init`` installs (``sys.exit(15)``) is restored after the block.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    armed, over = threading.Event(), threading.Event()

    def watchdog() -> None:
        armed.wait()
        if not over.wait(grace_s):  # set at once when the block ended without a signal
            step = f" (in step '{_CLEANUP['step']}')" if _CLEANUP["step"] else ""
            _say(f"SIGTERM: cleanup still running after {grace_s:.0f} s{step}; exiting")
            os._exit(128 + signal.SIGTERM)

    def handler(signum: int, frame: Any) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _CLEANUP["step"] = ""
        armed.set()
        try:
            stop()
        except BaseException as e:  # noqa: BLE001 - reported, then the exit below
            _say(f"SIGTERM: cleanup failed: {type(e).__name__}: {e}")
        finally:
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(128 + signum)

    threading.Thread(target=watchdog, name="sigterm-watchdog", daemon=True).start()
    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        over.set()
        armed.set()


def _kill_trial_workers(timeout: float = 5.0) -> None:
    """SIGKILL the worker processes (``ray::...``: the trials) of the local Ray node this driver
    started and wait for them, without talking to Ray; the node itself stays up, so nothing a
    trial could still do (finish its run, open the next seed's) outlives the closing of the runs."""
    import psutil
    import ray
    from ray._private import ray_constants

    node = getattr(ray._private.worker, "_global_node", None)
    if node is None:
        return
    workers = []
    for info in node.all_processes.get(ray_constants.PROCESS_TYPE_RAYLET, []):
        with contextlib.suppress(psutil.Error):
            for child in psutil.Process(info.process.pid).children(recursive=True):
                with contextlib.suppress(psutil.Error, IndexError):
                    if child.cmdline()[0].startswith("ray::"):
                        workers.append(child)
    for worker in workers:
        with contextlib.suppress(psutil.Error):
            worker.kill()
    psutil.wait_procs(workers, timeout=timeout)


def _kill_local_ray() -> None:
    """Stop the processes of the local Ray node this driver started, without talking to them (the
    GCS may already be gone, and ``ray.shutdown()`` would wait for it)."""
    import ray

    node = getattr(ray._private.worker, "_global_node", None)
    if node is not None:
        with contextlib.suppress(Exception):
            node.kill_all_processes(check_alive=False, allow_graceful=True)


# --------------------------------------------------------------------------- the server's death, bounded cleanup
SERVER_POLL_S = 1.0  # how often the launch checks, while Tune runs, that its MLflow server still runs
CLEANUP_REQUEST_S = 5  # the deadline of each MLflow request of a signal's cleanup (no retries then)
CLEANUP_STEPS_S = {
    "stopping the trials": 10.0,
    "closing the runs": 25.0,
    "stopping Ray": 10.0,
    "stopping the MLflow server": 10.0,
}  # each step's deadline; together below SIGTERM_GRACE_S, so the watchdog is the last resort only
DIRECT_CLOSE_S = 10.0  # of "closing the runs": kept for closing them through the SQLite store itself


@contextlib.contextmanager
def _watching_server(died: Callable[[], str], poll_s: float = SERVER_POLL_S) -> Iterator[None]:
    """While the block (Tune's ``fit``) runs, a thread checks every ``poll_s`` seconds that the
    launch's MLflow server still runs (``died()``: "" while it does).

    Once it died: one line saying so, and Tune is stopped as by Ctrl-C, with SIGUSR1, on which Tune's
    own handler (installed by ``fit``) saves the experiment, stops the trials and returns with them
    unfinished, so ``--resume`` runs them again. The signal is sent only while a handler is installed
    (SIGUSR1's default action ends the process), and again every 30 s until the block ends.
    """
    done = threading.Event()

    def watch() -> None:
        told, sent = False, -1e9
        while not done.wait(poll_s):
            death = died()
            if not death:
                continue
            if not told:
                _say(f"{death}; stopping the trials, then closing their runs through the store")
                told = True
            if callable(signal.getsignal(signal.SIGUSR1)) and time.monotonic() - sent > 30:
                os.kill(os.getpid(), signal.SIGUSR1)
                sent = time.monotonic()

    watcher = threading.Thread(target=watch, name="mlflow-server-watch", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join(poll_s + 5)


def _server_died_error(store: _Store, ctx: SweepContext | None, resume_command: str) -> SpotError:
    """The launch's one error when its MLflow server died (its runs are closed by then)."""
    log = f" (the server's log: {store.log_path})" if store.log_path else ""
    if ctx is None:
        return SpotError(f"{store.died()} before the sweep's runs were opened{log}; start the launch again")
    return SpotError(
        f"{store.died()} while the sweep ran{log}: its trials were stopped, and the runs they left RUNNING "
        f"and the parent run {ctx.parent_run_id} are marked KILLED in {store.backend}; to continue: {resume_command}"
    )


@contextlib.contextmanager
def _server_death(store: _Store, ctx: SweepContext, resume_command: str) -> Iterator[None]:
    """An error in the block, while the launch's MLflow server has died, becomes
    :func:`_server_died_error`, the runs closed through the store first."""
    try:
        yield
    except Exception:
        if not store.died():
            raise
        _close_runs(store, ctx, store.died())
        raise _server_died_error(store, ctx, resume_command) from None


def _close_in(uri: str, ctx: SweepContext, reason: str, deadline: float | None) -> None:
    """Mark the launch's RUNNING runs and its parent run (if RUNNING) KILLED in the store at ``uri``."""
    from mlflow.tracking import MlflowClient

    from spot import tracking
    from spot.tracking import limits

    mine = MlflowClient(uri)  # not the main thread's client: a signal may interrupt it
    tags = {"sweep_id": ctx.sweep_id}
    tracking.close_orphans(mine, ctx.experiment_id, tags, reason, keep=(ctx.parent_run_id,), deadline=deadline)
    if deadline is not None and time.monotonic() > deadline:
        raise TimeoutError("the deadline passed before the parent run was closed")
    with limits.waiting_on(uri, f"closing the parent run {ctx.parent_run_id}"):
        if mine.get_run(ctx.parent_run_id).info.status == "RUNNING":
            mine.set_tag(ctx.parent_run_id, "failure_reason", limits.cap_reason(reason))
            mine.set_terminated(ctx.parent_run_id, "KILLED")


def _close_runs(store: _Store, ctx: SweepContext, reason: str, deadline: float | None = None) -> str:
    """Close the launch's runs (:func:`_close_in`) through the server; through the SQLite store it
    serves when the server died, or did not answer (by ``deadline`` less :data:`DIRECT_CLOSE_S`).

    Returns ``""``, or where the runs were closed when that was not through the server.
    """
    if store.backend and store.died():
        _close_in(store.backend, ctx, reason, None)
        return f" in {store.backend} (the server is gone)"
    if not store.backend:  # a server given by URI: nothing else to go through
        _close_in(store.uri, ctx, reason, deadline)
        return ""
    try:
        _close_in(store.uri, ctx, reason, None if deadline is None else deadline - DIRECT_CLOSE_S)
        return ""
    except Exception as e:  # noqa: BLE001 - any failure through the server: the store itself next
        _say(f"note: closing the runs through {store.uri} failed ({type(e).__name__}: {e}); using {store.backend}")
        _close_in(store.backend, ctx, reason, None)
        return f" in {store.backend} (the server did not answer)"


def _cleanup_step(name: str, fn: Callable[[float], Any]) -> None:
    """One step of a signal's cleanup: says what it does and its deadline (:data:`CLEANUP_STEPS_S`),
    runs ``fn(deadline)`` (a ``time.monotonic()`` value it keeps to), says how it failed or that it
    overran; never raises."""
    budget = CLEANUP_STEPS_S[name]
    start = time.monotonic()
    _CLEANUP["step"] = name
    _say(f"SIGTERM: {name} (deadline {budget:.0f} s)")
    try:
        fn(start + budget)
    except Exception as e:  # noqa: BLE001 - reported; the next step runs
        _say(f"SIGTERM: {name} failed after {time.monotonic() - start:.1f} s: {type(e).__name__}: {e}")
        return
    spent = time.monotonic() - start
    if spent > budget:
        _say(f"SIGTERM: {name} took {spent:.1f} s, past its deadline of {budget:.0f} s")


def _left(deadline: float) -> float:
    return max(0.5, deadline - time.monotonic())


def _sigterm_cleanup(store: _Store, close: Callable[[str, float], None], started_ray: bool) -> None:
    """A SIGTERM's cleanup, in steps with their own deadlines (:func:`_cleanup_step`): stop the
    trials, close the runs (``close(reason, deadline)``; MLflow requests get :data:`CLEANUP_REQUEST_S`
    and no retries, and the runs go through the SQLite store itself if the server is gone or does not
    answer), stop Ray, stop the MLflow server."""
    from spot.tracking import limits

    os.environ.update({k: "0" if "RETRIES" in k else str(CLEANUP_REQUEST_S) for k in limits.HTTP_DEADLINES})
    _say("SIGTERM: stopping the trials, closing the runs, stopping Ray")
    if started_ray:
        _cleanup_step("stopping the trials", lambda until: _kill_trial_workers(_left(until)))
    _cleanup_step("closing the runs", lambda until: close("launch stopped by SIGTERM", until))
    if started_ray:
        _cleanup_step("stopping Ray", lambda until: _kill_local_ray())
    _cleanup_step("stopping the MLflow server", lambda until: store.stop(_left(until)))


# --------------------------------------------------------------------------- the launch
def _open_launch(
    sweep: Sweep, store: _Store, state: dict[str, Any], state_file: Path, *, resume: bool, resume_command: str
) -> tuple[Any, SweepContext]:
    """The store ready, the experiment, the parent run and the launch record: ``(client, ctx)``."""
    from mlflow.tracking import MlflowClient

    from spot import tracking
    from spot.tracking.processes import close_dead_runs

    sweep_id = state["sweep_id"]
    _check_gpus(sweep)
    store.wait_ready()
    client = MlflowClient(store.uri)
    exp_id = tracking.experiment_id(sweep.experiment, store.uri)
    close_dead_runs(client, [exp_id])
    parent_id = _open_parent(client, exp_id, sweep, state, resume=resume)
    ctx = SweepContext(
        sweep_id,
        sweep.name,
        sweep.experiment,
        exp_id,
        parent_id,
        store.uri,
        sweep.axis_keys,
        fast_compile=sweep.fast_compile,
    )
    if not resume:
        tmp = state_file.with_name(f"{state_file.name}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(state, indent=2))
        tmp.replace(state_file)  # whole or not at all
    print(
        f"MLflow experiment '{sweep.experiment}' (id {exp_id}) at {store.uri}; parent run {parent_id}\n"
        f"Ray storage {state_file.parent / sweep_id}; if interrupted: {resume_command}",
        flush=True,
    )
    return client, ctx


def _close_launch(
    store: _Store, ctx: SweepContext, reason: str, resume_command: str, deadline: float | None = None
) -> None:
    """Mark the runs the launch left RUNNING, and the parent run, KILLED with ``reason``: through the
    server, or through the SQLite store itself when spot's server is gone or does not answer
    (:func:`_close_runs`; ``deadline``: a ``time.monotonic()`` value)."""
    where = _close_runs(store, ctx, reason, deadline)
    _say(
        f"{reason}: the runs it left RUNNING and its parent run {ctx.parent_run_id} are marked KILLED{where}; "
        f"to continue: {resume_command}"
    )


def _run_launch(
    sweep: Sweep,
    store: _Store,
    state: dict[str, Any],
    state_file: Path,
    *,
    resume: bool,
    retry_errored: bool,
    address: str | None,
    max_concurrent: int | None,
    run_fn: RunFn | None,
    resume_command: str,
) -> tuple[Any, SweepContext, dict[str, str], bool]:
    """Ray, the parent run and the Tune experiment; returns ``(client, ctx, ray errors, interrupted)``.

    Once the parent run exists, however the launch ends, the runs its trials left RUNNING are
    closed (KILLED) before this returns or raises.
    """

    from spot import tracking

    sweep_id = state["sweep_id"]
    started_ray = _init_ray(address)  # a SIGTERM while Ray starts takes Ray's own handler (exit)
    client = ctx = None

    def close(reason: str, deadline: float | None = None) -> None:
        if ctx is not None:
            _close_launch(store, ctx, reason, resume_command, deadline)

    # The trials first (a SIGTERM to the driver alone leaves them running), then the runs, while the
    # MLflow server is up (it is in its own session: a SIGTERM to the group leaves it), then Ray.
    reason = "launch crashed"
    with _on_sigterm(lambda: _sigterm_cleanup(store, close, started_ray)):
        try:
            if run_fn is None:  # after Ray's processes are started: forking them once JAX runs here warns
                prebuild_datasets(sweep)
            client, ctx = _open_launch(sweep, store, state, state_file, resume=resume, resume_command=resume_command)
            errors, interrupted = _fit(
                sweep,
                ctx,
                state_file.parent / sweep_id,
                resume=resume,
                retry_errored=retry_errored,
                max_concurrent=max_concurrent,
                run_fn=run_fn,
                died=store.died,
            )
            reason = store.died()  # "" unless the server died: Tune stopped the trials (_watching_server)
        except KeyboardInterrupt:
            reason = "launch stopped by SIGINT"
            raise
        except Exception:
            if store.died():  # whatever failed, the server's death is the cause to report
                reason = store.died()
                raise _server_died_error(store, ctx, resume_command) from None
            raise
        finally:
            if started_ray:
                import ray

                ray.shutdown()  # every trial process is gone after this: RUNNING runs are orphans
            if reason:
                close(reason)
        if store.died():
            raise _server_died_error(store, ctx, resume_command)
        tracking.close_orphans(
            client,
            ctx.experiment_id,
            {"sweep_id": sweep_id},
            "launch interrupted" if interrupted else "trial process ended without closing its run",
            keep=(ctx.parent_run_id,),
        )
    return client, ctx, errors, interrupted


def run_sweep(
    path: str | Path,
    *,
    smoke: bool = False,
    resume: bool = False,
    retry_errored: bool = False,
    address: str | None = None,
    max_concurrent: int | None = None,
    tracking_uri: str | None = None,
    storage: str | Path = DEFAULT_STORAGE,
    workdir: str | Path | None = None,
    run_fn: RunFn | None = None,
    store: str | None = None,
    tracking_host: str | None = None,
) -> list[Row]:
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
      store: URI of the store the nodes share datasets and stage entries through (:mod:`spot.store`);
        default: the file's ``store:``, else ``$SPOT_STORE``, else none (local folders).
      tracking_host: with ``address`` and no server URI: bind the MLflow server spot starts to this
        address (e.g. ``0.0.0.0``) so that trials on other nodes reach it; default loopback.
    """
    from spot import tracking

    if retry_errored and not resume:
        raise SpotError("--retry-errored goes with --resume")
    if max_concurrent is not None and (isinstance(max_concurrent, bool) or max_concurrent < 1):
        raise SpotError(f"--max-concurrent {max_concurrent}: expected a positive number of trials")
    sweep = load(path, smoke=smoke)
    _check_tracking_uri(tracking.given_uri(tracking_uri))  # before anything is written
    _check_tracking_host(tracking_host, address or os.environ.get("RAY_ADDRESS"), tracking_uri)
    root = Path(workdir or Path.cwd()).resolve() / tracking.SWEEP_STORE.parent
    state_file = record_file(sweep, storage)
    with _launch_lock(state_file, sweep.experiment), _shared_store(sweep, store):
        return _launch(
            sweep,
            path,
            state_file,
            root,
            smoke=smoke,
            resume=resume,
            retry_errored=retry_errored,
            address=address,
            max_concurrent=max_concurrent,
            tracking_uri=tracking_uri,
            run_fn=run_fn,
            tracking_host=tracking_host,
        )


@contextlib.contextmanager
def _shared_store(sweep: Sweep, uri: str | None) -> Iterator[None]:
    """``$SPOT_STORE`` (and its options) for the launch: ``uri``, else the file's ``store:``, else as
    set; the driver builds and uploads datasets there and Ray passes it to every trial."""
    from spot import store as store_lib

    uri = uri or sweep.store
    env = store_lib.environment(uri, dict(sweep.store_options)) if uri else {}
    old = {k: os.environ.get(k) for k in (store_lib.ENV_URI, store_lib.ENV_OPTIONS)}
    if env:
        os.environ.pop(store_lib.ENV_OPTIONS, None)
        os.environ.update(env)
    named = store_lib.configured()
    print(
        f"store: {named[0]} (datasets and stage entries shared by every node)"
        if named
        else "store: none (datasets and stage entries in each node's local folders)",
        flush=True,
    )
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _launch_lock(state_file: Path, experiment: str) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``<storage>/<experiment>.lock`` for the launch: a second
    launch (or ``--resume``) of the same sweep with the same storage refuses while one runs, so
    no launch overwrites another's record. The lock dies with the process, however it ends."""
    lock_path = lock_file(state_file)
    try:
        state_file.parent.mkdir(parents=True, exist_ok=True)
        f = open(lock_path, "a+")
    except OSError as e:
        raise SpotError(f"--storage {state_file.parent}: cannot keep the launch record there ({e.strerror})") from None
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise SpotError(
                f"sweep '{experiment}' is already running with storage {state_file.parent} "
                f"({holder}); wait for it to end, or give this launch another --storage"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        f.flush()
        yield


def _announce(
    sweep: Sweep,
    state: dict[str, Any],
    state_file: Path,
    path: str | Path,
    *,
    smoke: bool,
    resume: bool,
    address: str | None,
    max_concurrent: int | None,
    tracking_uri: str | None,
    tracking_host: str | None = None,
) -> tuple[str | None, str]:
    """What the launch is (printed), the Ray address it uses and its resume command; refuses a
    trial that asks for more CPUs than a local machine has."""
    from spot import tracking

    if resume:
        print(
            f"resuming launch {state['sweep_id']} (parent run {state['parent_run_id']}, record {state_file})",
            flush=True,
        )
    if resume and max_concurrent is not None:
        print("note: --max-concurrent is ignored on --resume (the restored launch keeps its setting)")
    command = f"spot sweep {path}{' --smoke' if smoke else ''} --resume"
    print(
        f"sweep '{sweep.experiment}' ({state['sweep_id']}): {len(sweep.trials())} trials, {len(sweep.runs())} runs "
        f"(seed_mode {sweep.seed_mode}, {sweep.resources['cpu']:g} CPU / {sweep.resources['gpu']:g} GPU per trial)",
        flush=True,
    )
    if not address and os.environ.get("RAY_ADDRESS"):
        address = os.environ["RAY_ADDRESS"]  # Ray's own convention (set inside `ray job submit`)
        print(
            f"note: running on the Ray cluster at RAY_ADDRESS={address}; unset RAY_ADDRESS for a local sweep",
            flush=True,
        )
    if address and not tracking.given_uri(tracking_uri) and not tracking_host:
        print(
            "note: trials on other nodes cannot reach the loopback MLflow server; pass "
            "--tracking-uri http://<host>:<port> of a server every node can reach, or --tracking-host "
            "to expose the one spot starts",
            flush=True,
        )
    if not address and sweep.resources["cpu"] > (os.cpu_count() or 1):  # before datasets are built
        raise SpotError(
            f"sweep file '{sweep.path}': resources.cpu = {sweep.resources['cpu']:g} per trial, but the "
            f"largest node of the Ray cluster has {os.cpu_count()} CPUs; ask for at most {os.cpu_count()}"
        )
    return address, command


def _launch(
    sweep: Sweep,
    path: str | Path,
    state_file: Path,
    root: Path,
    *,
    smoke: bool,
    resume: bool,
    retry_errored: bool,
    address: str | None,
    max_concurrent: int | None,
    tracking_uri: str | None,
    run_fn: RunFn | None,
    tracking_host: str | None = None,
) -> list[Row]:
    """:func:`run_sweep` once the launch holds its lock."""

    state = _state(sweep, path, state_file, resume=resume)
    address, command = _announce(
        sweep,
        state,
        state_file,
        path,
        smoke=smoke,
        resume=resume,
        address=address,
        max_concurrent=max_concurrent,
        tracking_uri=tracking_uri,
        tracking_host=tracking_host,
    )
    # a served store starts while Ray and datasets do
    with _tracking_store(tracking_uri, root, tracking_host, address) as store:
        client, ctx, errors, interrupted = _run_launch(
            sweep,
            store,
            state,
            state_file,
            resume=resume,
            retry_errored=retry_errored,
            address=address,
            max_concurrent=max_concurrent or sweep.max_concurrent,
            run_fn=run_fn,
            resume_command=command,
        )

        def close(reason: str, deadline: float | None = None) -> None:  # Ray is down: the parent run, if open
            _close_runs(store, ctx, reason, deadline)

        with _on_sigterm(lambda: _sigterm_cleanup(store, close, started_ray=False)), _server_death(store, ctx, command):
            rows = summarize(sweep, client, ctx.experiment_id, ctx.sweep_id, errors)
            table = format_summary(rows, sweep.axis_keys)
            timing = breakdown_text(client, ctx.parent_run_id, rows, sweep.axis_keys)
            _close_parent(client, ctx, rows, table, interrupted=interrupted)
        n_done = sum(r.status == "FINISHED" for r in rows)
        paper = paper_table(sweep, store.uri, ctx.sweep_id, state_file.parent) if sweep.table and n_done else ""
    _print_outcome(sweep, store, ctx, rows, table, timing, paper, command)
    if interrupted:  # Tune stopped on Ctrl-C (SIGINT) and returned with trials unfinished
        raise Interrupted(signal.SIGINT)
    return rows


def _print_outcome(
    sweep: Sweep, store: Any, ctx: Any, rows: list[Row], table: str, timing: str, paper: str, command: str
) -> None:
    """The end of a launch's output: the summary table, how to open the runs, what is missing."""
    from spot import tracking

    n_done = sum(r.status == "FINISHED" for r in rows)
    link = (
        f"\nthen open the sweep's runs: {tracking.ui.sweep_url(ctx.experiment_id, ctx.sweep_id, store.link_base)}"
        if store.link_base
        else ""
    )
    missing = (
        ""
        if n_done == len(rows)
        else (f"\nto run what is missing: {command} (add --retry-errored to run failed trials again)")
    )
    print(
        f"\n{table}\n\n{n_done}/{len(rows)} runs finished. Experiment '{sweep.experiment}', "
        f"filter: tags.sweep_id = {tracking.quote(ctx.sweep_id)}\n{store.how_to_open}{link}{missing}",
        flush=True,
    )
    if timing:
        print(f"\n{timing}", flush=True)
    if paper:
        print(f"\n{paper}", flush=True)
