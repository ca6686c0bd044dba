"""A loopback MLflow tracking server for one sweep launch.

Several Ray trials logging at once must not write one SQLite file directly (concurrent writers hit
``database is locked`` and race on schema migrations, see docs/sweeps.md). ``spot sweep`` therefore
puts one ``mlflow server`` process in front of the store and gives the trials its HTTP URI:

    mlflow server --host 127.0.0.1 --port <free> --workers 1 \\
        --backend-store-uri sqlite:///<root>/mlflow.db --artifacts-destination <root>/artifacts

The server runs with job execution off (``MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false``) and one
worker, in its own session (a Ctrl-C in the terminal reaches the sweep driver, which then still
needs the server to mark runs), and with ``PR_SET_PDEATHSIG`` so that it also stops when the driver
is killed with ``kill -9``. :meth:`MlflowServer.stop` sends SIGTERM (forwarded by ``mlflow server``
to its uvicorn child) and waits.
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import TracebackType

from spot import SpotError

_PR_SET_PDEATHSIG = 1


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


def ui_command(backend_uri: str, artifacts: Path) -> str:
    """The command that shows a finished sweep's runs (``mlflow ui`` on the same store)."""
    return f"mlflow ui --backend-store-uri {backend_uri} --artifacts-destination {artifacts}"


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
    """

    def __init__(self, backend_uri: str, artifacts: Path, *, host: str = "127.0.0.1",
                 port: int | None = None, log_path: Path | None = None) -> None:
        self.backend_uri = backend_uri
        self.artifacts = artifacts.resolve()
        self.host = host
        self.port = port or free_port(host)
        self.log_path = log_path or self.artifacts.parent / "mlflow-server.log"
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def uri(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self, *, wait: bool = True, timeout: float = 120.0) -> None:
        """Start the server; with ``wait``, return once it is ready (see :meth:`wait_ready`)."""
        self.artifacts.mkdir(parents=True, exist_ok=True)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "mlflow", "server", "--host", self.host, "--port", str(self.port),
               "--workers", "1", "--backend-store-uri", self.backend_uri,
               "--artifacts-destination", str(self.artifacts)]
        env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
        env.pop("MLFLOW_TRACKING_URI", None)
        with open(self.log_path, "ab") as log:
            self._proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                          start_new_session=True, preexec_fn=_die_with_parent)
        if wait:
            self.wait_ready(timeout)

    def wait_ready(self, timeout: float = 120.0) -> None:
        """Wait until ``/health`` answers; raise SpotError with the log tail if the server died or hung."""
        if self._proc is None:
            raise SpotError("mlflow server was not started")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise SpotError(f"mlflow server exited with code {self._proc.returncode} before it was "
                                f"ready; its log ({self.log_path}) ends with:\n{self._log_tail()}")
            if self.healthy():
                return
            time.sleep(0.5)
        self.stop()
        raise SpotError(f"mlflow server on {self.uri} did not answer /health within {timeout:.0f} s; "
                        f"its log ({self.log_path}) ends with:\n{self._log_tail()}")

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.uri}/health", timeout=2) as resp:
                return resp.status == 200
        except (urllib.error.URLError, OSError):
            return False

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM the server and wait for it (SIGKILL after ``timeout``)."""
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the server leads its own session
            proc.wait()

    def _log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def __enter__(self) -> MlflowServer:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
