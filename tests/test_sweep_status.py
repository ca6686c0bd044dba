"""``spot sweep FILE --status``: each (config, seed) of the last launch, read from a real MLflow store."""

from __future__ import annotations

import fcntl
import json
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spot import sweep
from spot.cli import main
from spot.sweep.mlflow_server import sqlite_uri

SWEEP = """
name: st
base: {method: oracle, budget: tiny}
grid:
  data.name: [drawer-open, plate-slide, lift-ph, button-press]
seeds: [0]
"""
NAMES = ("drawer-open", "plate-slide", "lift-ph", "button-press")


def _dead_process() -> tuple[int, str]:
    """The pid and start ticks of a process that has ended (read while it is a zombie)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    while True:  # wait for it to exit without reaping it, so that /proc still names it
        fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        if fields[0] == "Z":
            break
        time.sleep(0.01)
    started = fields[19]  # field 22 of /proc/<pid>/stat
    proc.wait()
    return proc.pid, started


class Launch:
    """A launch record and an MLflow store of sweep ``st`` (launch st-1), as ``spot sweep`` leaves them:
    with ``names="old"`` as versions before the bookkeeping tags moved under ``spot.`` left them
    (``sweep_id``, ``trial_key``), with ``"new"`` as spot tags runs now (``spot.sweep_id``, ...)."""

    def __init__(self, root: Path, parent_status: str = "FINISHED", names: str = "old") -> None:
        from mlflow.tracking import MlflowClient

        self.prefix = "spot." if names == "new" else ""

        self.path = root / "st.yaml"
        self.path.write_text(SWEEP)
        spec = sweep.load(self.path)
        self.ray = root / "spot_runs" / "ray"
        self.ray.mkdir(parents=True)
        self.client = MlflowClient(sqlite_uri(root / "spot_runs" / "mlflow.db"))
        self.exp = self.client.create_experiment("st")
        parent = self.client.create_run(self.exp, tags={self.prefix + "sweep_id": "st-1", "spot.role": "sweep"})
        parent = parent.info.run_id
        self.client.set_terminated(parent, parent_status)
        record = {"sweep_id": "st-1", "spec_hash": spec.spec_hash(), "parent_run_id": parent}
        (self.ray / "st.json").write_text(json.dumps(record))
        self.keys = {t.axes["data.name"]: sweep.run_key(t.overrides, 0) for t in spec.trials()}

    def child(self, name: str, status: str | None = None, score: float | None = None, **tags: str) -> str:
        tags = {self.prefix + "sweep_id": "st-1", self.prefix + "trial_key": self.keys[name], **tags}
        run = self.client.create_run(self.exp, tags=tags).info.run_id
        if score is not None:
            self.client.log_metric(run, "eval/score_final", score)
        if status:
            self.client.set_terminated(run, status)
        return run

    def status(self, capsys, *flags: str) -> tuple[int, str, dict[str, str]]:
        rc = main(["sweep", str(self.path), "--status", *flags])
        out = capsys.readouterr().out
        lines = {ln.split()[0]: ln for ln in out.splitlines() if ln.split() and ln.split()[0] in NAMES}
        return rc, out, lines


@pytest.fixture(params=["old", "new"])
def launch(tmp_path, monkeypatch, request):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    return Launch(tmp_path, names=request.param)


def test_status_lists_each_config_and_seed_of_the_last_launch(launch, capsys):
    """drawer-open FINISHED; plate-slide RUNNING on another host at 20k of 300k updates after a killed
    try; lift-ph RUNNING under a dead process of this host; button-press never started."""
    launch.child("drawer-open", "FINISHED", 41.25)
    launch.child("plate-slide", "KILLED")
    running = launch.child("plate-slide", **{"spot.host": "elsewhere"})
    launch.client.log_param(running, "iql.steps", 300000)
    for step, score in [(0, 1.0), (20000, 20.5), (10000, 13.75)]:
        launch.client.log_metric(running, "eval/score", score, step=step)
    pid, started = _dead_process()
    launch.child("lift-ph", **{"spot.host": socket.gethostname(), "spot.pid": str(pid), "spot.pid_started": started})
    other = launch.client.create_run(
        launch.exp, tags={launch.prefix + "sweep_id": "st-0", launch.prefix + "trial_key": launch.keys["button-press"]}
    )
    launch.client.set_terminated(other.info.run_id, "FINISHED")  # another launch's run: not this launch's

    rc, out, lines = launch.status(capsys)
    assert rc == 3  # a run is still going
    assert "FINISHED" in lines["drawer-open"] and "41.25" in lines["drawer-open"]
    assert "RUNNING" in lines["plate-slide"] and "eval 20.5 at 20000 / 300000" in lines["plate-slide"]
    assert "on elsewhere" in lines["plate-slide"]
    # The dead process's run is closed, as every reading command does, and says why.
    assert "KILLED" in lines["lift-ph"] and "ended without closing the run" in lines["lift-ph"]
    assert "NOT RUN" in lines["button-press"]
    assert "last launch st-1" in out and "no launch running" in out
    assert "4 runs: 1 finished, 1 killed, 1 not run, 1 running" in out


def test_status_exit_codes_when_the_launch_ended(launch, capsys):
    for name in NAMES[:3]:
        launch.child(name, "FINISHED", 10.0)
    failed = launch.child("button-press", "FAILED")
    launch.client.set_tag(failed, "failure_reason", "SpotError: data file broken.hdf5 is damaged")
    rc, out, lines = launch.status(capsys)
    assert rc == 1 and "FAILED" in lines["button-press"] and "broken.hdf5 is damaged" in lines["button-press"]
    launch.child("button-press", "FINISHED", 12.5)  # a resumed launch retried it
    rc, out, lines = launch.status(capsys)
    assert rc == 0 and "12.50" in lines["button-press"] and "4 runs: 4 finished" in out


def test_status_of_a_run_without_an_evaluation_yet(launch, capsys):
    run = launch.child("drawer-open")
    launch.client.log_param(run, "iql.steps", 100)
    rc, _, lines = launch.status(capsys)
    assert rc == 3 and "no evaluation yet (IQL steps 100)" in lines["drawer-open"]


def _hold_lock(ray: Path, holder: str):
    f = open(ray / "st.lock", "a+")
    fcntl.flock(f, fcntl.LOCK_EX)
    f.write(holder)
    f.flush()
    return f


def test_status_while_a_new_launch_starts(launch, capsys):
    """The lock is held but the record is still the previous, ended launch's: the rows say so and the
    exit code is 'in progress', never 0."""
    for name in NAMES:
        launch.child(name, "FINISHED", 10.0)
    with _hold_lock(launch.ray, "pid 4242 on node-a, since 2026-11-27 00:00:00\n"):
        rc, out, _ = launch.status(capsys)
    assert rc == 3 and "a launch is running (pid 4242 on node-a" in out
    assert "these are the previous launch's runs" in out
    rc, out, _ = launch.status(capsys)  # the lock released: the launch ended
    assert rc == 0 and "no launch running" in out


def test_status_while_the_first_launch_starts(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "st.yaml").write_text(SWEEP)
    (tmp_path / "spot_runs" / "ray").mkdir(parents=True)
    with _hold_lock(tmp_path / "spot_runs" / "ray", "pid 7 on node-b, since now\n"):
        assert main(["sweep", "st.yaml", "--status"]) == 3
    assert "its first launch is starting (pid 7 on node-b, since now); no run yet" in capsys.readouterr().out


def _fails(args: list[str], capsys, pattern: str) -> None:
    assert main(args) == 2
    assert re.search(pattern, capsys.readouterr().err)


def test_status_of_a_sweep_that_never_launched(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "st.yaml").write_text(SWEEP)
    never = r"error: sweep 'st' was never launched with storage \S*spot_runs/ray"
    _fails(["sweep", "st.yaml", "--status"], capsys, never)


def test_status_with_a_damaged_launch_record(launch, capsys):
    (launch.ray / "st.json").write_text("[1, 2]")
    _fails(
        ["sweep", str(launch.path), "--status"], capsys, r"launch record \S*st\.json is damaged \(expected an object"
    )


def test_status_of_an_edited_sweep_file(launch, capsys):
    launch.path.write_text(SWEEP.replace("seeds: [0]", "seeds: [0, 1]"))
    _fails(["sweep", str(launch.path), "--status"], capsys, r"expands to other trials than its last launch st-1")


def test_status_without_the_store(launch, capsys):
    (launch.path.parent / "spot_runs" / "mlflow.db").unlink()
    _fails(["sweep", str(launch.path), "--status"], capsys, r"no MLflow store at \S*spot_runs/mlflow\.db")


def test_status_in_another_store(launch, tmp_path, capsys):
    """A store that has the experiment but not this launch (launched with another --tracking-uri)."""
    from mlflow.tracking import MlflowClient

    other = tmp_path / "other.db"
    MlflowClient(sqlite_uri(other)).create_experiment("st")
    uri = f"sqlite:///{other}"
    _fails(["sweep", str(launch.path), "--status", "--tracking-uri", uri], capsys, r"does not hold launch st-1")
    empty = tmp_path / "empty.db"
    MlflowClient(sqlite_uri(empty)).search_experiments()  # a store without the experiment
    uri = f"sqlite:///{empty}"
    _fails(["sweep", str(launch.path), "--status", "--tracking-uri", uri], capsys, r"no experiment 'st' in the MLflow")


def test_status_refuses_the_flags_of_a_launch(launch, capsys):
    flags = ["--resume", "--max-concurrent", "2"]
    _fails(["sweep", str(launch.path), "--status", *flags], capsys, r"does not take --resume, --max-concurrent")
