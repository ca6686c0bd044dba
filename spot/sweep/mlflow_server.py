"""A loopback MLflow tracking server for one sweep launch.

Several Ray trials logging at once must not write one SQLite file directly (concurrent writers hit
``database is locked`` and race on schema migrations, see docs/sweeps.md). ``spot sweep`` therefore
puts one ``mlflow server`` process in front of the store and gives the trials its HTTP URI:

    mlflow server --host 127.0.0.1 --port <free> --workers 1 \\
        --backend-store-uri sqlite:///<root>/mlflow.db --artifacts-destination <root>/artifacts

Before the server starts, the driver creates or migrates the store itself (under a file lock,
:func:`spot.tracking.locking.prepare_store`) and writes a random nonce into it (a tag of the
Default experiment); :meth:`MlflowServer.wait_ready` accepts the server only once ``/health``
answers *and* the nonce reads back through the server's REST API, so a process that took the
port between :func:`free_port` and the server's bind (``mlflow server`` cannot be handed a bound
socket) never receives a run: the server is started again on another port, up to three times.

The server runs with MLflow's telemetry off (``MLFLOW_DISABLE_TELEMETRY=true`` unless the
environment sets it), job execution off (``MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false``) and one
worker, in its own session (a Ctrl-C in the terminal reaches the sweep driver, which then still
needs the server to mark runs), and with ``PR_SET_PDEATHSIG`` so that it also stops when the driver
is killed with ``kill -9``. :meth:`MlflowServer.stop` sends SIGTERM (forwarded by ``mlflow server``
to its uvicorn child) and waits.

A server that dies on its own while a sweep runs (``kill -9``, out of memory) is reported by
:meth:`MlflowServer.died` (the sweep driver polls it while Tune runs, :mod:`spot.sweep.tracking_store`), which
also ends what is left of the server's process group (``mlflow server`` runs uvicorn as a child,
which would otherwise keep the port and the store).
"""

from __future__ import annotations

import ctypes
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from types import TracebackType

from spot import SpotError
from spot.tracking.store import check_reachable  # noqa: F401 (re-exported: the launch checks a server with it)

_PR_SET_PDEATHSIG = 1
NONCE_TAG = "spot.server_nonce."
"""Prefix of the tag (on experiment 0) that names one server start; removed once checked."""
ATTEMPTS = 3


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def sqlite_uri(db: Path) -> str:
    return f"sqlite:///{db.resolve()}"


def is_local_store(uri: str) -> bool:
    """True for URIs that name a store on this disk (SQLite file, file store, plain path).

    Such a store is served through :class:`MlflowServer` instead of being written by every trial.
    """
    return uri.startswith(("sqlite:", "file:")) or "://" not in uri


def _kill_group(pgid: int) -> None:
    """SIGKILL what is left of a process group (the server leads its own session); nothing if none."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: the server outlives a kill -9 of the driver
        pass


class MlflowServer:
    """``mlflow server`` on loopback in front of one backend store; a context manager.

    Args:
      backend_uri: the store, e.g. ``sqlite:////abs/spot_runs/mlflow.db``.
      artifacts: folder the server stores artifacts in (``--artifacts-destination``); trials
        upload through the server, so they never need the path themselves.
      log_path: file for the server's stdout/stderr (default ``<artifacts>/../mlflow-server.log``).
      host: the address the server binds (``--host``): loopback unless asked otherwise (a cluster
        sweep's ``--tracking-host``).
      advertise: the host name in :attr:`uri`, the address clients reach the server at (default
        ``host``; give it when ``host`` is ``0.0.0.0``).
    """

    def __init__(
        self,
        backend_uri: str,
        artifacts: Path,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        log_path: Path | None = None,
        advertise: str | None = None,
    ) -> None:
        self.backend_uri = backend_uri
        self.artifacts = artifacts.resolve()
        self.host = host
        self.advertise = advertise or host
        self.port = port or free_port(host)
        self.log_path = log_path or self.artifacts.parent / "mlflow-server.log"
        self._proc: subprocess.Popen[bytes] | None = None
        self.nonce = ""
        self._log_start = 0
        self._death = ""

    @property
    def uri(self) -> str:
        return f"http://{self.advertise}:{self.port}"

    def server_env(self) -> dict[str, str]:
        """The server's environment: ours, telemetry off unless set, no job execution, no
        tracking URI of its own."""
        env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
        env.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
        env.pop("MLFLOW_TRACKING_URI", None)
        return env

    def start(self, *, wait: bool = True, timeout: float = 120.0) -> None:
        """Prepare the store, write this start's nonce, start the server; with ``wait``, return
        once it is ready and verified (see :meth:`wait_ready`)."""
        self.artifacts.mkdir(parents=True, exist_ok=True)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._mark_store()
        self._spawn()
        if wait:
            self.wait_ready(timeout)

    def _mark_store(self) -> None:
        """Create/migrate the store (locked) and put this start's nonce in it."""
        from mlflow.tracking import MlflowClient

        from spot.tracking.locking import prepare_store

        prepare_store(self.backend_uri)
        self.nonce = secrets.token_hex(16)
        MlflowClient(self.backend_uri).set_experiment_tag("0", NONCE_TAG + self.nonce, self.nonce)

    def _spawn(self) -> None:
        cmd = [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--host",
            self.host,
            "--port",
            str(self.port),
            "--workers",
            "1",
            "--backend-store-uri",
            self.backend_uri,
            "--artifacts-destination",
            str(self.artifacts),
        ]
        self._log_start = self.log_path.stat().st_size if self.log_path.exists() else 0
        with open(self.log_path, "ab") as log:
            self._proc = subprocess.Popen(
                cmd,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=self.server_env(),
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Wait until the server answers ``/health`` and knows this start's nonce.

        If the port turns out to belong to another process (our server could not bind it, or
        something else answers there without the nonce), the server is started again on a new
        port (:attr:`uri` changes), at most :data:`ATTEMPTS` times in all. Raises SpotError with
        the log tail if the server died or hung, or the port was taken every time.
        """
        if self._proc is None:
            raise SpotError("mlflow server was not started")
        taken = []
        for _ in range(ATTEMPTS):
            problem = self._wait_verified(timeout)
            if problem is None:
                self._unmark_store()
                return
            taken.append(problem)
            self.stop()
            self.port = free_port(self.host)
            print(f"note: {problem}; starting the mlflow server again on port {self.port}", file=sys.stderr, flush=True)
            self._spawn()
        self.stop()
        raise SpotError("could not start the mlflow server on a port of its own: " + "; ".join(taken))

    def _wait_verified(self, timeout: float) -> str | None:
        """None once the server is ready and verified; a description if the port is someone else's."""
        assert self._proc is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                tail = self._log_tail(since=self._log_start)
                if "address already in use" in tail.lower():
                    return f"port {self.port} was taken by another process before the server bound it"
                raise SpotError(
                    f"mlflow server exited with code {self._proc.returncode} before it was "
                    f"ready; its log ({self.log_path}) ends with:\n{tail}"
                )
            if self.healthy():
                if self.served_nonce() == self.nonce:
                    return None
                return (
                    f"port {self.port} answers /health but not as the server spot started (it does not "
                    "know this start's nonce)"
                )
            time.sleep(0.5)
        self.stop()
        raise SpotError(
            f"mlflow server on {self.uri} did not answer /health within {timeout:.0f} s; "
            f"its log ({self.log_path}) ends with:\n{self._log_tail()}"
        )

    def served_nonce(self) -> str | None:
        """The nonce tag of experiment 0 as the process on :attr:`uri` reports it (None if it
        does not answer like an MLflow server or has no such tag)."""
        url = f"{self.uri}/api/2.0/mlflow/experiments/get?" + urllib.parse.urlencode({"experiment_id": "0"})
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                tags = json.loads(resp.read(1 << 20))["experiment"].get("tags", [])
        except (urllib.error.URLError, OSError, ValueError, KeyError, TypeError, AttributeError):
            return None
        if not isinstance(tags, list):
            return None
        values = [t.get("value") for t in tags if isinstance(t, dict) and t.get("key") == NONCE_TAG + self.nonce]
        return values[0] if values else None

    def _unmark_store(self) -> None:
        from mlflow.tracking import MlflowClient

        try:
            MlflowClient(self.backend_uri).delete_experiment_tag("0", NONCE_TAG + self.nonce)
        except Exception:  # noqa: BLE001 - a leftover tag is harmless
            pass

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.uri}/health", timeout=2) as resp:
                return resp.status == 200
        except (urllib.error.URLError, OSError):
            return False

    @property
    def pid(self) -> int | None:
        """The ``mlflow server`` process's id (None before :meth:`start` and after :meth:`stop`)."""
        proc = self._proc
        return proc.pid if proc is not None else None

    def died(self) -> str:
        """``""`` while the server runs (or after :meth:`stop`); once it ended on its own, a sentence
        saying so (``the MLflow server at URI (pid N) died (killed by SIGKILL)``; the same sentence
        at every later call). What was left of its process group is killed."""
        proc = self._proc
        if self._death or proc is None or proc.poll() is None:
            return self._death
        code = proc.returncode
        try:
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
        except ValueError:
            how = f"exit code {code}"
        self._death = f"the MLflow server at {self.uri} (pid {proc.pid}) died ({how})"
        _kill_group(proc.pid)
        return self._death

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM the server and wait for it (SIGKILL after ``timeout``); a server that died on its
        own has what is left of its process group killed."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is not None:
            if not self._death:  # (died() has killed the group already)
                _kill_group(proc.pid)  # its uvicorn child outlives a kill -9 of `mlflow server`
            return
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the server leads its own session
            proc.wait()

    def _log_tail(self, lines: int = 20, since: int = 0) -> str:
        try:
            with open(self.log_path, "rb") as f:
                f.seek(since)
                text = f.read().decode(errors="replace")
            return "\n".join(text.splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def __enter__(self) -> MlflowServer:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
