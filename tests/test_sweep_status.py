"""``spot sweep FILE --status``: each (config, seed) of the last launch, read from a real MLflow store."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys

import pytest

from spot import sweep
from spot.cli import main
from spot.mlflow_server import sqlite_uri

SWEEP = """
name: st
base: {method: oracle, budget: tiny}
grid:
  data.name: [drawer-open, plate-slide, lift-ph, button-press]
seeds: [0]
"""


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.fixture
def launch(tmp_path, monkeypatch):
    """A launch record and a store: drawer-open FINISHED, plate-slide RUNNING on another host at 20k of
    300k updates, lift-ph RUNNING under a dead process of this host; nothing else."""
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    path = tmp_path / "st.yaml"
    path.write_text(SWEEP)
    spec = sweep.load(path)
    (tmp_path / "spot_runs" / "ray").mkdir(parents=True)
    (tmp_path / "spot_runs" / "ray" / "st.json").write_text(json.dumps({"sweep_id": "st-1", "spec_hash": "x"}))
    client = MlflowClient(sqlite_uri(tmp_path / "spot_runs" / "mlflow.db"))
    exp = client.create_experiment("st")
    keys = {t.axes["data.name"]: sweep.run_key(t.overrides, 0) for t in spec.trials()}

    def child(name: str, **tags: str):
        return client.create_run(exp, tags={"sweep_id": "st-1", "trial_key": keys[name], **tags}).info.run_id

    done = child("drawer-open")
    client.log_metric(done, "eval/score_final", 41.25)
    client.set_terminated(done, "FINISHED")
    old = child("plate-slide")  # an earlier try of the same (config, seed), killed
    client.set_terminated(old, "KILLED")
    running = child("plate-slide", **{"spot.host": "elsewhere"})
    client.log_param(running, "iql.steps", 300000)
    for step, score in [(0, 1.0), (20000, 20.5), (10000, 13.75)]:
        client.log_metric(running, "eval/score", score, step=step)
    child("lift-ph", **{"spot.host": socket.gethostname(), "spot.pid": str(_dead_pid())})
    client.create_run(exp, tags={"sweep_id": "st-0", "trial_key": keys["lift-ph"]})  # another launch's
    return path


def test_status_lists_each_config_and_seed_of_the_last_launch(launch, capsys):
    assert main(["sweep", str(launch), "--status"]) == 1  # not every run finished
    out = capsys.readouterr().out
    lines = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith(("drawer", "plate", "lift", "button"))}
    assert "FINISHED" in lines["drawer-open"] and "41.25" in lines["drawer-open"]
    assert "RUNNING" in lines["plate-slide"] and "eval 20.5 at 20000 / 300000" in lines["plate-slide"]
    assert "on elsewhere" in lines["plate-slide"]
    # The dead process's run is closed, as every reading command does, and says why.
    assert "KILLED" in lines["lift-ph"] and "ended without closing the run" in lines["lift-ph"]
    assert "NOT RUN" in lines["button-press"]
    assert "launch st-1" in out and "4 runs: 1 finished, 1 killed, 1 not run, 1 running" in out


def _fails(args: list[str], capsys, pattern: str) -> None:
    assert main(args) == 2
    assert re.search(pattern, capsys.readouterr().err)


def test_status_of_a_sweep_that_never_launched(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "st.yaml").write_text(SWEEP)
    never = r"error: sweep 'st' was never launched with storage \S*spot_runs/ray"
    _fails(["sweep", "st.yaml", "--status"], capsys, never)


def test_status_with_a_damaged_launch_record(launch, capsys):
    (launch.parent / "spot_runs" / "ray" / "st.json").write_text("[1, 2]")
    _fails(["sweep", str(launch), "--status"], capsys, r"launch record \S*st\.json is damaged \(expected an object")


def test_status_without_the_store(launch, capsys):
    (launch.parent / "spot_runs" / "mlflow.db").unlink()
    _fails(["sweep", str(launch), "--status"], capsys, r"no MLflow store at \S*spot_runs/mlflow\.db")
