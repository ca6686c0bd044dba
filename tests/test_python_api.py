"""The Python API (docs/python.md): a sweep from a dict or a file, runs as a DataFrame, a table and
the claims report from that frame, each checked against the file path or the CLI it stands for."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pandas as pd
import pytest
import yaml

import spot.results
from spot import SpotError, cli, sweep

ROOT = Path(__file__).resolve().parents[1]
WALKER = ROOT / "experiments" / "lab-walker2d"
TABLE1_CSV = ROOT / "experiments" / "lab-hopper-medium-replay" / "results" / "lab_table1.csv"

SWEEP = {
    "name": "api-test",
    "base": {"budget": "tiny", "data": {"name": "hopper-medium-replay", "size": "tiny"}, "labels.source": "script"},
    "grid": {"method": ["oracle", "pt"], "iql.lr": [1e-3, 3e-4]},
    "zip": {"iql.expectile": [0.7, 0.8], "iql.temperature": [3.0, 5.0]},
    "seeds": [0, 2],
    "resources": {"cpu": 1, "gpu": 0},
    "smoke": {"seeds": [0], "grid": {"method": ["oracle"]}},
}


def test_a_dict_and_its_file_resolve_to_the_same_trials(tmp_path):
    path = tmp_path / "api-test.yaml"
    path.write_text(yaml.safe_dump(SWEEP, sort_keys=False))  # axis order matters
    for smoke in (False, True):
        from_file, from_dict = sweep.resolve(path, smoke=smoke), sweep.resolve(SWEEP, smoke=smoke)
        assert from_dict.trials() == from_file.trials()
        assert from_dict.spec_hash() == from_file.spec_hash() and from_dict.experiment == from_file.experiment
        assert (from_dict.resources, from_dict.seed_mode) == (from_file.resources, from_file.seed_mode)
    # 2 methods x 2 learning rates x 2 zip rows x 2 seeds, counted by hand; smoke: 1 x 2 x 2 x 1
    assert len(sweep.resolve(SWEEP).runs()) == 16 and len(sweep.resolve(SWEEP, smoke=True).runs()) == 4
    assert list(tmp_path.iterdir()) == [path]  # resolving writes nothing


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"seedz": [0]}, r"sweep 'api-test' \(a dict\): 'seedz': unknown key; did you mean 'seeds'"),
        ({"base": {"iql.stepz": 5}}, r"'api-test' \(a dict\).*iql.stepz"),
        ({"base": {"method": object()}}, r"not writable as YAML"),  # no YAML value: a file could not hold it
        ({"seeds": [0, 0]}, r"'seeds': repeats a seed"),
        ({"name": None}, r"'name': expected letters"),
    ],
)
def test_a_bad_dict_is_refused_as_a_file_would_be_and_nothing_is_written(tmp_path, change, match):
    bad = {**SWEEP, **change}
    with pytest.raises(SpotError, match=match):
        sweep.run_sweep(bad, storage=tmp_path / "ray", workdir=tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_dict_needs_its_name(tmp_path):
    with pytest.raises(SpotError, match=r"'name': missing"):
        sweep.resolve({k: v for k, v in SWEEP.items() if k != "name"})


def _claims_results(study: Path) -> list[Path]:
    """The CSVs a study's claims file names (read here with PyYAML, not spot's reader)."""
    names = yaml.safe_load((study / "claims.yaml").read_text())["results"]
    files: list[Path] = []
    for name in names:
        p = (study / name).resolve()
        files.extend(sorted(p.glob("*.csv")) if p.is_dir() else [p])
    return files


def test_load_runs_of_a_study_folder_has_every_run_and_its_status():
    frame = spot.results.load_runs(WALKER)
    rows = [r for f in _claims_results(WALKER) for r in csv.DictReader(f.open(newline=""))]
    assert len(rows) > 100  # three folders of results
    assert len(frame) == len(rows)
    finished = sum(r["status"] == "FINISHED" for r in rows)
    assert (frame["status"] == "FINISHED").sum() == finished and finished < len(rows)  # KILLED/FAILED kept
    only = spot.results.load_runs(WALKER, experiments=["lab_walker"])
    assert len(only) == sum(r["experiment"] == "lab_walker" for r in rows) > 0


def test_table_and_report_from_the_frame_are_the_clis(capsys):
    frame = spot.results.load_runs(TABLE1_CSV)
    assert cli.main(["tables", "--table", "1", "--results", str(TABLE1_CSV)]) in (0, None)
    printed = capsys.readouterr().out
    assert spot.results.table(frame, 1, fmt="md") == printed
    committed = (ROOT / "experiments" / "lab-hopper-medium-replay" / "lab_table1.md").read_text()
    assert printed == committed  # what rebuild.sh writes
    wide = spot.results.table(frame, 1)
    assert wide.attrs["table"] == 1 and "mean" in {field for _, field in wide.columns}

    runs = spot.results.load_runs(WALKER)
    assert cli.main(["report", str(WALKER)]) in (0, None)
    printed = capsys.readouterr().out
    assert spot.results.claims_report(runs, WALKER) == printed == (WALKER / "report_walker.md").read_text()


@pytest.mark.slow
def test_run_sweep_from_a_dict_runs_its_trial(tmp_path, spot_dirs, monkeypatch):
    """One real tiny trial (oracle, tiny budget) through Ray, the loopback MLflow server and the pipeline."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    spec = {
        "name": "api-tiny",
        "base": {
            "budget": "tiny",
            "method": "oracle",
            "data": {"name": "hopper-medium-replay", "size": "tiny"},
            "iql.steps": 20,
            "eval": {"every": 10, "episodes": 1},
        },
        "seeds": [0],
        "resources": {"cpu": 1, "gpu": 0},
    }
    rows = sweep.run_sweep(spec, storage=tmp_path / "ray", workdir=tmp_path)
    assert [r.status for r in rows] == ["FINISHED"]
    written = tmp_path / "ray" / "api-tiny.sweep.yaml"
    assert yaml.safe_load(written.read_text()) == spec  # the launch's file: what --resume names
    uri = f"sqlite:///{tmp_path / 'spot_runs' / 'mlflow.db'}"
    runs = spot.results.load_runs(tracking_uri=uri, experiments=["api-tiny"])
    assert list(runs["status"]) == ["FINISHED"] and runs["method"].tolist() == ["oracle"]


def test_study_notebook_runs_under_papermill(tmp_path):
    """analysis/study.py -> .ipynb (jupytext) -> executed (papermill), on the committed walker study."""
    jupytext = pytest.importorskip("jupytext")
    papermill = pytest.importorskip("papermill")
    notebook = jupytext.read(ROOT / "analysis" / "study.py")
    src, dst = tmp_path / "study.ipynb", tmp_path / "study-run.ipynb"
    jupytext.write(notebook, src)
    params = {"study": str(WALKER), "table_results": str(TABLE1_CSV)}
    papermill.execute_notebook(
        str(src), str(dst), parameters=params, cwd=str(tmp_path), progress_bar=False, kernel_name="python3"
    )
    cells = json.loads(dst.read_text())["cells"]
    outputs = [o for c in cells for o in c.get("outputs", [])]
    stdout = "".join("".join(o.get("text", "")) for o in outputs if o.get("name") == "stdout")
    rows = [r for f in _claims_results(WALKER) for r in csv.DictReader(f.open(newline=""))]
    finished = sum(r["status"] == "FINISHED" for r in rows)
    assert f"{len(rows)} runs from " in stdout and f", {finished} finished" in stdout
    markdown = ["".join(o["data"]["text/markdown"]) for o in outputs if "text/markdown" in o.get("data", {})]
    assert (WALKER / "report_walker.md").read_text().strip() in [m.strip() for m in markdown]  # as spot report
    assert any(m.startswith("**Table 1:") for m in markdown)
    assert "method=oracle seeds [0]" in stdout and "method=pt seeds [0]" in stdout  # the dict's trials


def test_table1_neither_bolds_nor_gives_p_for_a_single_run():
    """Issue 42: Table 1 bolded SPOT and printed P(SPOT > method) with one run in a cell."""
    frame = spot.results.load_runs(TABLE1_CSV)
    done = frame[frame["status"] == "FINISHED"]
    best_spot = done[done["method"] == "spot"].nlargest(1, "metrics.eval/score_final")
    one = pd.concat([frame[frame["method"].isin(["mr", "pt"])], best_spot])  # SPOT: 1 run, MR: 2, PT: 1
    text = spot.results.table(one, 1, fmt="md")
    row = next(line for line in text.splitlines() if line.startswith("| hopper-medium-replay"))
    header = next(line for line in text.splitlines() if line.startswith("| dataset"))

    def split(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    cells = dict(zip(split(header), split(row), strict=True))
    # the 95 % rule by hand: SPOT's one run and MR's mean are both within 5 % of the best
    score, mr = best_spot["metrics.eval/score_final"].item(), done[done["method"] == "mr"]["metrics.eval/score_final"]
    assert min(score, mr.mean()) >= 0.95 * max(score, mr.mean())
    assert cells["MR"].startswith("**") and "(2)" in cells["MR"]
    assert not cells["SPOT"].startswith("**") and "(1)" in cells["SPOT"]
    summary = {ln.split("|")[1].strip(): ln.split("|")[5].strip() for ln in text.splitlines() if ln.startswith("| mr ")}
    summary.update(
        {ln.split("|")[1].strip(): ln.split("|")[5].strip() for ln in text.splitlines() if ln.startswith("| pt ")}
    )
    assert summary == {"mr": "– (n < 2)", "pt": "– (n < 2)"}  # SPOT has one run: no P for any method


@pytest.mark.parametrize("progress", [True, False])
def test_each_policy_evaluation_prints_a_progress_line_unless_quiet(progress, capsys):
    """Issue 42: `spot run` showed nothing during IQL, its longest stage."""
    from types import SimpleNamespace

    from spot import config
    from spot.run import policy_stages

    cfg = config.resolve({"method": "pt", "iql.steps": 3000}, {"seed": 4})
    logged, seen = [], []
    ctx = SimpleNamespace(
        cfg=cfg, progress=progress, on_eval=seen.append, log=lambda metrics, step: logged.append((step, metrics))
    )
    res = {"score_mean": 41.26, "score_std": 2.04, "return_mean": 1.0, "episode_length_mean": 5.0}
    policy_stages.log_evaluation(ctx, res, 2000)
    err = capsys.readouterr().err
    assert err == ("spot: pt seed 4: policy step 2,000/3,000: score 41.3 ± 2.0\n" if progress else "")
    assert logged[0][0] == 2000 and seen == [{"step": 2000, "score": 41.26}]


def test_spot_sweep_quiet_reaches_the_launch_and_its_dataset_builds(tmp_path, monkeypatch):
    """Issue 42: `spot sweep` lacked the --quiet every other command has (no progress bars)."""
    from spot.data import registry
    from spot.sweep import launch

    path = tmp_path / "api-test.yaml"
    path.write_text(yaml.safe_dump(SWEEP, sort_keys=False))
    seen: list[dict] = []
    monkeypatch.setattr(launch, "run_sweep", lambda *a, **kw: seen.append(kw) or [])
    assert cli.main(["sweep", str(path), "--quiet"]) in (0, None)
    assert cli.main(["sweep", str(path)]) in (0, None)
    assert [kw["quiet"] for kw in seen] == [True, False]
    builds: list[bool] = []
    monkeypatch.setattr(registry, "build", lambda name, size, seed, progress=True: builds.append(progress) or path)
    launch.prebuild_datasets(sweep.resolve(SWEEP), progress=False)
    assert builds == [False]  # one dataset: hopper-medium-replay, tiny, seed 0


def test_fig3_from_a_run_renders_transition_0_by_default():
    """Issue 42: `spot figures fig3 --run-id` needed --index."""
    from spot.cli import build_parser

    args = build_parser().parse_args(["figures", "fig3", "--run-id", "0123456789abcdef"])
    assert args.index == [0]
    assert build_parser().parse_args(["figures", "fig3", "--run-id", "x", "--index", "3", "9"]).index == [3, 9]
