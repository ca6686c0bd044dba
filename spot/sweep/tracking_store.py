"""The tracking store of a launch: a server given by URI, or a SQLite store served through a
loopback ``mlflow server`` (:mod:`spot.sweep.mlflow_server`); the watch on that server while Tune
runs, and closing the launch's runs through it or, when it is gone, through the store itself.

Hangs and deadlines (issue 43): while Tune runs, a thread polls the MLflow server the launch started
(:func:`watching_server`); if it dies, the launch stops its trials as Ctrl-C does, closes the runs
through the SQLite store itself (:func:`close_runs`) and ends with one error naming the server
(:func:`server_died_error`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from spot import SpotError
from spot.sweep.signals import say
from spot.sweep.trial import SweepContext
from spot.sweep.uris import LOOPBACK, advertised_host, check_tracking_uri


@dataclass(frozen=True)
class Store:
    """The launch's store: ``uri()`` (a served store's port may change while it starts, see
    :meth:`spot.sweep.mlflow_server.MlflowServer.wait_ready`), how to open it, and its server's
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


SERVER_POLL_S = 1.0  # how often the launch checks, while Tune runs, that its MLflow server still runs
DIRECT_CLOSE_S = 10.0  # of "closing the runs": kept for closing them through the SQLite store itself


@contextlib.contextmanager
def tracking_store(uri: str | None, root: Path, host: str | None = None, address: str | None = None) -> Iterator[Store]:
    """The tracking store of a launch; a SQLite store is served by a loopback server (bound to
    ``host`` instead, for a cluster sweep's ``--tracking-host``).

    The server starts here but is only waited for by ``wait_ready()``, so that Ray can start
    meanwhile.
    """
    from spot import tracking
    from spot.sweep import mlflow_server

    uri = check_tracking_uri(tracking.given_uri(uri))
    if uri and not uri.startswith("sqlite:"):
        if uri.startswith(("http://", "https://")):
            mlflow_server.check_reachable(uri)  # before Ray starts: a clear error within seconds
        link = uri if uri.startswith(("http://", "https://")) else ""
        yield Store(lambda: uri, f"MLflow: {uri}", lambda: None, link_base=link)
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
        advertise=advertised_host(bind, address),
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
        yield Store(
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


@contextlib.contextmanager
def watching_server(died: Callable[[], str], poll_s: float = SERVER_POLL_S) -> Iterator[None]:
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
                say(f"{death}; stopping the trials, then closing their runs through the store")
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


def server_died_error(store: Store, ctx: SweepContext | None, resume_command: str) -> SpotError:
    """The launch's one error when its MLflow server died (its runs are closed by then)."""
    log = f" (the server's log: {store.log_path})" if store.log_path else ""
    if ctx is None:
        return SpotError(f"{store.died()} before the sweep's runs were opened{log}; start the launch again")
    return SpotError(
        f"{store.died()} while the sweep ran{log}: its trials were stopped, and the runs they left RUNNING "
        f"and the parent run {ctx.parent_run_id} are marked KILLED in {store.backend}; to continue: {resume_command}"
    )


@contextlib.contextmanager
def server_death(store: Store, ctx: SweepContext, resume_command: str) -> Iterator[None]:
    """An error in the block, while the launch's MLflow server has died, becomes
    :func:`server_died_error`, the runs closed through the store first."""
    try:
        yield
    except Exception:
        if not store.died():
            raise
        close_runs(store, ctx, store.died())
        raise server_died_error(store, ctx, resume_command) from None


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


def close_runs(store: Store, ctx: SweepContext, reason: str, deadline: float | None = None) -> str:
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
        say(f"note: closing the runs through {store.uri} failed ({type(e).__name__}: {e}); using {store.backend}")
        _close_in(store.backend, ctx, reason, None)
        return f" in {store.backend} (the server did not answer)"
