"""The tracker interface: the in-memory and the MLflow implementation."""

import math

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from spot import SpotError, config, tracking


def _params(cfg):
    """What MLflow returns for the params of ``cfg``: the active ones, as strings."""
    return {k: str(list(v) if isinstance(v, tuple) else v) for k, v in tracking.active_params(cfg).items()}


def test_memory_tracker_keeps_steps_and_drops_non_finite(tmp_path):
    tr = tracking.MemoryTracker()
    tr.log_metrics({"a": 1, "b": float("nan"), "c": None, "d": np.float32(2.5)}, step=3)
    tr.log_series("s", [10, 20, 30], [1.0, math.inf, 3.0])
    f = tmp_path / "x.txt"
    f.write_text("hello")
    tr.log_artifact(f)
    tr.set_tags({"k": 1})
    assert tr.metrics == {"a": [(3, 1.0)], "d": [(3, 2.5)], "s": [(10, 1.0), (30, 3.0)]}
    assert tr.artifacts["x.txt"] == b"hello" and tr.tags == {"k": "1"}
    tr.log_artifact(f, "models")
    tr.log_dict({"a": [1.0, float("nan")], "b": np.array([np.inf, 2.0]), "c": np.float32(0.5)}, "x.json")
    assert tr.artifacts["models/x.txt"] == b"hello"
    assert tr.artifacts["x.json"] == {"a": [1.0, None], "b": [None, 2.0], "c": 0.5}  # valid JSON: no NaN
    assert isinstance(tr, tracking.Tracker)


def test_json_artifacts_are_strict_json(tmp_path):
    import json

    cfg = config.load(None, [f"tracking.uri=sqlite:///{tmp_path / 'm.db'}", "tracking.experiment=t"])
    with tracking.start_run(cfg, {"name": "hopper-medium-replay"}, system_metrics=False) as tr:
        tr.log_dict({"mean_error": [[0.5, float("nan")], [float("-inf"), 1.0]]}, "extrapolation_error.json")
    path = tmp_path / "artifacts" / tr.run_id  # spot's local store keeps artifacts beside the database
    got = next(path.rglob("extrapolation_error.json")).read_text()

    def refuse(name):
        raise ValueError(f"bare {name} in JSON")

    assert json.loads(got, parse_constant=refuse) == {"mean_error": [[0.5, None], [None, 1.0]]}


@pytest.mark.parametrize(
    "method, dropped",
    [
        ("oracle", ("mr.", "pt.", "hpl.", "ipl.")),
        ("mr", ("pt.", "hpl.", "ipl.")),
        ("pt", ("mr.", "hpl.", "ipl.")),
        ("spot", ("mr.", "hpl.", "ipl.")),
        ("ipl", ("mr.", "pt.", "hpl.")),
        ("hpl", ("mr.", "pt.", "ipl.")),
    ],
)
def test_only_the_active_methods_params(method, dropped):
    cfg = config.load(None, [f"method={method}"])
    flat, active = config.to_flat(cfg), tracking.active_params(cfg)
    assert not any(k.startswith(dropped) for k in active)
    assert active == {k: v for k, v in flat.items() if not k.startswith(dropped)}  # the rest, all of it


@pytest.mark.parametrize(
    "overrides",
    [
        ["method=spot", "budget=tiny", "data.name=drawer-open", "seed=3", "iql.hidden=[8, 8]", "shaping.weight=0.5"],
        ["method=oracle", "variant=authors", "labels.teacher=discounted", "eval.every=3000"],
        ["method=hpl", "budget=small", "data.name=walker2d-medium-replay", "tracking.experiment=x"],
    ],
)
def test_reproduce_command_resolves_to_the_same_config(overrides):
    import shlex

    cfg = config.load(None, overrides)
    command = tracking.reproduce_command(cfg)
    words = shlex.split(command)
    assert words[:2] == ["spot", "run"] and not any(w.startswith("tracking.") for w in words)
    again = config.load(None, words[2:])
    assert config.replace(again, **{"tracking.experiment": cfg.tracking.experiment}) == cfg


def test_mlflow_tracker_batches_and_marks_failures(tmp_path):
    cfg = config.load(None, [f"tracking.uri=sqlite:///{tmp_path / 'm.db'}", "tracking.experiment=t"])
    with tracking.start_run(cfg, {"name": "hopper-medium-replay", "source": "recipe"}) as tr:
        tr.log_series("curve", range(1500), np.arange(1500.0))  # more than one log_batch request
        tr.log_metrics({"x": 1.0, "nan": float("nan")})
        run_id = tr.run_id
    client = MlflowClient(cfg.tracking.uri)
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and run.data.metrics["x"] == 1.0 and "nan" not in run.data.metrics
    history = client.get_metric_history(run_id, "curve")
    assert len(history) == 1500 and {m.step for m in history} == set(range(1500))
    assert run.data.params == _params(cfg)  # every active param, across several batches
    with pytest.raises(RuntimeError), tracking.start_run(cfg, {"name": "x"}) as tr:
        raise RuntimeError("boom")
    failed = client.get_run(tr.run_id)
    assert failed.info.status == "FAILED" and failed.data.tags["failure_reason"] == "RuntimeError: boom"


# --------------------------------------------------------------------------- store and queries
def test_resolve_uri_for_writing_and_reading(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert tracking.resolve_uri("http://h:5") == "http://h:5"
    new, old = tmp_path / "spot_runs" / "mlflow.db", tmp_path / "mlruns" / "mlflow.db"
    assert tracking.resolve_uri() == f"sqlite:///{new}"  # spot run's store is spot sweep's
    assert (tmp_path / "spot_runs").is_dir() and not (tmp_path / "mlruns").exists()
    with pytest.raises(SpotError, match="no MLflow store here"):
        tracking.resolve_uri(read=True)
    old.parent.mkdir()
    old.touch()  # a folder from before: spot run wrote ./mlruns/mlflow.db
    assert tracking.resolve_uri(read=True) == f"sqlite:///{old}"
    assert "note: reading" in capsys.readouterr().err
    new.touch()  # both: the default store, and a note naming the other
    assert tracking.resolve_uri(read=True) == f"sqlite:///{new}"
    assert f"{old} (an older spot run's store) is not read" in capsys.readouterr().err
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{old}")
    assert tracking.resolve_uri(read=True) == f"sqlite:///{old}"
    with pytest.raises(SpotError, match="no MLflow store at"):
        tracking.resolve_uri(f"sqlite:///{tmp_path / 'nope.db'}", read=True)


def test_quote_picks_the_quote_the_value_lacks():
    assert tracking.quote("ab") == "'ab'" and tracking.quote("it's") == '"it\'s"' and tracking.quote('a"b') == "'a\"b'"
    with pytest.raises(SpotError, match="both quote characters"):
        tracking.quote("'\"")
    assert (
        tracking.tag_filter({"sweep_id": "s", "axis.data.name": "x"}, "RUNNING")
        == "tags.`sweep_id` = 's' and tags.`axis.data.name` = 'x' and attributes.status = 'RUNNING'"
    )


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    return MlflowClient(f"sqlite:///{tmp_path_factory.mktemp('q') / 'm.db'}")


def test_queries_page_find_finished_and_close_orphans(client, monkeypatch):
    from spot.tracking import queries

    e1, e2 = client.create_experiment("q1"), client.create_experiment("q2")
    ids = {}
    for i, (exp, status) in enumerate(
        [(e1, "FINISHED"), (e1, "RUNNING"), (e1, "RUNNING"), (e2, "FAILED"), (e2, "RUNNING")]
    ):
        run = client.create_run(exp, tags={"sweep_id": "it's", "n": str(i)})
        if status != "RUNNING":
            client.set_terminated(run.info.run_id, status)
        ids[i] = run.info.run_id
    monkeypatch.setattr(queries, "PAGE", 2)  # several pages
    monkeypatch.setattr(queries, "SEARCH_EXPERIMENTS", 1)  # one request per experiment
    found = list(tracking.search_runs(client, [e1, e2], tracking.tag_filter({"sweep_id": "it's"})))
    assert sorted(r.data.tags["n"] for r in found) == ["0", "1", "2", "3", "4"]
    assert tracking.finished_run(client, e1, {"sweep_id": "it's"}).info.run_id == ids[0]
    assert tracking.finished_run(client, e2, {"sweep_id": "it's"}) is None
    assert tracking.close_orphans(client, e1, {"sweep_id": "it's"}, "gone", keep=(ids[1],)) == 1
    closed = client.get_run(ids[2])
    assert closed.info.status == "KILLED" and closed.data.tags["failure_reason"] == "gone"
    assert client.get_run(ids[1]).info.status == "RUNNING" and client.get_run(ids[4]).info.status == "RUNNING"


def test_record_failure_once_per_attempt(client):
    exp = client.create_experiment("f")
    cfg = config.load(None, ["method=pt", "budget=tiny"])
    tags = {"attempt": "a1", "sweep_id": "s"}
    run_id = tracking.record_failure(client, exp, cfg, tags, ValueError("bad file"), parent_run_id="p")
    run = client.get_run(run_id)
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"] == "ValueError: bad file"
    assert run.data.tags["mlflow.parentRunId"] == "p" and run.data.tags["method"] == "pt"
    assert run.data.params == _params(cfg)  # every active param (over 100: several batches)
    assert tracking.record_failure(client, exp, cfg, tags, ValueError("again")) is None  # the attempt has one


def test_a_run_is_found_by_its_lookup_tags_only_once_its_params_are_in(client):
    """A process killed between creating a run and logging its params leaves a run that the sweep's
    lookups (trial_key, attempt) do not find: those tags arrive in the same request as the last
    batch of params."""
    from spot.tracking import record

    exp = client.create_experiment("lookup")
    cfg = config.load(None, ["method=pt", "budget=tiny"])
    tags = {"trial_key": "k1", "attempt": "a1", "sweep_id": "s"}
    run = record.create_run(client, exp, "r", tags, cfg)  # ... and the process dies here
    got = client.get_run(run.info.run_id).data
    assert got.tags["spot.sweep_id"] == "s" and not {"trial_key", "spot.trial_key", "attempt", "spot.attempt"} & set(
        got.tags
    )
    assert got.params == {}
    assert tracking.finished_run(client, exp, {"trial_key": "k1"}) is None
    record.log_params(client, run.info.run_id, cfg, record.lookup_tags(tags))
    got = client.get_run(run.info.run_id).data
    assert got.tags["spot.trial_key"] == "k1" and got.tags["spot.attempt"] == "a1" and got.params == _params(cfg)


class _LosesTheInsertRace:
    """A client whose first ``log_inputs`` finds that another run (``rival``) inserted the same
    dataset between MLflow's lookup and its insert: the rival's call goes through, then the store's
    unique-constraint error is raised, as the REST store raised it in a sweep (session 8)."""

    def __init__(self, client, rival, fails=1, message=None):
        self.client, self.rival, self.fails, self.calls = client, rival, fails, 0
        self.message = message or (
            "BAD_REQUEST: (sqlite3.IntegrityError) UNIQUE constraint failed: "
            "datasets.experiment_id, datasets.name, datasets.digest"
        )

    def log_inputs(self, run_id, datasets):
        from mlflow.exceptions import MlflowException

        self.calls += 1
        if self.calls == 1:
            self.client.log_inputs(self.rival, datasets=datasets)
        if self.calls <= self.fails:
            raise MlflowException(self.message)
        return self.client.log_inputs(run_id, datasets=datasets)


def _dataset_args(tmp_path):
    from types import SimpleNamespace

    path = tmp_path / "toy.hdf5"
    path.write_bytes(b"")
    ds = SimpleNamespace(observations=np.zeros((4, 3), np.float32), actions=np.zeros((4, 2), np.float32))
    cfg = config.load(None, ["method=pt", "budget=tiny", f"data.name={path}"])
    return ds, {"name": "toy"}, cfg, "ab" * 20


def test_a_run_that_loses_the_dataset_insert_race_still_logs_its_input(client, tmp_path, monkeypatch):
    from spot.tracking import record

    monkeypatch.setattr(record.time, "sleep", lambda s: None)
    exp = client.create_experiment("race")
    first, second = (client.create_run(exp).info.run_id for _ in range(2))
    racing = _LosesTheInsertRace(client, rival=first)
    record.log_dataset_input(racing, second, *_dataset_args(tmp_path))
    assert racing.calls == 2  # the lost race, then the retry that links the existing row
    for run_id in (first, second):
        (inp,) = client.get_run(run_id).inputs.dataset_inputs
        assert (inp.dataset.name, inp.dataset.digest) == ("toy", "ab" * 16)
        assert {t.key: t.value for t in inp.tags} == {"mlflow.data.context": "training"}


@pytest.mark.parametrize("fails, message", [(5, None), (1, "RESOURCE_DOES_NOT_EXIST: run 'x' not found")])
def test_other_input_errors_and_a_race_that_never_ends_are_raised(client, tmp_path, monkeypatch, fails, message):
    from mlflow.exceptions import MlflowException

    from spot.tracking import record

    assert message or record.INPUT_RACE_TRIES == fails  # the race is lost on every try
    monkeypatch.setattr(record.time, "sleep", lambda s: None)
    exp = client.create_experiment(f"race-{fails}")
    first, second = (client.create_run(exp).info.run_id for _ in range(2))
    racing = _LosesTheInsertRace(client, rival=first, fails=fails, message=message)
    with pytest.raises(MlflowException, match=message.split(":")[0] if message else "UNIQUE constraint"):
        record.log_dataset_input(racing, second, *_dataset_args(tmp_path))
    assert racing.calls == fails
