"""MLflow's own fields on a run, and the links and command that open the runs table."""

import json
import re
import shlex
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import pytest
from mlflow.tracking import MlflowClient

from spot import tracking

ROOT = Path(__file__).resolve().parents[1]


def test_sweep_link_opens_the_runs_table_filtered_to_the_sweep():
    url = tracking.sweep_url("7", "quickstart-20261125-081500-ab12")
    parsed = urlparse(url)
    assert (parsed.scheme, parsed.netloc, parsed.path) == ("http", "127.0.0.1:5000", "/")
    route, _, query = parsed.fragment.partition("?")
    assert route == "/experiments/7/runs"
    q = parse_qs(query)
    assert q["workflowType"] == ["machine_learning"]
    assert q["viewStateShareKey"] == ["spot-quickstart-20261125-081500-ab12"]  # the view share_sweep_view writes
    assert "searchFilter" not in q  # (the UI ignores a shared view when the link has a filter of its own)
    view = tracking.ui.sweep_view("p1", ("method", "shaping.weight"))
    assert view["searchFilter"] == "tags.`mlflow.parentRunId` = 'p1'"
    assert (
        "tags.`axis.shaping.weight`" in view["selectedColumns"] and "tags.`axis.method`" not in view["selectedColumns"]
    )
    assert "metrics.`eval/score_final`" in view["selectedColumns"] and "tags.`seed`" in view["selectedColumns"]
    assert " " not in url and "'" not in url  # URL-encoded
    assert tracking.runs_url("3", base="http://mlflow:5000/").startswith(
        "http://mlflow:5000/#/experiments/3/runs?workflowType=machine_learning"
    )


def test_ui_command_is_the_lean_one():
    assert (
        tracking.ui_command("sqlite:////w/spot runs/mlflow.db")
        == "spot ui --tracking-uri 'sqlite:////w/spot runs/mlflow.db'"
    )
    words = shlex.split(tracking.ui.server_command("sqlite:////w/spot_runs/mlflow.db", "/w/spot runs/artifacts", 5000))
    assert words[0] == "MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false" and words[1:3] == ["mlflow", "server"]
    assert words[words.index("--workers") + 1] == "1" and words[words.index("--host") + 1] == "127.0.0.1"
    assert words[words.index("--artifacts-destination") + 1] == "/w/spot runs/artifacts"  # quoted


def test_ui_command_options_exist_in_the_installed_mlflow():
    from click.testing import CliRunner
    from mlflow.cli import cli

    text = CliRunner().invoke(cli, ["ui", "--help"]).output
    for option in ("--backend-store-uri", "--artifacts-destination", "--workers"):
        assert option in text
    from mlflow.environment_variables import MLFLOW_SERVER_ENABLE_JOB_EXECUTION

    assert MLFLOW_SERVER_ENABLE_JOB_EXECUTION.name == "MLFLOW_SERVER_ENABLE_JOB_EXECUTION"


@pytest.mark.slow
def test_a_runs_record_has_mlflows_own_fields(tmp_path, spot_dirs, tiny_drawer, monkeypatch, capsys):
    from spot import cli

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    monkeypatch.setenv("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL", "1")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    argv = [
        "run",
        "method=oracle",
        "budget=tiny",
        "data.name=drawer-open",
        "iql.steps=100",
        "eval.every=100",
        "tracking.experiment=fields",
        "--tracking-uri",
        uri,
        "--quiet",
    ]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    run_id = re.search(r"^run ([0-9a-f]{32}):", printed, re.M).group(1)
    client = MlflowClient(uri)
    run = client.get_run(run_id)
    exp_id = run.info.experiment_id
    tags = run.data.tags

    # `spot run` says where it logged, how to open it and links to the run and the runs table
    assert f"logged to {uri} (experiment id {exp_id}, run {run_id})" in printed
    assert f"open the runs with: spot ui --tracking-uri {uri}" in printed
    assert f"#/experiments/{exp_id}/runs/{run_id}" in printed
    assert f"#/experiments/{exp_id}/runs?workflowType=machine_learning" in printed
    assert run.info.status == "FINISHED" and tags["mlflow.runName"] == "oracle drawer-open s0"  # by what varies
    # an ML experiment (MLflow's model-training workspace); the paper's score beside the run's own
    assert client.get_experiment(exp_id).tags["mlflow.experimentKind"] == "custom_model_development"
    assert tags["variant"] == "spot" and tags["method"] == "oracle" and tags["seed"] == "0"
    assert "eval/score_paper" not in run.data.metrics  # the paper's Table 1 has no Oracle on drawer-open

    # source and version
    assert tags["mlflow.source.name"] == shlex.join(["spot", *argv]) and tags["mlflow.source.type"] == "LOCAL"
    if tracking.git_commit() != "unknown":
        assert re.fullmatch(r"[0-9a-f]{40}", tags["mlflow.source.git.commit"])
        assert tags["spot.git_commit"].startswith(tags["mlflow.source.git.commit"])

    # the description: method, dataset, budget, the command line and a command that reproduces it
    note = tags["mlflow.note.content"]
    assert "**oracle** on **drawer-open**" in note and "budget **tiny**" in note
    assert shlex.join(["spot", *argv]) in note
    assert "spot run method=oracle budget=tiny variant=spot data.name=drawer-open seed=0 iql.steps=100" in note

    # the dataset as an input, with the fingerprint the stage cache uses
    digest = tags["spot.data_digest"]
    assert re.fullmatch(r"[0-9a-f]{64}", digest)
    (inp,) = run.inputs.dataset_inputs
    assert inp.dataset.name == "drawer-open" and inp.dataset.digest == digest[:32]
    assert {(t.key, t.value) for t in inp.tags} == {("mlflow.data.context", "training")}
    assert json.loads(inp.dataset.source)["uri"].endswith(".hdf5")
    schema = json.loads(inp.dataset.schema)["mlflow_colspec"]
    assert {c["name"]: c["tensor-spec"]["shape"] for c in schema}["observations"] == [-1, 39]

    # system metrics, the environment, only the Oracle's params
    assert "system/cpu_utilization_percentage" in run.data.metrics
    assert "system/system_memory_usage_megabytes" in run.data.metrics
    names = {a.path for a in client.list_artifacts(run_id)}
    assert {"environment.json", "requirements.txt", "config.yaml", "models"} <= names
    with open(client.download_artifacts(run_id, "environment.json", str(tmp_path))) as f:
        env = json.load(f)
    assert env["python"] and env["cpu"]["count"] >= 1 and "mlflow" in env["packages"]
    assert "XLA_FLAGS" in env["env"]  # spot.runtime.configure sets it
    with open(client.download_artifacts(run_id, "requirements.txt", str(tmp_path))) as f:
        assert f"mlflow=={env['packages']['mlflow']}\n" in f.read()
    assert not any(k.startswith(("mr.", "pt.", "hpl.", "ipl.")) for k in run.data.params)
    assert not any(k.startswith("cache/") for k in run.data.metrics)


def test_the_papers_table1_score_is_logged_beside_the_runs_own(tmp_path):
    """``eval/score_paper``: the paper's Table 1 mean of the run's (method, dataset), read here from
    the CSV row itself; a cell the paper lacks logs nothing."""
    from spot.tracking import naming

    rows = [line.split(",") for line in (ROOT / "spot" / "paper_tables.csv").read_text().splitlines()[1:]]
    pt_hopper = [r for r in rows if r[:3] == ["1", "hopper-medium-replay", "pt"] and r[3] == ""]
    assert naming.paper_score("pt", "hopper-medium-replay-v2") == float(pt_hopper[0][4])
    assert naming.paper_score("oracle", "drawer-open") is None and naming.paper_score("pt", "nope") is None
    tracker = tracking.MemoryTracker()
    naming.log_paper_score(tracker, "pt", "hopper-medium-replay")
    assert tracker.metrics["eval/score_paper"] == [(0, float(pt_hopper[0][4]))]
    # run names by what varies: a sweep trial's axes (λ for the shaping weight), else the dataset
    tags = {"axis.method": "spot", "axis.shaping.weight": "0.5", "axis.labels.num_queries": "100"}
    assert naming.run_name("spot", "hopper-medium-replay", 1, tags) == "spot λ=0.5 num_queries=100 s1"
    assert naming.run_name("pt", "walker2d-medium-replay", 0, {"axis.data.name": "walker2d"}) == "pt walker2d s0"
    assert naming.run_name("pt", "walker2d-medium-replay", 2, {}) == "pt walker2d-medium-replay s2"
