"""The driver of a launch (``spot sweep FILE``): the flow from the file to the summary.

:func:`run_sweep` validates the file, builds the datasets the runs need, serves a SQLite store
through a loopback ``mlflow server`` unless given a server's URI (:mod:`spot.sweep.tracking_store`),
starts Ray, creates the experiment and the parent run (:mod:`spot.sweep.parent`), runs one Tune
experiment (:mod:`spot.sweep.tune`), closes the runs it left RUNNING, and logs and prints the
summary. ``--resume`` restores the Ray experiment recorded in ``<storage>/<experiment>.json``
(:mod:`spot.sweep.launch_record`).

Hangs and deadlines (issue 43): while Tune runs, the MLflow server the launch started is watched
(:func:`spot.sweep.tracking_store.watching_server`); if it dies, the launch stops its trials as
Ctrl-C does, closes the runs through the SQLite store itself and ends with one error naming the
server. A SIGTERM's cleanup runs in steps, each with its own deadline and message
(:func:`spot.sweep.signals.sigterm_cleanup`), and closes the runs through the store directly when
the server is gone or does not answer.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from spot import SpotError
from spot import config as config_lib
from spot.sweep import search as search_lib
from spot.sweep.launch_record import launch_lock, launch_state, record_file, write_record
from spot.sweep.parent import close_parent, open_parent
from spot.sweep.signals import Interrupted, on_sigterm, say, sigterm_cleanup
from spot.sweep.spec import Sweep, load
from spot.sweep.summary import Row, breakdown_text, format_summary, paper_table, summarize
from spot.sweep.tracking_store import Store, close_runs, server_death, server_died_error, tracking_store
from spot.sweep.trial import RunFn, SweepContext
from spot.sweep.tune import check_gpus, fit, init_ray
from spot.sweep.uris import check_tracking_host, check_tracking_uri

DEFAULT_STORAGE = Path("spot_runs") / "ray"


def prebuild_datasets(sweep: Sweep, progress: bool = True) -> list[Path]:
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
        paths.append(registry.build(name, size, seed, progress=progress))
    return paths


def _open_launch(
    sweep: Sweep, store: Store, state: dict[str, Any], state_file: Path, *, resume: bool, resume_command: str
) -> tuple[Any, SweepContext]:
    """The store ready, the experiment, the parent run and the launch record: ``(client, ctx)``."""
    from mlflow.tracking import MlflowClient

    from spot import tracking
    from spot.tracking.processes import close_dead_runs

    sweep_id = state["sweep_id"]
    check_gpus(sweep)
    store.wait_ready()
    client = MlflowClient(store.uri)
    exp_id = tracking.experiment_id(sweep.experiment, store.uri)
    close_dead_runs(client, [exp_id])
    parent_id = open_parent(client, exp_id, sweep, state, resume=resume)
    ctx = SweepContext(
        sweep_id,
        sweep.name,
        sweep.experiment,
        exp_id,
        parent_id,
        store.uri,
        sweep.axis_keys,
        fast_compile=sweep.fast_compile,
        metric=sweep.metric,
        stopper=search_lib.STOPPER_NAMES[sweep.scheduler.name] if sweep.scheduler else "",
    )
    if not resume:
        write_record(state_file, state)
    print(
        f"MLflow experiment '{sweep.experiment}' (id {exp_id}) at {store.uri}; parent run {parent_id}\n"
        f"Ray storage {state_file.parent / sweep_id}; if interrupted: {resume_command}",
        flush=True,
    )
    return client, ctx


def _close_launch(
    store: Store, ctx: SweepContext, reason: str, resume_command: str, deadline: float | None = None
) -> None:
    """Mark the runs the launch left RUNNING, and the parent run, KILLED with ``reason``: through the
    server, or through the SQLite store itself when spot's server is gone or does not answer
    (:func:`close_runs`; ``deadline``: a ``time.monotonic()`` value)."""
    where = close_runs(store, ctx, reason, deadline)
    say(
        f"{reason}: the runs it left RUNNING and its parent run {ctx.parent_run_id} are marked KILLED{where}; "
        f"to continue: {resume_command}"
    )


def _run_launch(
    sweep: Sweep,
    store: Store,
    state: dict[str, Any],
    state_file: Path,
    *,
    resume: bool,
    retry_errored: bool,
    address: str | None,
    max_concurrent: int | None,
    run_fn: RunFn | None,
    resume_command: str,
    quiet: bool = False,
) -> tuple[Any, SweepContext, dict[str, str], bool]:
    """Ray, the parent run and the Tune experiment; returns ``(client, ctx, ray errors, interrupted)``.

    Once the parent run exists, however the launch ends, the runs its trials left RUNNING are
    closed (KILLED) before this returns or raises.
    """

    from spot import tracking

    sweep_id = state["sweep_id"]
    started_ray = init_ray(address)  # a SIGTERM while Ray starts takes Ray's own handler (exit)
    client = ctx = None

    def close(reason: str, deadline: float | None = None) -> None:
        if ctx is not None:
            _close_launch(store, ctx, reason, resume_command, deadline)

    # The trials first (a SIGTERM to the driver alone leaves them running), then the runs, while the
    # MLflow server is up (it is in its own session: a SIGTERM to the group leaves it), then Ray.
    reason = "launch crashed"
    with on_sigterm(lambda: sigterm_cleanup(store, close, started_ray)):
        try:
            if run_fn is None:  # after Ray's processes are started: forking them once JAX runs here warns
                prebuild_datasets(sweep, progress=not quiet)
            client, ctx = _open_launch(sweep, store, state, state_file, resume=resume, resume_command=resume_command)
            errors, interrupted = fit(
                sweep,
                ctx,
                state_file.parent / sweep_id,
                resume=resume,
                retry_errored=retry_errored,
                max_concurrent=max_concurrent,
                run_fn=run_fn,
                died=store.died,
            )
            reason = store.died()  # "" unless the server died: Tune stopped the trials (watching_server)
        except KeyboardInterrupt:
            reason = "launch stopped by SIGINT"
            raise
        except Exception:
            if store.died():  # whatever failed, the server's death is the cause to report
                reason = store.died()
                raise server_died_error(store, ctx, resume_command) from None
            raise
        finally:
            if started_ray:
                import ray

                ray.shutdown()  # every trial process is gone after this: RUNNING runs are orphans
            if reason:
                close(reason)
        if store.died():
            raise server_died_error(store, ctx, resume_command)
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
    quiet: bool = False,
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
      quiet: no progress bars (``--quiet``: the datasets the driver builds, the configs' check).
    """
    from spot import tracking

    if retry_errored and not resume:
        raise SpotError("--retry-errored goes with --resume")
    if max_concurrent is not None and (isinstance(max_concurrent, bool) or max_concurrent < 1):
        raise SpotError(f"--max-concurrent {max_concurrent}: expected a positive number of trials")
    sweep = load(path, smoke=smoke, progress=False if quiet else None)
    check_tracking_uri(tracking.given_uri(tracking_uri))  # before anything is written
    check_tracking_host(tracking_host, address or os.environ.get("RAY_ADDRESS"), tracking_uri)
    root = Path(workdir or Path.cwd()).resolve() / tracking.SWEEP_STORE.parent
    state_file = record_file(sweep, storage)
    with launch_lock(state_file, sweep.experiment), _shared_store(sweep, store):
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
            quiet=quiet,
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
    n_trials, n_runs = search_lib.counts(sweep)
    print(
        f"sweep '{sweep.experiment}' ({state['sweep_id']}): {n_trials} trials, {n_runs} runs "
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
    quiet: bool = False,
) -> list[Row]:
    """:func:`run_sweep` once the launch holds its lock."""

    state = launch_state(sweep, path, state_file, resume=resume)
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
    with tracking_store(tracking_uri, root, tracking_host, address) as store:
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
            quiet=quiet,
        )

        def close(reason: str, deadline: float | None = None) -> None:  # Ray is down: the parent run, if open
            close_runs(store, ctx, reason, deadline)

        with on_sigterm(lambda: sigterm_cleanup(store, close, started_ray=False)), server_death(store, ctx, command):
            rows = summarize(sweep, client, ctx.experiment_id, ctx.sweep_id, errors)
            table = format_summary(rows, sweep.axis_keys)
            timing = breakdown_text(client, ctx.parent_run_id, rows, sweep.axis_keys)
            close_parent(client, ctx, rows, table, interrupted=interrupted)
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
        f"filter: tags.spot.sweep_id = {tracking.quote(ctx.sweep_id)}\n{store.how_to_open}{link}{missing}",
        flush=True,
    )
    if timing:
        print(f"\n{timing}", flush=True)
    if paper:
        print(f"\n{paper}", flush=True)
