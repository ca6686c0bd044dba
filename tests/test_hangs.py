"""No silent hang on MLflow (issue 43, finding 4; and finding 7's failure_reason).

* Every MLflow HTTP request of spot's processes has a deadline (``MLFLOW_HTTP_REQUEST_TIMEOUT`` and
  ``MLFLOW_HTTP_REQUEST_MAX_RETRIES``, set unless the user set them), and a request that gets no
  answer is one line naming the server, the request and what spot was doing. The tests use a
  loopback server that answers ``/health`` and stalls on everything else, with 1 s deadlines.
* A sweep whose MLflow server is killed (``kill -9``) stops its trials, closes the runs through the
  SQLite store and exits with one error; ``--resume`` then finishes them (the fault test, slow).
* A SIGTERM's cleanup runs in steps, each with its deadline and message, and closes the runs through
  the store itself when the server does not answer.
* ``failure_reason`` is capped at 1,000 characters with a note of what was left out.
"""

from __future__ import annotations

import http.server
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from spot import SpotError, config, tracking
from spot.sweep.mlflow_server import free_port, sqlite_uri
from spot.tracking import limits

HERE = Path(__file__).resolve().parent
DEADLINES = {"MLFLOW_HTTP_REQUEST_TIMEOUT": "1", "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}


class _Stalling:
    """A loopback HTTP server that answers ``GET /health`` with 200 and holds every other request
    open, unanswered, until :meth:`close` (at most 120 s); records the requests."""

    def __init__(self) -> None:
        released = self.released = threading.Event()
        seen = self.requests = []

        class Handler(http.server.BaseHTTPRequestHandler):
            def _answer(self) -> None:
                seen.append(f"{self.command} {self.path}")
                if self.path == "/health":
                    self.send_response(200)
                    self.send_header("Content-Length", "2")
                    self.end_headers()
                    self.wfile.write(b"OK")
                    return
                released.wait(120)  # stall: no status line, no body

            do_GET = do_POST = do_PATCH = do_DELETE = _answer

            def log_message(self, *args) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.uri = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.released.set()
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def stalling():
    s = _Stalling()
    yield s
    s.close()


@pytest.fixture
def short_deadlines(monkeypatch):
    for key, value in DEADLINES.items():
        monkeypatch.setenv(key, value)


def _expected(uri: str, doing: str, failed: str, path: str, tries: int = 1, retries: int = 0) -> str:
    return (
        f"tracking server {uri} did not answer while spot was {doing}: {failed} to {path}, "
        f"{tries} tr{'y' if tries == 1 else 'ies'} (MLFLOW_HTTP_REQUEST_TIMEOUT=1 s, "
        f"MLFLOW_HTTP_REQUEST_MAX_RETRIES={retries}); check that the server runs and answers, or pass "
        "another --tracking-uri"
    )


# --------------------------------------------------------------------------- deadlines
def test_spot_sets_mlflow_deadlines_unless_the_user_did(monkeypatch):
    from mlflow.environment_variables import MLFLOW_HTTP_REQUEST_MAX_RETRIES, MLFLOW_HTTP_REQUEST_TIMEOUT

    for key in DEADLINES:
        monkeypatch.delenv(key, raising=False)
    limits.set_http_deadlines()
    # MLflow's own defaults are 120 s and 7 retries (about 20 minutes on a stalled server).
    assert (MLFLOW_HTTP_REQUEST_TIMEOUT.get(), MLFLOW_HTTP_REQUEST_MAX_RETRIES.get()) == (30, 2)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "7")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", " ")  # blank: unset
    limits.set_http_deadlines()
    assert (MLFLOW_HTTP_REQUEST_TIMEOUT.get(), MLFLOW_HTTP_REQUEST_MAX_RETRIES.get()) == (7, 2)


def test_spot_processes_get_the_deadlines_when_spot_tracking_is_imported():
    env = {k: v for k, v in os.environ.items() if k not in DEADLINES}
    code = f"import os, spot.tracking; print(*(os.environ[k] for k in {tuple(DEADLINES)!r}))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["30", "2"], out.stderr


def test_a_server_that_answers_health_then_stalls_is_one_error_within_the_deadline(stalling, short_deadlines):
    start = time.monotonic()
    with pytest.raises(limits.TrackingUnreachable) as got:
        tracking.experiment_id("e", stalling.uri)
    took = time.monotonic() - start
    path = "/api/2.0/mlflow/experiments/get-by-name"
    assert str(got.value) == _expected(stalling.uri, "looking up experiment 'e'", "no answer within 1 s", path)
    assert isinstance(got.value, SpotError) and 1 <= took < 10, took
    assert stalling.requests[0] == "GET /health" and stalling.requests[1].startswith(f"GET {path}?")


def test_retries_are_counted_in_the_message_and_in_the_wait(stalling, short_deadlines, monkeypatch):
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "1")
    from mlflow.tracking import MlflowClient

    start = time.monotonic()
    with pytest.raises(limits.TrackingUnreachable) as got:
        tracking.all_experiments(MlflowClient(stalling.uri))
    path = "/api/2.0/mlflow/experiments/search"
    expected = _expected(stalling.uri, "listing the experiments", "no answer within 1 s", path, tries=2, retries=1)
    assert str(got.value) == expected
    assert time.monotonic() - start >= 2  # two tries of 1 s each
    assert sum(r.startswith("POST /api/2.0/mlflow/experiments/search") for r in stalling.requests) == 2


def test_a_refused_connection_is_one_error_at_once(short_deadlines):
    from mlflow.tracking import MlflowClient

    uri = f"http://127.0.0.1:{free_port()}"
    start = time.monotonic()
    with pytest.raises(limits.TrackingUnreachable) as got:
        list(tracking.search_runs(MlflowClient(uri), ["1"], "tags.x = 'y'"))
    assert str(got.value) == _expected(uri, "searching runs", "connection refused", "/api/2.0/mlflow/runs/search")
    assert time.monotonic() - start < 10


def test_other_mlflow_errors_pass_unchanged(tmp_path):
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    client = MlflowClient(sqlite_uri(tmp_path / "m.db"))
    with pytest.raises(MlflowException) as got, limits.waiting_on("http://x", "reading"):
        client.get_run("0" * 32)
    assert limits.unreachable(got.value) is None and not isinstance(got.value, SpotError)


def test_spot_run_against_a_stalling_server_fails_with_one_line(tmp_path, stalling, tiny_drawer):
    from conftest import TINY_RUN, run_cli

    env = {**DEADLINES, "SPOT_DATA_DIR": os.environ["SPOT_DATA_DIR"], "SPOT_CACHE_DIR": str(tmp_path / "cache")}
    start = time.monotonic()
    out = run_cli(
        "run", *TINY_RUN, "method=oracle", f"tracking.uri={stalling.uri}", "tracking.experiment=h",
        cwd=tmp_path, env=env, timeout=300,
    )  # fmt: skip
    took = time.monotonic() - start
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-3000:]
    path = "/api/2.0/mlflow/experiments/get-by-name"
    expected = _expected(stalling.uri, "looking up experiment 'h'", "no answer within 1 s", path)
    assert out.stderr.strip().splitlines()[-1] == f"error: {expected}", out.stderr[-3000:]
    assert took < 120, took  # start-up and the dataset; the wait itself is 1 s


# --------------------------------------------------------------------------- trials
def _ctx(uri: str):
    from spot.sweep.trial import SweepContext

    return SweepContext("sw", "sw", "e", "1", "p" * 32, uri, ("iql.lr",))


def test_a_trial_whose_server_does_not_answer_ends_with_one_line(short_deadlines, monkeypatch):
    from spot.sweep import trial

    monkeypatch.setenv("MLFLOW_TRACKING_URI", "unused")  # run_trial sets it: restored after the test
    uri = f"http://127.0.0.1:{free_port()}"
    ran = []
    with pytest.raises(limits.TrackingUnreachable) as got:
        trial.run_trial(
            {"iql.lr": 0.1}, [0], _ctx(uri), trial_id="t", report=print, run_fn=lambda *a, **k: ran.append(1)
        )
    assert str(got.value) == _expected(uri, "looking up a run", "connection refused", "/api/2.0/mlflow/runs/search")
    assert ran == []


def test_a_failure_the_server_cannot_record_is_not_recorded_again(short_deadlines):
    from mlflow.tracking import MlflowClient

    from spot.sweep import trial

    uri = f"http://127.0.0.1:{free_port()}"
    try:
        MlflowClient(uri).get_run("0" * 32)
    except Exception as e:  # noqa: BLE001 - the error a run gets when its server is gone
        lost = e
    cfg = config.resolve({"seed": 0})

    class NoCalls:
        def __getattr__(self, name):
            raise AssertionError(f"called {name} on a server known to be gone")

    with pytest.raises(limits.TrackingUnreachable, match=r"while spot was running seed 0: connection refused"):
        trial._record_failure(NoCalls(), _ctx(uri), cfg, {"attempt": "a"}, lost, 0)


# --------------------------------------------------------------------------- failure_reason
def test_failure_reason_is_capped_with_a_note():
    listing = "\n".join(f"file_{i:05d}.hdf5" for i in range(1000))  # 15 chars a name, 999 newlines
    error = SpotError(f"no dataset here; the folder holds: {listing}")
    text = f"SpotError: no dataset here; the folder holds: {listing}"
    got = limits.failure_reason(error)
    assert got == text[:1000] + f"… ({len(text) - 1000} more chars)"
    assert len(text) - 1000 == 11 + 35 + 1000 * 15 + 999 - 1000  # "SpotError: ", the words, the names
    assert limits.failure_reason(ValueError("short")) == "ValueError: short"


def test_runs_record_capped_failure_reasons(tmp_path):
    from mlflow.tracking import MlflowClient

    uri = sqlite_uri(tmp_path / "m.db")
    cfg = config.resolve({"tracking.uri": uri, "tracking.experiment": "e"})
    error = SpotError("the folder holds: " + ", ".join(f"f{i}" for i in range(3000)))
    with pytest.raises(SpotError), tracking.start_run(cfg, {"name": "x"}, system_metrics=False) as tracker:
        raise error
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("e").experiment_id
    failed = tracking.record_failure(client, exp, cfg, {"attempt": "a"}, error)
    for run_id in (tracker.run_id, failed):
        reason = client.get_run(run_id).data.tags["failure_reason"]
        assert reason.startswith("SpotError: the folder holds: f0, f1, ")
        assert len(reason) < 1100 and re.search(r"… \(\d+ more chars\)$", reason), reason[-60:]


# --------------------------------------------------------------------------- closing a launch's runs
def _launch_store(db: Path) -> tuple:
    """A store with a sweep's parent run and two trial runs, all RUNNING, and one run of another sweep."""
    from mlflow.tracking import MlflowClient

    from spot.sweep.trial import SweepContext

    client = MlflowClient(sqlite_uri(db))
    exp = client.create_experiment("s")
    parent = client.create_run(exp, tags={"sweep_id": "sw", "spot.role": "sweep"}).info.run_id
    runs = [client.create_run(exp, tags={"sweep_id": "sw", "trial_key": k}).info.run_id for k in "ab"]
    other = client.create_run(exp, tags={"sweep_id": "another"}).info.run_id
    return client, SweepContext("sw", "sw", "s", exp, parent, "", ()), [parent, *runs], other


def test_runs_are_closed_through_the_store_when_the_server_died(tmp_path, capsys):
    from spot.sweep import launch, tracking_store

    client, ctx, ids, other = _launch_store(tmp_path / "m.db")
    gone = "the MLflow server at http://127.0.0.1:9 (pid 1234) died (killed by SIGKILL)"
    store = tracking_store.Store(
        lambda: "http://127.0.0.1:9", "", lambda: None, backend=sqlite_uri(tmp_path / "m.db"), died=lambda: gone
    )
    launch._close_launch(store, ctx, gone, "spot sweep s.yaml --resume")
    for run_id in ids:
        run = client.get_run(run_id)
        assert run.info.status == "KILLED" and run.data.tags["failure_reason"] == gone
    assert client.get_run(other).info.status == "RUNNING"
    said = capsys.readouterr().err
    assert f"{gone}: the runs it left RUNNING and its parent run {ids[0]} are marked KILLED in " in said
    assert "(the server is gone); to continue: spot sweep s.yaml --resume" in said


def test_runs_are_closed_through_the_store_when_the_server_stalls(tmp_path, stalling, short_deadlines, capsys):
    from spot.sweep import tracking_store

    client, ctx, ids, _ = _launch_store(tmp_path / "m.db")
    store = tracking_store.Store(lambda: stalling.uri, "", lambda: None, backend=sqlite_uri(tmp_path / "m.db"))
    start = time.monotonic()
    where = tracking_store.close_runs(store, ctx, "launch stopped by SIGTERM", deadline=time.monotonic() + 25)
    assert time.monotonic() - start < 10
    assert where == f" in {sqlite_uri(tmp_path / 'm.db')} (the server did not answer)"
    assert all(client.get_run(i).info.status == "KILLED" for i in ids)
    assert f"note: closing the runs through {stalling.uri} failed (TrackingUnreachable: " in capsys.readouterr().err


_SIGTERM_PROBE = """
import os, signal, sys, time
from pathlib import Path
from spot.sweep import launch, signals, tracking_store
from spot.sweep.mlflow_server import sqlite_uri
from spot.sweep.trial import SweepContext

uri, db, exp, parent = sys.argv[1:]
store = tracking_store.Store(lambda: uri, "", lambda: None, backend=sqlite_uri(Path(db)))
ctx = SweepContext("sw", "sw", "s", exp, parent, uri, ())
close = lambda reason, deadline: launch._close_launch(store, ctx, reason, "RESUME", deadline)
with signals.on_sigterm(lambda: signals.sigterm_cleanup(store, close, started_ray=False)):
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(60)
sys.exit(5)  # never reached: the handler ends the process
"""


def test_a_sigterm_cleanup_goes_step_by_step_and_closes_runs_past_a_stalled_server(tmp_path, stalling):
    client, ctx, ids, _ = _launch_store(tmp_path / "m.db")
    env = {k: v for k, v in os.environ.items() if k not in DEADLINES}  # spot's defaults: 30 s, 2 retries
    start = time.monotonic()
    args = [stalling.uri, str(tmp_path / "m.db"), ctx.experiment_id, ctx.parent_run_id]
    done = subprocess.run(
        [sys.executable, "-c", _SIGTERM_PROBE, *args], env=env, capture_output=True, text=True, timeout=120
    )
    took = time.monotonic() - start
    assert done.returncode == 143, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if ln.startswith(("SIGTERM", "note", "launch"))]
    assert lines[:3] == [
        "SIGTERM: stopping the trials, closing the runs, stopping Ray",
        "SIGTERM: closing the runs (deadline 25 s)",
        # the cleanup's requests wait 5 s, without retries (spot's usual deadline would be 30 s, 3 tries)
        f"note: closing the runs through {stalling.uri} failed (TrackingUnreachable: tracking server "
        f"{stalling.uri} did not answer while spot was searching runs: no answer within 5 s to "
        "/api/2.0/mlflow/runs/search, 1 try (MLFLOW_HTTP_REQUEST_TIMEOUT=5 s, MLFLOW_HTTP_REQUEST_MAX_RETRIES=0); "
        "check that the server runs and answers, or pass another --tracking-uri); "
        f"using {sqlite_uri(tmp_path / 'm.db')}",
    ], done.stderr
    assert lines[3].startswith("launch stopped by SIGTERM: the runs it left RUNNING and its parent run ")
    assert lines[4:] == ["SIGTERM: stopping the MLflow server (deadline 10 s)"]
    assert "Traceback" not in done.stderr and took < 40, took
    for run_id in ids:
        run = client.get_run(run_id)
        assert run.info.status == "KILLED" and run.data.tags["failure_reason"] == "launch stopped by SIGTERM"


# --------------------------------------------------------------------------- watching the server
def test_the_watch_stops_tune_once_when_the_server_dies(capsys):
    from spot.sweep import tracking_store

    got = []
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: got.append(signum))  # as Tune's handler
    died = {"text": ""}
    try:
        with tracking_store.watching_server(lambda: died["text"], poll_s=0.05):
            time.sleep(0.3)
            assert got == []
            died["text"] = "the MLflow server at http://127.0.0.1:9 (pid 7) died (killed by SIGKILL)"
            deadline = time.monotonic() + 5
            while not got and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert got == [signal.SIGUSR1]  # once (again only after 30 s)
    assert capsys.readouterr().err == (
        "the MLflow server at http://127.0.0.1:9 (pid 7) died (killed by SIGKILL); stopping the trials, then "
        "closing their runs through the store\n"
    )


def test_the_watch_sends_nothing_while_no_handler_would_take_it():
    # SIGUSR1's default action ends the process: without Tune's handler the watch must not send it.
    code = (
        "import signal, time\nfrom spot.sweep import tracking_store\nsignal.signal(signal.SIGUSR1, signal.SIG_DFL)\n"
        "with tracking_store.watching_server(lambda: 'dead', poll_s=0.05):\n    time.sleep(0.5)\nprint('alive')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "alive", out.stderr


# --------------------------------------------------------------------------- kill -9 of a sweep's server
SERVED_SWEEP = """
name: served
base: {method: oracle, budget: tiny, data.name: drawer-open}
grid:
  iql.lr: [0.0003, 0.001]
seeds: [0]
resources: {cpu: 1, gpu: 0}
max_concurrent: 2
fast_compile: true
"""


def _sweep_env(root: Path) -> dict[str, str]:
    env = {**os.environ, "SPOT_DATA_DIR": str(root / "data"), "SPOT_CACHE_DIR": str(root / "cache")}
    env["PYTHONUNBUFFERED"] = "1"
    for key in ("MLFLOW_TRACKING_URI", "RAY_ADDRESS", "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", *DEADLINES):
        env.pop(key, None)
    return env


def _server_processes(driver: int) -> tuple[int, list[int]]:
    """The ``mlflow server`` process among the driver's children, and its own children (uvicorn)."""
    import psutil

    for proc in psutil.Process(driver).children(recursive=True):
        try:
            if proc.cmdline()[1:4] == ["-m", "mlflow", "server"]:
                return proc.pid, [c.pid for c in proc.children(recursive=True)]
        except (psutil.Error, IndexError):
            continue
    raise AssertionError("no mlflow server among the driver's processes")


def _wait(predicate, timeout: float, proc: subprocess.Popen, log: Path, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"sweep ended before {what}:\n{log.read_text()[-4000:]}"
        assert time.monotonic() < deadline, f"no {what} in {timeout:.0f} s:\n{log.read_text()[-4000:]}"
        time.sleep(0.3)


@pytest.mark.slow
def test_kill_9_of_the_sweeps_server_stops_the_trials_closes_the_runs_and_resume_finishes(tmp_path):
    import psutil
    from mlflow.tracking import MlflowClient

    gate, log = tmp_path / "gate", tmp_path / "launch.log"
    gate.mkdir()
    (gate / "hold").touch()
    (tmp_path / "served.yaml").write_text(SERVED_SWEEP)
    cmd = [sys.executable, str(HERE / "sweep_driver.py"), str(gate), "served.yaml"]
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            cmd, cwd=tmp_path, env=_sweep_env(tmp_path), stdout=out, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            _wait(lambda: len(list(gate.glob("started-*"))) >= 2, 300, proc, log, "two running trials")
            server, children = _server_processes(proc.pid)
            port = re.search(r"starting mlflow server on http://127\.0\.0\.1:(\d+)", log.read_text())[1]
            os.kill(server, signal.SIGKILL)
            killed_at = time.monotonic()
            rc = proc.wait(240)
            took = time.monotonic() - killed_at
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    text = log.read_text()
    death = f"the MLflow server at http://127.0.0.1:{port} (pid {server}) died (killed by SIGKILL)"
    assert rc == 2, text[-4000:]
    assert f"{death}; stopping the trials, then closing their runs through the store" in text
    last = text.strip().splitlines()[-1]
    assert last.startswith(f"error: {death} while the sweep ran (the server's log: "), text[-4000:]
    assert last.endswith("; to continue: spot sweep served.yaml --resume") and "Traceback" not in text
    assert took < 120, took  # Tune's stop, Ray's shutdown, the runs closed: no idle wait
    # The server's uvicorn child, which outlives a kill -9 of `mlflow server`, was ended too.
    assert children and not [p for p in children if psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"]
    client = MlflowClient(sqlite_uri(tmp_path / "spot_runs" / "mlflow.db"))
    runs = client.search_runs([client.get_experiment_by_name("served").experiment_id])
    assert runs and not [r for r in runs if r.info.status == "RUNNING"], [(r.info.status, r.data.tags) for r in runs]
    trials = [r for r in runs if "spot.trial_key" in r.data.tags]
    assert len(trials) == 2 and all(r.data.tags["failure_reason"] == death for r in trials)
    (parent,) = [r for r in runs if r.data.tags.get("spot.role") == "sweep"]
    assert parent.info.status == "KILLED" and parent.data.tags["failure_reason"] == death
    # --resume starts a new server on the same store and runs the stopped trials again.
    (gate / "hold").unlink()
    resumed = subprocess.run(
        [*cmd, "--resume"], cwd=tmp_path, env=_sweep_env(tmp_path), capture_output=True, text=True, timeout=400
    )
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    assert "2/2 runs finished" in resumed.stdout
    runs = client.search_runs([client.get_experiment_by_name("served").experiment_id])
    finished = [
        r.data.tags["spot.trial_key"] for r in runs if "spot.trial_key" in r.data.tags and r.info.status == "FINISHED"
    ]
    assert len(finished) == 2 and len(set(finished)) == 2


def test_a_server_that_stops_answering_mid_command_is_one_error_line(monkeypatch, capsys):
    """An MLflow call deep inside a command (after the run opened) that gets no answer ends the
    command with one `error:` line naming the server, exit 2, not MLflow's traceback."""
    import requests
    from mlflow.exceptions import MlflowException

    from spot import cli

    def stalled(args):
        try:
            raise requests.exceptions.ReadTimeout("HTTPConnectionPool(host='127.0.0.1', port=9): read timeout=3")
        except requests.exceptions.ReadTimeout as e:
            raise MlflowException("API request to http://127.0.0.1:9/api/2.0/mlflow/runs/log-batch failed") from e

    monkeypatch.setattr(cli, "_parse", lambda argv: type("A", (), {"fn": staticmethod(stalled)})())
    assert cli.main(["config", "keys"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: tracking server http://127.0.0.1:9 did not answer")
    assert "no answer within 3 s" in err[0] and "/api/2.0/mlflow/runs/log-batch" in err[0]


def test_other_errors_mid_command_still_raise(monkeypatch):
    from spot import cli

    def broken(args):
        raise ValueError("a bug, not a server")

    monkeypatch.setattr(cli, "_parse", lambda argv: type("A", (), {"fn": staticmethod(broken)})())
    with pytest.raises(ValueError, match="a bug"):
        cli.main(["config", "keys"])
