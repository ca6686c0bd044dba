"""Runs recorded as files (tracking.record, spot run --record) and imported into MLflow (spot results import)."""

import json
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from spot import SpotError, config
from spot.results import load
from spot.tracking import record_checks, recorded

TINY = ["budget=tiny", "data.name=drawer-open", "iql.steps=100", "iql.chunk=50", "eval.every=50", "eval.episodes=1"]


def _record(tmp_path: Path, status: str = "FINISHED", seed: int = 0) -> Path:
    """A record written through start_record's tracker, as a run would, ending with ``status``."""
    cfg = config.load(None, [*TINY, "method=oracle", f"seed={seed}", f"tracking.record={tmp_path / 'rec'}"])
    card = {"name": "drawer-open", "source": "recipe", "size": "tiny"}
    with pytest.raises(RuntimeError) if status == "FAILED" else _nothing():
        with recorded.start_record(cfg, card) as tr:
            tr.log_metrics({"eval/score": 1.5, "iql/q_mean": float("nan")}, step=0)
            tr.log_series("eval/score", [50, 100], [2.5, 3.5])
            tr.log_metrics({"eval/score_final": 3.5})
            tr.set_tags({"cache.reward": "hit"})
            (tmp_path / "curve.txt").write_text("a curve")
            tr.log_artifact(tmp_path / "curve.txt", "plots")
            if status == "FAILED":
                raise RuntimeError("boom")
    if status == "RUNNING":  # as a record looks while its run goes on, or after its process was killed
        head = json.loads((tr.folder / "record.json").read_text())
        (tr.folder / "record.json").write_text(json.dumps({**head, "status": "RUNNING", "end_time": None}))
    return tr.folder


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_a_record_holds_the_run_and_imports_once(tmp_path):
    folder = _record(tmp_path)
    head = record_checks.read_record(folder)
    assert head["status"] == "FINISHED" and head["end_time"] >= head["start_time"]
    assert head["tags"]["method"] == "oracle" and head["tags"]["spot.cache.reward"] == "hit"
    assert head["params"]["iql.steps"] == "100" and head["params"]["seed"] == "0"
    # NaN is not logged (as MLflow's tracker); the points keep their steps
    points = [(k, v, s) for k, v, s, _ in record_checks.read_metrics(folder)]
    assert points == [
        ("eval/score", 1.5, 0),
        ("eval/score", 2.5, 50),
        ("eval/score", 3.5, 100),
        ("eval/score_final", 3.5, 0),
    ]
    assert (folder / "artifacts" / "plots" / "curve.txt").read_text() == "a curve"
    assert "iql:" in (folder / "artifacts" / "config.yaml").read_text()

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    first = recorded.import_records(tmp_path / "rec", uri, "imported")
    assert [d["action"] for d in first] == ["imported"]
    run = MlflowClient(uri).get_run(first[0]["run_id"])
    assert run.info.status == "FINISHED"
    assert (run.info.start_time, run.info.end_time) == (head["start_time"], head["end_time"])
    assert run.data.params["iql.steps"] == "100" and run.data.tags["spot.record_id"] == folder.name
    history = MlflowClient(uri).get_metric_history(run.info.run_id, "eval/score")
    assert [(m.step, m.value) for m in history] == [(0, 1.5), (50, 2.5), (100, 3.5)]
    again = recorded.import_records(tmp_path / "rec", uri, "imported")
    assert [d["action"] for d in again] == ["already imported"] and again[0]["run_id"] == run.info.run_id
    runs = load.load_runs(uri, ["imported"])
    assert len(runs) == 1 and runs["method"].tolist() == ["oracle"]


def test_failed_runs_import_failed_and_running_ones_wait(tmp_path):
    failed = _record(tmp_path, "FAILED", seed=1)
    running = _record(tmp_path, "RUNNING", seed=2)
    assert record_checks.read_record(failed)["tags"]["failure_reason"] == "RuntimeError: boom"
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    done = {d["record_id"]: d for d in recorded.import_records(tmp_path / "rec", uri)}
    assert done[running.name]["action"].startswith("skipped: still RUNNING")
    assert MlflowClient(uri).get_run(done[failed.name]["run_id"]).info.status == "FAILED"


def test_bad_records_are_refused_before_anything_is_imported(tmp_path):
    folder = _record(tmp_path)
    head = json.loads((folder / "record.json").read_text())
    # a last line cut short by a killed process is dropped; a bad line before it is an error
    with open(folder / "metrics.jsonl", "a") as f:
        f.write('{"key": "eval/sc')
    assert len(record_checks.read_metrics(folder)) == 4
    (folder / "metrics.jsonl").write_text('{"key": "x"}\n{"key": "y", "value": 1, "step": 0, "timestamp": 1}\n')
    with pytest.raises(SpotError, match=r"metrics.jsonl: line 1 is not a metric point"):
        record_checks.read_metrics(folder)
    for change, message in [
        ({"status": "DONE"}, r"status 'DONE', expected one of RUNNING"),
        ({"start_time": "yesterday"}, r"field 'start_time' should be int"),
        ({"format": 9}, r"record format 9"),
        ({"params": {"iql.steps": 100}}, r"params values must be strings"),
    ]:
        (folder / "record.json").write_text(json.dumps({**head, **change}))
        with pytest.raises(SpotError, match=message):
            recorded.import_records(tmp_path / "rec", f"sqlite:///{tmp_path / 'never.db'}")
    assert not (tmp_path / "never.db").exists()  # nothing was written
    with pytest.raises(SpotError, match="does not exist"):
        record_checks.find_records(tmp_path / "nowhere")


def test_an_artifact_cannot_leave_its_record(tmp_path):
    folder = _record(tmp_path)
    tracker = recorded.RecordTracker(folder, record_checks.read_record(folder))
    with pytest.raises(SpotError, match="leaves the record's artifacts folder"):
        tracker.log_text("x", "../../outside.txt")
    assert not (tmp_path / "outside.txt").exists()


@pytest.mark.slow  # two tiny runs of two seeds each, in this process (~40 s on 2 cores)
def test_spot_run_record_then_import_matches_a_logged_run(tmp_path, spot_dirs, tiny_drawer, monkeypatch, capsys):
    """`spot run --seeds 0,1 --record` then `spot results import` and export: the same rows (config
    hash, data digest, finals, curves) as the same runs logged to MLflow directly."""
    import signal

    from spot import cli

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "cache"))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    handler = signal.getsignal(signal.SIGTERM)
    args = ["run", *TINY, "method=oracle", "--seeds", "0,1", "--quiet"]
    assert cli.main([*args, "tracking.experiment=direct", "--tracking-uri", uri]) == 0
    assert cli.main([*args, "tracking.experiment=recorded", "--record", str(tmp_path / "rec")]) == 0
    assert "spot results import" in capsys.readouterr().out
    assert signal.getsignal(signal.SIGTERM) is handler  # spot run's SIGTERM handler is its own
    assert cli.main(["results", "import", str(tmp_path / "rec"), "--tracking-uri", uri]) == 0
    assert "2 of 2 records imported" in capsys.readouterr().out
    frames = {}
    for name in ("direct", "recorded"):
        path = tmp_path / f"{name}.csv"
        assert cli.main(["results", "export", "--experiment", name, "--tracking-uri", uri, "--out", str(path)]) == 0
        frames[name] = load.read(path).sort_values("seed").reset_index(drop=True)
    a, b = frames["direct"], frames["recorded"]
    assert b["status"].tolist() == ["FINISHED", "FINISHED"] and b["seed"].tolist() == [0, 1]
    for col in ("config_hash", "data_digest", "method", "dataset", "metrics.eval/score_final", "curve.eval/score"):
        assert a[col].tolist() == b[col].tolist(), col
    capsys.readouterr()
    assert cli.main(["results", "import", str(tmp_path / "rec"), "--tracking-uri", uri]) == 0
    assert "0 of 2 records imported" in capsys.readouterr().out


def test_an_interrupted_import_leaves_no_run_and_resumes(tmp_path, monkeypatch):
    folder = _record(tmp_path)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"

    def broken(self, run_id, local_dir, artifact_path=None):
        raise KeyboardInterrupt("stopped while copying artifacts")

    monkeypatch.setattr(MlflowClient, "log_artifacts", broken)
    with pytest.raises(KeyboardInterrupt):
        recorded.import_records(tmp_path / "rec", uri, "imported")
    assert load.load_runs(uri, ["imported"]).empty  # the half-written run was deleted
    monkeypatch.undo()
    done = recorded.import_records(tmp_path / "rec", uri, "imported")
    assert [d["action"] for d in done] == ["imported"]
    runs = load.load_runs(uri, ["imported"])
    assert runs["run_id"].tolist() == [done[0]["run_id"]] and runs["tags.spot.record_id"].tolist() == [folder.name]


@pytest.mark.slow  # a tiny run stopped by SIGTERM (~30 s)
def test_sigterm_ends_a_spot_run_killed(tmp_path, spot_dirs, tiny_drawer):
    import os
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "SPOT_CACHE_DIR": str(tmp_path / "cache")}
    cmd = [sys.executable, "-m", "spot.cli", "run", *TINY, "iql.steps=20000", "method=oracle", "--quiet"]
    proc = subprocess.Popen([*cmd, "--record", str(tmp_path / "rec")], env=env, text=True, stderr=subprocess.PIPE)
    deadline = time.time() + 300
    while not list((tmp_path / "rec").glob("*/metrics.jsonl")) or not any(
        '"eval/score"' in p.read_text() for p in (tmp_path / "rec").glob("*/metrics.jsonl")
    ):
        assert proc.poll() is None and time.time() < deadline, "the run ended or never evaluated"
        time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "interrupted" in err
    (folder,) = record_checks.find_records(tmp_path / "rec")
    head = record_checks.read_record(folder)
    assert head["status"] == "KILLED" and head["tags"]["failure_reason"] == "KeyboardInterrupt: signal SIGTERM"
    assert [k for k, *_ in record_checks.read_metrics(folder)].count("eval/score") >= 1  # its curve so far


def test_a_sweep_may_not_record(tmp_path):
    from spot import sweep

    path = tmp_path / "s.yaml"
    path.write_text("name: s\nbase: {method: oracle, budget: tiny, tracking.record: /tmp/x}\nseeds: [0]\n")
    with pytest.raises(SpotError, match=r"'base.tracking.record': may not be set here: a sweep logs to MLflow"):
        sweep.load(path)


@pytest.mark.slow  # Oracle and PT at one tiny seed through the GPU script, on CPU (~1 min)
def test_the_gpu_script_records_every_method(tmp_path, spot_dirs, tiny_drawer):
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {
        **os.environ,
        "SPOT_CACHE_DIR": str(tmp_path / "cache"),
        "OUT": str(tmp_path / "out"),
        "SEEDS": "0",
        "METHODS": "oracle,pt",
        "LIMIT_S": "600",
        "SPOT": f"{sys.executable} -m spot.cli",
    }
    overrides = [*TINY, "data.size=tiny", "labels.num_queries=30", "labels.segment_length=25"]
    out = subprocess.run(
        ["bash", str(root / "scripts" / "paper_cells_gpu.sh"), *overrides],
        env=env,
        cwd=root,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    heads = [record_checks.read_record(f) for f in record_checks.find_records(tmp_path / "out" / "records")]
    assert sorted(h["tags"]["method"] for h in heads) == ["oracle", "pt"]
    for head in heads:
        assert head["status"] == "FINISHED" and head["experiment"] == "gpu_paper_hopper_fr_pf"
        assert head["params"]["budget"] == "tiny" and head["params"]["variant"] == "paper"
        assert head["tags"]["spot.vmap.members"] == "oracle:0,pt:0"
