"""The `spot` command through a subprocess: help, data, labels, config; exit code 2 on user errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mlflow.tracking import MlflowClient

from spot import cli, stages
from tests.conftest import run_cli

PT_LABELS = Path(__file__).parent / "data" / "pt-human-labels"


@pytest.mark.parametrize(
    "cmd", [[], ["data"], ["data", "build"], ["labels", "make"], ["run"], ["bench"], ["config", "show"]]
)
def test_help_on_every_command(cmd):
    out = run_cli(*cmd, "--help")
    assert out.returncode == 0, out.stderr
    assert "usage: spot" in out.stdout


def test_data_build_info_and_labels(tmp_path, spot_dirs, tiny_drawer):
    listed = run_cli("data", "list")
    assert listed.returncode == 0 and "hopper-medium-replay" in listed.stdout and "drawer-open" in listed.stdout
    assert "size=tiny" in listed.stdout  # the session's tiny build is listed
    built = run_cli("data", "build", "drawer-open", "--size", "tiny")  # cached: returns at once
    assert built.returncode == 0, built.stderr
    assert str(tiny_drawer) in built.stdout
    info = run_cli("data", "info", "drawer-open", "--size", "tiny")
    assert info.returncode == 0, info.stderr
    summary = json.loads(info.stdout)["summary"]
    assert summary["obs_dim"] == 39 and summary["act_dim"] == 4 and summary["transitions"] > 1000
    out = tmp_path / "q.npz"
    made = run_cli(
        "labels",
        "make",
        "drawer-open",
        "--size",
        "tiny",
        "--num-queries",
        "30",
        "--segment-length",
        "25",
        "--out",
        str(out),
    )
    assert made.returncode == 0, made.stderr
    with np.load(out) as z:
        assert len(z["labels"]) == 30
    shown = run_cli("labels", "info", str(out), "--dataset", "drawer-open", "--size", "tiny")
    assert shown.returncode == 0 and "all segments fit" in shown.stdout
    dense = run_cli(
        "labels",
        "make",
        "drawer-open",
        "--size",
        "tiny",
        "--num-queries",
        "30",
        "--segment-length",
        "25",
        "--score",
        "dense",
        "--out",
        str(out),
    )
    assert dense.returncode == 2 and "no dense reward 'infos/dense_reward'" in dense.stderr


def test_labels_make_resolves_its_settings_like_run(tmp_path, spot_dirs, tiny_drawer):
    """On drawer-open the Meta-World suite preset gives 25-step segments and the discounted teacher,
    for `spot labels make` as for `spot run`; flags and overrides win over presets."""
    from spot import config
    from spot.data import labels, registry
    from spot.run import label_stages

    out = tmp_path / "q.npz"
    made = run_cli("labels", "make", "drawer-open", "--size", "tiny", "labels.num_queries=30", "--out", str(out))
    assert made.returncode == 0, made.stderr
    assert "teacher=discounted" in made.stdout and "budget=small" in made.stdout
    got = labels.Preferences.load_npz(out)
    cfg = config.load(None, ["data.name=drawer-open", "data.size=tiny", "labels.num_queries=30"])  # `spot run`'s
    assert (cfg.labels.segment_length, cfg.labels.teacher) == (25, "discounted")
    ds, _ = registry.load("drawer-open", "tiny", 0, progress=False)
    expected = label_stages.make_preferences(cfg, ds)
    assert got.segment_length == 25 and len(got) == 30
    for name in ("starts_1", "starts_2", "labels"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))
    by_hand = labels.scripted_teacher(ds, 30, 25, teacher="discounted", discount=0.99, seed=42)
    np.testing.assert_array_equal(got.labels, by_hand.labels)
    # a flag (shorthand for labels.teacher) and an override beat the suite preset
    made = run_cli(
        "labels",
        "make",
        "drawer-open",
        "--size",
        "tiny",
        "labels.num_queries=30",
        "labels.segment_length=40",
        "--teacher",
        "sum",
        "--out",
        str(out),
    )
    assert made.returncode == 0, made.stderr
    assert "teacher=sum" in made.stdout
    got = labels.Preferences.load_npz(out)
    assert got.segment_length == 40
    np.testing.assert_array_equal(got.labels, labels.scripted_teacher(ds, 30, 40, teacher="sum", seed=42).labels)
    bad = run_cli("labels", "make", "drawer-open", "--size", "tiny", "labels.num_querys=3", "--out", str(out))
    assert bad.returncode == 2 and "did you mean 'labels.num_queries'" in bad.stderr


def test_labels_info_on_real_pt_files():
    out = run_cli("labels", "info", str(PT_LABELS / "hopper-medium-replay-v2"))
    assert out.returncode == 0, out.stderr
    assert "500 queries, segment length 100" in out.stdout
    assert "ties 191" in out.stdout


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["data", "build", "hopper-mediun"], "unknown dataset 'hopper-mediun'; did you mean hopper-medium"),
        (["data", "info", "/no/such/file.hdf5"], "unknown dataset '/no/such/file.hdf5'"),
        (["config", "show", "iql.stepz=3"], "unknown config key 'iql.stepz'; did you mean 'iql.steps'"),
        (["config", "show", "shaping.weight=3"], "'shaping.weight': value 3.0 is out of range"),
        (["run", "/no/such.yaml"], "config file '/no/such.yaml' does not exist"),
        (["labels", "info", "/no/such/folder"], "/no/such/folder"),
    ],
)
def test_user_errors_exit_2_without_traceback(args, fragment, spot_dirs):
    out = run_cli(*args)
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert fragment in out.stderr
    assert "Traceback" not in out.stderr


def test_label_index_past_dataset_end_is_a_user_error(spot_dirs, tiny_drawer):
    # The real hopper labels index ~400k transitions; the tiny drawer dataset is much shorter.
    out = run_cli(
        "labels", "info", str(PT_LABELS / "hopper-medium-replay-v2"), "--dataset", "drawer-open", "--size", "tiny"
    )
    assert out.returncode == 2 and "past the end" in out.stderr and "Traceback" not in out.stderr


def test_config_show_resolves_presets(tmp_path):
    f = tmp_path / "r.yaml"
    f.write_text("method: spot\nbudget: tiny\n")
    out = run_cli("config", "show", str(f), "shaping.weight=0.5")
    assert out.returncode == 0, out.stderr
    assert "kind: cosine" in out.stdout and "weight: 0.5" in out.stdout
    keys = run_cli("config", "keys")
    assert "iql.expectile" in keys.stdout and "one of ['top', 'top_next', 'bottom_next', 'bottom']" in keys.stdout


# --------------------------------------------------------------------------- help, version, flags
def _leaf_parsers(parser, path=()):
    import argparse

    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, child in action.choices.items():
            yield from _leaf_parsers(child, (*path, name))


def test_every_command_has_an_example_and_shows_defaults():
    from spot import cli

    leaves = dict(_leaf_parsers(cli.build_parser()))
    assert len(leaves) >= 18 and ("eval",) in leaves
    for path, parser in leaves.items():
        text = parser.format_help()
        assert "example" in text and f"spot {' '.join(path)}" in text.split("example")[-1], path
    text = leaves[("data", "build")].format_help()
    assert "(default: small)" in text and "(default: 0)" in text
    assert "(default: spot_runs/ray)" in leaves[("sweep",)].format_help()


def test_version(capsys):
    from importlib.metadata import version

    from spot import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"spot {version('spot-pbrl')}"


def test_one_name_per_concept_across_commands():
    from spot import cli

    p = cli.build_parser()
    for argv in (
        ["run"],
        ["eval", "r"],
        ["sweep", "f"],
        ["tables", "--table", "1"],
        ["report"],
        ["results", "export", "--experiment", "e", "--out", "o"],
        ["figures", "fig2"],
        ["figures", "fig3"],
        ["figures", "fig4"],
    ):
        assert p.parse_args([*argv, "--tracking-uri", "http://h:1"]).tracking_uri == "http://h:1", argv
    for argv in (
        ["data", "build", "x"],
        ["data", "info", "x"],
        ["labels", "info", "p"],
        ["labels", "make", "d", "--out", "o"],
        ["figures", "fig3"],
        ["figures", "fig4"],
    ):
        assert p.parse_args([*argv, "--data-seed", "3"]).data_seed == 3, argv
        assert p.parse_args([*argv, "--seed", "4"]).data_seed == 4, argv  # the old name
    for argv in (
        ["run"],
        ["data", "build", "x"],
        ["data", "info", "x"],
        ["data", "fetch"],
        ["labels", "info", "p"],
        ["labels", "make", "d", "--out", "o"],
    ):
        assert p.parse_args([*argv, "--quiet"]).quiet is True, argv


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", "f.yaml", "--max-concurrent", "0"],
        ["sweep", "f.yaml", "--max-concurrent", "x"],
        ["eval", "r", "--episodes", "0"],
        ["bench", "iql", "--seeds", "-1"],
    ],
)
def test_counts_must_be_positive(argv, capsys):
    from spot import cli

    with pytest.raises(SystemExit) as e:
        cli.build_parser().parse_args(argv)
    assert e.value.code == 2 and "expected a positive integer" in capsys.readouterr().err


def test_run_takes_tracking_uri_and_says_where_it_logged(tmp_path, monkeypatch, capsys):
    """`spot run --tracking-uri` is the override tracking.uri=; the run's end names the store, the
    lean mlflow ui command and links to the run and the runs table (pipeline.run stubbed: an empty
    MLflow run)."""
    from spot import cli, pipeline, tracking

    seen = {}

    def fake_run(cfg, progress):
        seen["cfg"] = cfg
        with tracking.start_run(cfg, {"name": "x"}, system_metrics=False) as tr:
            return {"run_id": tr.run_id, "eval/score_final": 1.0}

    monkeypatch.setattr(pipeline, "run", fake_run)
    uri = f"sqlite:///{tmp_path / 'm.db'}"
    assert cli.main(["run", "method=pt", "tracking.experiment=cli", "--tracking-uri", uri, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert seen["cfg"].tracking.uri == uri and seen["cfg"].method == "pt"
    run_id = out.split()[1].rstrip(":")
    exp_id = MlflowClient(uri).get_experiment_by_name("cli").experiment_id
    assert f"logged to {uri} (experiment id {exp_id}, run {run_id})" in out
    assert f"open the runs with: spot ui --tracking-uri {uri}" in out
    assert f"then: http://127.0.0.1:5000/#/experiments/{exp_id}/runs/{run_id}" in out
    assert f"runs table: http://127.0.0.1:5000/#/experiments/{exp_id}/runs?workflowType=machine_learning" in out


def test_fig4_honours_the_output_extension(tmp_path, capsys):
    from matplotlib.figure import Figure

    from spot import cli, config, tracking

    png = tmp_path / "subgoal_projection.png"
    fig = Figure(figsize=(2, 1.5), dpi=50)
    fig.subplots().plot([0, 1], [1, 0])
    fig.savefig(png)
    uri = f"sqlite:///{tmp_path / 'm.db'}"
    with tracking.start_run(config.load(None, [f"tracking.uri={uri}"]), {"name": "x"}, system_metrics=False) as tr:
        tr.log_artifact(png)
    magic = {"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml", "jpg": b"\xff\xd8\xff"}
    for ext, head in magic.items():
        out = tmp_path / f"fig4.{ext}"
        assert cli.main(["figures", "fig4", "--run-id", tr.run_id, "--out", str(out), "--tracking-uri", uri]) == 0
        assert out.read_bytes().startswith(head), ext
    assert (tmp_path / "fig4.png").read_bytes() == png.read_bytes()  # a PNG is copied as is
    assert (
        cli.main(["figures", "fig4", "--run-id", tr.run_id, "--out", str(tmp_path / "f.xyz"), "--tracking-uri", uri])
        == 2
    )
    assert "unknown figure format 'xyz'" in capsys.readouterr().err


def test_sweep_dry_run_lists_trials_and_launches_nothing(tmp_path):
    sweep_file = Path(__file__).resolve().parents[1] / "sweeps" / "quickstart.yaml"
    out = run_cli("sweep", str(sweep_file), "--dry-run", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "3 trials, 3 runs" in out.stdout
    assert [ln.split()[1] for ln in out.stdout.splitlines()[1:]] == ["method=oracle", "method=pt", "method=spot"]
    assert list(tmp_path.iterdir()) == []  # no store, no Ray folder


def test_output_into_a_closed_pipe_stops_quietly(tmp_path):
    # `spot sweep FILE --dry-run | head`: the reader leaves early; no traceback, status 141. The sweep
    # has 3 x 3000 trials (under spec.MAX_RUNS) so that its listing (~150 kB) overflows the pipe's
    # buffer after head has left.
    repo = Path(__file__).resolve().parents[1]
    sweep = yaml.safe_load((repo / "sweeps" / "quickstart.yaml").read_text())
    sweep["seeds"] = list(range(3000))
    (tmp_path / "big.yaml").write_text(yaml.safe_dump(sweep))
    cmd = f"{sys.executable} -m spot.cli sweep {tmp_path / 'big.yaml'} --dry-run | head -c 1 > /dev/null"
    proc = subprocess.run(
        ["bash", "-c", f"set -o pipefail; {cmd}"], cwd=repo, capture_output=True, text=True, env=dict(os.environ)
    )
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr, proc.stderr
    assert proc.returncode == 141, (proc.returncode, proc.stderr)


def test_a_broken_pipe_that_is_not_stdout_is_a_real_error(monkeypatch):
    # a closed socket or child pipe (MLflow over HTTP, Ray) must not pass for `| head`

    def broken() -> None:
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(stages, "load_plugins", broken)
    with pytest.raises(BrokenPipeError):
        cli.main(["data", "list"])
