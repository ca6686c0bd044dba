"""Run tags: the first-class ones bare, the bookkeeping under ``spot.`` (issue 42), and stores,
records and results written with the old bare names still read, resumed and exported alike."""

from __future__ import annotations

import json

import pytest

from spot import config, sweep, tracking
from spot.sweep.mlflow_server import sqlite_uri
from spot.tracking import tagnames

SWEEP = """
name: tagged
base: {method: oracle, budget: tiny, data.name: drawer-open}
grid:
  iql.lr: [0.001, 0.0003]
seeds: [0]
"""
FIRST_CLASS = {"method", "dataset", "seed", "variant", "failure_reason"}
OLD_BOOKKEEPING = {  # names runs carried before the move (stores and records written then)
    "attempt",
    "trial_key",
    "trial_id",
    "config_key",
    "sweep_id",
    "sweep_name",
    "git_commit",
    "data_digest",
    "budget",
    "dataset_source",
    "dataset_size",
    "label_source",
    "resumed_at",
    "record_id",
}


def _bare_bookkeeping(tags: dict[str, str]) -> list[str]:
    """The tags of a run outside what may stay bare: first-class, ``axis.*``, MLflow's, ``spot.*``."""
    return sorted(k for k in tags if k not in FIRST_CLASS and not k.startswith(("axis.", "mlflow.", "spot.")))


def test_the_names_of_tags():
    assert [tagnames.stored(k) for k in ("method", "dataset", "seed", "variant", "axis.iql.lr")] == [
        "method",
        "dataset",
        "seed",
        "variant",
        "axis.iql.lr",
    ]
    assert tagnames.stored("trial_key") == "spot.trial_key" and tagnames.stored("cache.reward") == "spot.cache.reward"
    assert tagnames.stored("spot.pid") == "spot.pid" and tagnames.stored("mlflow.runName") == "mlflow.runName"
    assert tagnames.stored("version.jax") == "spot.version.jax"
    assert tagnames.stored("failure_reason") == "failure_reason"
    assert tagnames.legacy("spot.sweep_id") == "sweep_id" and tagnames.legacy("sweep_id") == "sweep_id"
    old = {"sweep_id": "a", "cache.reward": "hit", "method": "pt"}
    assert tagnames.get(old, "sweep_id") == "a" and tagnames.get(old, "spot.cache.reward") == "hit"
    assert tagnames.get({"spot.sweep_id": "new", "sweep_id": "old"}, "sweep_id") == "new"
    assert tagnames.get({}, "trial_key", "-") == "-" and not tagnames.has(old, "trial_key")
    assert tagnames.normalized(old) == {"spot.sweep_id": "a", "spot.cache.reward": "hit", "method": "pt"}
    assert tagnames.normalized({"sweep_id": "old", "spot.sweep_id": "new"}) == {"spot.sweep_id": "new"}
    assert tagnames.alternatives({"sweep_id": "s", "axis.x": "1"}) == [
        {"spot.sweep_id": "s", "axis.x": "1"},
        {"sweep_id": "s", "axis.x": "1"},
    ]
    assert tagnames.alternatives({"method": "pt"}) == [{"method": "pt"}]


@pytest.fixture
def store(tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(tmp_path)
    uri = sqlite_uri(tmp_path / "mlflow.db")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = MlflowClient(uri)
    return uri, client, client.create_experiment("tagged")


def _context(uri: str, exp: str, sweep_id: str, parent: str):
    from spot.sweep.trial import SweepContext

    return SweepContext(sweep_id, "tagged", "tagged", exp, parent, uri, ("iql.lr",))


def _fake_run(ran: list):
    """A ``run_fn`` opening a real MLflow run (start_run: every tag a run starts with) that tags a
    stage-cache hit, as the pipeline does, and logs its scores."""

    def run(cfg, *, progress, parent_run_id, extra_tags, on_eval):
        with tracking.start_run(
            cfg, {"name": cfg.data.name}, extra_tags=extra_tags, parent_run_id=parent_run_id, system_metrics=False
        ) as tr:
            tr.set_tags({"cache.reward": "hit", "stage.reward.source": "reused"})
            tr.log_metrics({"eval/score_final": 12.5, "eval/score_best": 13.0})
            ran.append(tr.run_id)
            return {"run_id": tr.run_id, "eval/score_final": 12.5, "eval/score_best": 13.0}

    return run


def test_a_sweep_written_now_carries_only_the_new_names(store, tmp_path):
    """A trial's run (through start_run, with a stage-cache tag), a failed attempt's record and the
    launch's parent run: every bookkeeping tag under ``spot.``; the resume finds the finished run."""
    from spot.sweep import parent as parent_lib
    from spot.sweep import summary, trial

    uri, client, exp = store
    (tmp_path / "tagged.yaml").write_text(SWEEP)
    spec = sweep.load(tmp_path / "tagged.yaml")
    state = {"sweep_id": "tagged-1"}
    parent = parent_lib.open_parent(client, exp, spec, state, resume=False)
    ctx = _context(uri, exp, "tagged-1", parent)
    first = spec.trials()[0]
    ran: list[str] = []
    trial.run_trial(first.overrides, [0], ctx, trial_id="t1", report=lambda m: None, run_fn=_fake_run(ran))
    assert len(ran) == 1
    run = client.get_run(ran[0]).data.tags
    assert _bare_bookkeeping(run) == []
    assert run["spot.sweep_id"] == "tagged-1" and run["spot.trial_key"] == sweep.run_key(first.overrides, 0)
    assert run["spot.trial_id"] == "t1" and len(run["spot.attempt"]) == 32 and run["spot.cache.reward"] == "hit"
    assert run["spot.version.mlflow"] and run["spot.git_commit"] and run["spot.budget"] == "tiny"
    assert run["method"] == "oracle" and run["dataset"] == "drawer-open" and run["seed"] == "0"
    assert run["axis.iql.lr"] == "0.001" and run["variant"]
    assert _bare_bookkeeping(client.get_run(parent).data.tags) == []
    assert client.get_run(parent).data.tags["spot.sweep_id"] == "tagged-1"

    # The resume finds the finished run under the new names and does not run it again.
    again = trial.run_trial(first.overrides, [0], ctx, trial_id="t2", report=lambda m: None, run_fn=_fake_run(ran))
    assert len(ran) == 1 and again[0]["run_id"] == ran[0]

    # An attempt that failed before its run opened gets a FAILED run with the new names too.
    cfg = config.resolve(spec.trials()[1].overrides, {"seed": 0, "tracking.experiment": "tagged"})
    tags = trial._seed_tags(spec.trials()[1].overrides, sweep.run_key(spec.trials()[1].overrides, 0), ctx, "t3")
    failed = tracking.record_failure(client, exp, cfg, tags, ValueError("bad dataset"), parent_run_id=parent)
    assert _bare_bookkeeping(client.get_run(failed).data.tags) == []
    assert tracking.record_failure(client, exp, cfg, tags, ValueError("again")) is None  # found by spot.attempt

    parent_lib.open_parent(client, exp, spec, {**state, "parent_run_id": parent}, resume=True)
    assert "spot.resumed_at" in client.get_run(parent).data.tags
    rows = summary.summarize(spec, client, exp, "tagged-1")
    assert [(r.status, r.score_final, r.trial_id) for r in rows] == [("FINISHED", 12.5, "t1"), ("FAILED", None, "")]
    assert rows[1].reason == "ValueError: bad dataset"


def _old_store(client, exp: str, spec) -> tuple[str, list[str]]:
    """A launch as spot wrote it before the move: parent and trial runs with bare bookkeeping tags."""
    parent = client.create_run(exp, tags={"sweep_id": "old-1", "spot.role": "sweep", "git_commit": "abc"}).info.run_id
    runs = []
    for t, score in zip(spec.trials(), (20.0, 30.0), strict=True):
        tags = {
            "sweep_id": "old-1",
            "trial_key": sweep.run_key(t.overrides, 0),
            "trial_id": f"old{score:g}",
            "attempt": f"a{score:g}",
            "method": "oracle",
            "dataset": "drawer-open",
            "dataset_source": "recipe",
            "seed": "0",
            "git_commit": "abc",
            "data_digest": "d" * 64,
            "cache.reward": "hit",
            "axis.iql.lr": str(t.overrides["iql.lr"]),
            "mlflow.parentRunId": parent,
        }
        run = client.create_run(exp, tags=tags).info.run_id
        client.log_param(run, "iql.lr", t.overrides["iql.lr"])
        client.log_metric(run, "eval/score_final", score)
        client.set_terminated(run, "FINISHED")
        runs.append(run)
    client.set_terminated(parent, "FINISHED")
    return parent, runs


def test_a_store_with_the_old_names_resumes_summarizes_loads_and_exports(store, tmp_path):
    from spot.results import export, load
    from spot.sweep import summary, trial

    uri, client, exp = store
    (tmp_path / "tagged.yaml").write_text(SWEEP)
    spec = sweep.load(tmp_path / "tagged.yaml")
    parent, runs = _old_store(client, exp, spec)
    ctx = _context(uri, exp, "old-1", parent)

    ran: list[str] = []  # the resume finds both finished runs by their old sweep_id and trial_key
    for t in spec.trials():
        trial.run_trial(t.overrides, [0], ctx, trial_id="new", report=lambda m: None, run_fn=_fake_run(ran))
    assert ran == []
    rows = summary.summarize(spec, client, exp, "old-1")
    assert [(r.status, r.score_final, r.run_id, r.trial_id) for r in rows] == [
        ("FINISHED", 20.0, runs[0], "old20"),
        ("FINISHED", 30.0, runs[1], "old30"),
    ]

    frame = load.load_runs(uri, ["tagged"], sweep_id="old-1")  # the parent (no method tag) left out
    assert sorted(frame["run_id"]) == sorted(runs)
    assert set(frame["tags.spot.sweep_id"]) == {"old-1"} and set(frame["tags.spot.cache.reward"]) == {"hit"}
    assert "tags.sweep_id" not in frame and set(frame["dataset_source"]) == {"recipe"}
    out = export.to_frame(frame)
    assert list(out["sweep_id"]) == ["old-1", "old-1"] and list(out["git_commit"]) == ["abc", "abc"]
    assert list(out["data_digest"]) == ["d" * 64] * 2 and sorted(out["metrics.eval/score_final"]) == [20.0, 30.0]

    # The same runs under the new names export to the same CSV (but for the run ids).
    client.create_experiment("tagged-new")
    new_exp = client.get_experiment_by_name("tagged-new").experiment_id
    for run_id in runs:
        old = client.get_run(run_id).data
        tags = {**tagnames.stored_tags(old.tags), "mlflow.parentRunId": "p"}
        new = client.create_run(new_exp, tags=tags).info.run_id
        client.log_param(new, "iql.lr", old.params["iql.lr"])
        client.log_metric(new, "eval/score_final", old.metrics["eval/score_final"])
        client.set_terminated(new, "FINISHED")
    again = export.to_frame(load.load_runs(uri, ["tagged-new"], sweep_id="old-1"))
    cols = [c for c in out if c not in ("run_id", "experiment", "start_time", "end_time")]
    assert again[cols].equals(out[cols])


def test_old_runs_left_running_are_closed_and_stopped_by_their_old_names(store, tmp_path):
    from spot.sweep import parent as parent_lib
    from spot.sweep import reports

    uri, client, exp = store
    (tmp_path / "tagged.yaml").write_text(SWEEP)
    spec = sweep.load(tmp_path / "tagged.yaml")
    parent = client.create_run(exp, tags={"sweep_id": "old-2", "spot.role": "sweep"}).info.run_id
    cut = client.create_run(exp, tags={"sweep_id": "old-2", "trial_key": "k", "attempt": "a1"}).info.run_id
    stopped = client.create_run(exp, tags={"sweep_id": "old-2", "trial_key": "k2", "attempt": "a2"}).info.run_id
    other = client.create_run(exp, tags={"sweep_id": "another", "attempt": "a3"}).info.run_id
    parent_lib.open_parent(client, exp, spec, {"sweep_id": "old-2", "parent_run_id": parent}, resume=True)
    assert client.get_run(cut).info.status == "KILLED" and client.get_run(parent).info.status == "RUNNING"
    reports.mark_stopped(client, _context(uri, exp, "old-2", parent), ["a2"], reports.StoppedEarly("at step 5"))
    assert client.get_run(stopped).data.tags["failure_reason"] == "at step 5"
    assert client.get_run(other).info.status == "RUNNING"  # another launch's run


def test_records_with_the_old_names_import_under_the_new_ones(tmp_path):
    """A record folder written before the move (bare bookkeeping tags) imports as a run with the new
    names; a run imported back then (tag ``record_id``) is found as already imported."""
    from mlflow.tracking import MlflowClient

    from spot.tracking import record_checks, recorded
    from tests.test_recorded import _record

    new, old, done = _record(tmp_path, seed=0), _record(tmp_path, seed=1), _record(tmp_path, seed=2)
    assert record_checks.read_record(new)["tags"]["spot.cache.reward"] == "hit"
    assert _bare_bookkeeping(record_checks.read_record(new)["tags"]) == []
    head = json.loads((old / "record.json").read_text())
    head["tags"] = {tagnames.legacy(k) if k.startswith("spot.") else k: v for k, v in head["tags"].items()}
    assert {"cache.reward", "budget", "git_commit", "version.mlflow"} <= set(head["tags"])
    (old / "record.json").write_text(json.dumps(head))
    uri = sqlite_uri(tmp_path / "mlflow.db")
    client = MlflowClient(uri)
    exp = client.create_experiment("imported")
    earlier = client.create_run(exp, tags={"record_id": done.name}).info.run_id  # imported by an older spot
    client.set_terminated(earlier, "FINISHED")

    got = {d["record_id"]: d for d in recorded.import_records(tmp_path / "rec", uri, "imported")}
    assert got[done.name]["action"] == "already imported" and got[done.name]["run_id"] == earlier
    for folder in (new, old):
        assert got[folder.name]["action"] == "imported"
        tags = client.get_run(got[folder.name]["run_id"]).data.tags
        assert _bare_bookkeeping(tags) == [] and tags["spot.record_id"] == folder.name
        assert tags["spot.cache.reward"] == "hit" and tags["method"] == "oracle" and tags["spot.budget"] == "tiny"
