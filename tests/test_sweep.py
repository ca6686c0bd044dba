"""Sweep files (validation, expansion) and one real sweep: Ray + a loopback MLflow server + the pipeline.

The real sweep (4 trials of oracle at the tiny budget on a tiny Meta-World dataset, 2 of which fail
on a broken data file) is launched as ``spot sweep --smoke`` in a subprocess, killed with SIGKILL
once one run has finished, and continued with ``--resume``. The tracking checks (tags, parent
run, metrics) and the exactly-once checks both read the store it leaves behind.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from spot import SpotError, sweep
from spot.sweep.mlflow_server import MlflowServer, sqlite_uri

REPO = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- (a) validation
@pytest.mark.parametrize(
    "text, match",
    [
        ("bsae: {method: pt}\n", r"'bsae': unknown key; did you mean 'base'"),
        ("base: {methd: pt}\n", r"'base': unknown config key 'methd'; did you mean 'method'"),
        (
            "grid: {shaping.wieght: [0.1]}\n",
            r"'grid': unknown config key 'shaping.wieght'; did you mean 'shaping.weight'",
        ),
        ("smoke: {base: [1]}\n", r"'smoke.base': expected a mapping of config keys, got list"),
        ("grid: {shaping.weight: 0.1}\n", r"'grid.shaping.weight': expected a non-empty list"),
        ("table: 5\n", r"'table': expected one of 1, 2, 3, 4, 7, 8, got 5"),
        ("grid: {shaping.weight: [0.1, 0.1]}\n", r"'grid.shaping.weight': repeats a value"),
        (
            "zip: {data.name: [hopper-medium-replay, walker2d-medium-replay], labels.num_queries: [100]}\n",
            r"'zip': paired axes need lists of equal length",
        ),
        ("base: {seed: 3}\n", r"'base.seed': may not be set here: give seeds in 'seeds:'"),
        ("base: {tracking: {uri: 'x'}}\n", r"'base.tracking.uri': may not be set here"),
        ("seeds: [0, -1]\n", r"'seeds': expected a non-empty list of non-negative integers"),
        ("seed_mode: pmap\n", r"'seed_mode': expected one of trials, sequential, vmap"),
        ("resources: {cpus: 1}\n", r"'resources.cpus': unknown key"),
        ("base: {method: pt}\ngrid: {method: [pt, spot]}\n", r"'base.method': is also an axis"),
        (
            "grid: {method: [pt]}\nsmoke: {grid: {shaping.weight: [0.1]}}\n",
            r"'smoke.grid.shaping.weight': is not an axis",
        ),
        (
            "grid: {shaping.weight: [0.5, 2.0]}\n",
            r"trial shaping.weight=2.0: config key 'shaping.weight': value 2.0 is out of range",
        ),
        (
            "zip: {data.name: [hopper-medium-replay, hoper-medium], labels.num_queries: [10, 20]}\n",
            r"trial data.name=hoper-medium labels.num_queries=20: unknown dataset 'hoper-medium'",
        ),
        ("zip: {method: [pt, pt], labels.num_queries: [5, 5]}\n", r"trial method=pt labels.num_queries=5 occurs twice"),
    ],
)
def test_bad_sweep_files_name_file_and_key(tmp_path, text, match):
    path = _write(tmp_path, text)
    with pytest.raises(SpotError, match=match) as info:
        sweep.load(path)
    assert str(path) in str(info.value)


def test_smoke_needs_a_smoke_block(tmp_path):
    with pytest.raises(SpotError, match="--smoke needs a 'smoke:' block"):
        sweep.load(_write(tmp_path, "grid: {method: [pt]}\n"), smoke=True)


# --------------------------------------------------------------------------- (b) expansion
SWEEP = """
name: t3
base: {method: spot, budget: small}
grid:
  shaping.kind: [cosine, potential]
  shaping:
    weight: [-0.5, 0.1, 1.0]
zip:
  data.name: [hopper-medium-expert, walker2d-medium-replay]
  labels.num_queries: [100, 500]
seeds: [0, 1]
smoke:
  base: {budget: tiny}
  grid: {shaping.weight: [0.1]}
  seeds: [3]
"""


def test_expansion_grid_x_zip_x_seeds(tmp_path):
    s = sweep.load(_write(tmp_path, SWEEP))
    trials = s.trials()
    assert s.experiment == "t3" and s.axis_keys == ("shaping.kind", "shaping.weight", "data.name", "labels.num_queries")
    assert len(trials) == 2 * 3 * 2 * 2 and all(len(t.seeds) == 1 for t in trials)
    # Seeds vary slowest, then the grid (first axis slowest), then the zip rows.
    assert [t.seeds[0] for t in trials] == [0] * 12 + [1] * 12
    assert trials[0].axes == {
        "shaping.kind": "cosine",
        "shaping.weight": -0.5,
        "data.name": "hopper-medium-expert",
        "labels.num_queries": 100,
    }
    assert trials[1].axes["data.name"] == "walker2d-medium-replay" and trials[1].axes["labels.num_queries"] == 500
    assert trials[2].axes["shaping.weight"] == 0.1 and trials[6].axes["shaping.kind"] == "potential"
    assert trials[0].overrides == {"method": "spot", "budget": "small", **trials[0].axes}
    assert {tuple(sorted(t.axes.items())) for t in trials[:12]} == {tuple(sorted(t.axes.items())) for t in trials[12:]}
    keys = {sweep.run_key(t.overrides, t.seeds[0]) for t in trials}
    assert len(keys) == 24

    vmap = sweep.load(_write(tmp_path, SWEEP + "seed_mode: vmap\n", "v.yaml"))
    assert len(vmap.trials()) == 12 and all(t.seeds == (0, 1) for t in vmap.trials())
    assert len(vmap.runs()) == 24 and vmap.spec_hash() != s.spec_hash()

    smoke = sweep.load(_write(tmp_path, SWEEP), smoke=True)
    assert smoke.experiment == "t3-smoke" and smoke.seeds == (3,)
    assert len(smoke.trials()) == 2 * 1 * 2
    assert all(t.overrides["budget"] == "tiny" and t.axes["shaping.weight"] == 0.1 for t in smoke.trials())


# Every sweep file the repository ships: the quickstart and the paper's tables (sweeps/, sweeps/paper/)
# and the lab's studies (experiments/<study>/sweeps/).
REPO_SWEEP_FILES = sorted([*(REPO / "sweeps").rglob("*.yaml"), *(REPO / "experiments").glob("*/sweeps/*.yaml")])


def test_repo_sweep_files_are_found():
    names = {p.relative_to(REPO).as_posix() for p in REPO_SWEEP_FILES}
    assert {"sweeps/quickstart.yaml", "sweeps/paper/table1.yaml"} <= names
    assert any(n.startswith("experiments/") for n in names)


@pytest.mark.parametrize("path", REPO_SWEEP_FILES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_repo_sweep_files_resolve(path):
    full, smoke = sweep.load(path), sweep.load(path, smoke=True)
    if path.stem == "table1":
        # Table 1's smoke runs every cell (6 methods x 10 datasets) with 2 seeds at the tiny budget
        cells = {(t.axes["method"], t.axes["data.name"]) for t in full.trials()}
        assert len(cells) == 60 and {(t.axes["method"], t.axes["data.name"]) for t in smoke.trials()} == cells
        assert len(smoke.runs()) == 2 * len(cells)
    else:
        assert len(smoke.runs()) <= min(4, len(full.runs()))
    assert all(t.overrides["budget"] == "tiny" for t in smoke.trials())


def test_each_table_reads_the_experiment_its_sweep_file_writes():
    """tables.SWEEP_EXPERIMENTS (which experiment `spot tables --table N` reads by default) names
    the sweep file whose `table:` is N (Table 8 is the stage times of Table 1's runs)."""
    from spot.results import tables

    assert set(tables.SWEEP_EXPERIMENTS) == set(tables.TABLES)
    for number, name in tables.SWEEP_EXPERIMENTS.items():
        data = yaml.safe_load((REPO / "sweeps" / "paper" / f"{name}.yaml").read_text())
        assert data["name"] == name and data["table"] == (1 if number == 8 else number)


# --------------------------------------------------------------------------- (c) + (d) a real sweep
KILL_SWEEP = """
name: killtest
base: {method: oracle, budget: small}
grid:
  data.name: [drawer-open, {broken}]
seeds: [0, 1]
resources: {cpu: 1, gpu: 0}
max_concurrent: 2
smoke:
  base: {budget: tiny, data.size: tiny, iql.steps: 100, eval.every: 100}
  fast_compile: true
"""


def _finished_child_runs(db: Path) -> int:
    if not db.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            return con.execute(
                "select count(*) from runs r join tags t on r.run_uuid = t.run_uuid "
                "where t.key = 'spot.trial_key' and r.status = 'FINISHED'"
            ).fetchone()[0]
    except sqlite3.OperationalError:  # tables not created yet
        return 0


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory):
    """Launch, SIGKILL the driver's process group after the first finished run, resume; return paths."""
    root = tmp_path_factory.mktemp("sweep")
    broken = root / "broken.hdf5"
    broken.write_bytes(b"not an hdf5 file")
    path = _write(root, KILL_SWEEP.replace("{broken}", str(broken)), "killtest.yaml")
    env = {
        **os.environ,
        "SPOT_DATA_DIR": str(root / "data"),
        "SPOT_CACHE_DIR": str(root / "cache"),
        "JAX_COMPILATION_CACHE_DIR": str(root / "jax"),
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = [sys.executable, "-m", "spot.cli", "sweep", str(path), "--smoke"]
    db = root / "spot_runs" / "mlflow.db"
    with open(root / "launch.log", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 400
        while _finished_child_runs(db) < 1:
            assert proc.poll() is None, (
                "sweep ended before it was killed:\n" + (root / "launch.log").read_text()[-3000:]
            )
            assert time.monotonic() < deadline, "no run finished in time:\n" + (root / "launch.log").read_text()[-3000:]
            time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    first_port = int(re.search(r"mlflow server on http://127.0.0.1:(\d+)", (root / "launch.log").read_text())[1])
    resumed = subprocess.run([*cmd, "--resume"], cwd=root, env=env, capture_output=True, text=True, timeout=500)
    assert "runs finished" in resumed.stdout, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    state = json.loads((root / "spot_runs" / "ray" / "killtest-smoke.json").read_text())
    return {
        "root": root,
        "db": db,
        "state": state,
        "resumed": resumed,
        "first_port": first_port,
        "sweep": sweep.load(path, smoke=True),
        "broken": str(broken),
    }


@pytest.fixture(scope="module")
def store(killed_and_resumed):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(sqlite_uri(killed_and_resumed["db"]))
    exp = client.get_experiment_by_name("killtest-smoke")
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    return client, exp, runs


@pytest.mark.slow
def test_resume_leaves_exactly_one_finished_run_per_config_and_seed(killed_and_resumed, store):
    _, _, runs = store
    out = killed_and_resumed["resumed"]
    assert out.returncode == 1  # the broken-file trials failed; the summary says so
    children = [r for r in runs if "spot.trial_key" in r.data.tags]
    s = killed_and_resumed["sweep"]
    assert len(s.runs()) == 4
    for trial, seed in s.runs():
        mine = [r for r in children if r.data.tags["spot.trial_key"] == sweep.run_key(trial.overrides, seed)]
        finished = [r for r in mine if r.info.status == "FINISHED"]
        if trial.axes["data.name"] == "drawer-open":
            assert len(finished) == 1, [(r.info.status, r.data.tags.get("failure_reason")) for r in mine]
        else:
            assert not finished and any(r.info.status == "FAILED" for r in mine)
            assert all("broken.hdf5" in r.data.tags["failure_reason"] or r.info.status == "KILLED" for r in mine)
    assert not [r for r in runs if r.info.status == "RUNNING"]
    # The summary lists every (config, seed) with its status, the failure reason included.
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith(("drawer-open", killed_and_resumed["broken"]))]
    assert len(lines) == 4 and sum("FINISHED" in ln for ln in lines) == 2 and sum("FAILED" in ln for ln in lines) == 2
    assert "2/4 runs finished" in out.stdout and "spot ui --tracking-uri sqlite:///" in out.stdout
    link = next(ln for ln in out.stdout.splitlines() if ln.startswith("then open the sweep's runs: "))
    from urllib.parse import unquote

    assert "workflowType=machine_learning" in link and "viewStateShareKey=spot-killtest" in unquote(link)
    # The first launch's server died with its driver (PR_SET_PDEATHSIG).
    assert not MlflowServer("sqlite:///x", Path("/tmp"), port=killed_and_resumed["first_port"]).healthy()


@pytest.mark.slow
def test_runs_carry_sweep_tags_parent_and_metrics(killed_and_resumed, store):
    _, _, runs = store
    state = killed_and_resumed["state"]
    (parent,) = [r for r in runs if r.data.tags.get("spot.role") == "sweep"]
    assert parent.info.run_id == state["parent_run_id"] and parent.data.tags["spot.sweep_id"] == state["sweep_id"]
    assert parent.info.status == "FAILED" and parent.data.metrics["sweep/runs_finished"] == 2
    assert "spot.resumed_at" in parent.data.tags
    children = [r for r in runs if "spot.trial_key" in r.data.tags]
    assert len(children) >= 4
    for r in children:
        tags = r.data.tags
        assert tags["mlflow.parentRunId"] == parent.info.run_id
        assert tags["spot.sweep_id"] == state["sweep_id"] and tags["spot.sweep_name"] == "killtest"
        assert tags["spot.trial_id"] and tags["spot.budget"] == "tiny"
        assert tags["method"] == "oracle" and tags["seed"] in ("0", "1")
        assert tags["axis.data.name"] in ("drawer-open", killed_and_resumed["broken"])
        assert tags["dataset"] == tags["axis.data.name"]
        assert r.data.params["data.name"] == tags["axis.data.name"] and r.data.params["iql.steps"] == "100"
        if r.info.status == "FINISHED":
            assert {"eval/score_final", "eval/score_best", "time/total_s"} <= set(r.data.metrics)


@pytest.mark.slow
def test_trial_skips_a_config_and_seed_that_already_finished(killed_and_resumed, store, monkeypatch):
    """What makes a re-run trial idempotent: it reports the FINISHED run instead of running again."""
    _, exp, runs = store
    state, s = killed_and_resumed["state"], killed_and_resumed["sweep"]
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "")
    ctx = sweep.SweepContext(
        state["sweep_id"],
        "killtest",
        "killtest-smoke",
        exp.experiment_id,
        state["parent_run_id"],
        sqlite_uri(killed_and_resumed["db"]),
        s.axis_keys,
    )
    trial = next(t for t in s.trials() if t.axes["data.name"] == "drawer-open" and t.seeds == (1,))
    (done,) = [
        r
        for r in runs
        if r.data.tags.get("spot.trial_key") == sweep.run_key(trial.overrides, 1) and r.info.status == "FINISHED"
    ]

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished (config, seed) ran again")

    reports: list[dict] = []
    sweep.run_trial(trial.overrides, [1], ctx, trial_id="again", report=reports.append, run_fn=must_not_run)
    assert reports == [
        {
            "seed": 1,
            "run_id": done.info.run_id,
            "skipped": 1,
            "score_final": done.data.metrics["eval/score_final"],
            "score_best": done.data.metrics["eval/score_best"],
        }
    ]


def test_smoke_asks_for_no_gpu_unless_its_block_does(tmp_path):
    text = "grid: {method: [pt]}\nresources: {cpu: 1, gpu: 0.25}\nsmoke: {base: {budget: tiny}}\n"
    assert sweep.load(_write(tmp_path, text)).resources == {"cpu": 1.0, "gpu": 0.25}
    assert sweep.load(_write(tmp_path, text), smoke=True).resources == {"cpu": 1.0, "gpu": 0.0}
    text2 = text.replace("smoke: {base: {budget: tiny}}", "smoke: {base: {budget: tiny}, resources: {gpu: 1}}")
    assert sweep.load(_write(tmp_path, text2), smoke=True).resources == {"cpu": 1.0, "gpu": 1.0}


def test_fast_compile_is_a_sweep_key_a_smoke_block_can_set(tmp_path):
    text = "grid: {method: [pt]}\nsmoke: {base: {budget: tiny}, fast_compile: true}\n"
    assert sweep.load(_write(tmp_path, text)).fast_compile is False
    assert sweep.load(_write(tmp_path, text), smoke=True).fast_compile is True
    top = "grid: {method: [pt]}\nfast_compile: true\nsmoke: {base: {budget: tiny}}\n"
    assert sweep.load(_write(tmp_path, top), smoke=True).fast_compile is True  # the smoke block inherits it
    with pytest.raises(SpotError, match=r"'smoke.fast_compile': expected true or false, got 'yes'"):
        sweep.load(_write(tmp_path, text.replace("fast_compile: true", "fast_compile: 'yes'")), smoke=True)


@pytest.mark.slow
def test_status_after_the_resumed_launch(killed_and_resumed):
    """``spot sweep FILE --status`` on the real store: the launch's four (config, seed), as the summary."""
    root = killed_and_resumed["root"]
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    cmd = [sys.executable, "-m", "spot.cli", "sweep", str(root / "killtest.yaml"), "--smoke", "--status"]
    out = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stderr  # the launch ended; the broken file's two runs failed
    assert f"launch {killed_and_resumed['state']['sweep_id']}" in out.stdout
    assert "4 runs: 2 failed, 2 finished" in out.stdout
    failed = [ln.split("FAILED", 1)[1].strip() for ln in out.stdout.splitlines() if " FAILED " in ln]
    assert len(failed) == 2 and all(failed), out.stdout  # each with its failure reason
