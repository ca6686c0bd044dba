"""Paper tables and figures from MLflow runs (spot.results.tables, spot.figures, analysis/ notebooks).

The fixture is a tmp SQLite MLflow store with runs written directly (known scores per seed),
so every expected number below is computed by hand.
"""

from __future__ import annotations

import io
import json
import math
import os
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from spot import SpotError, tracking
from spot.results import load, paper, select, table_format, tables

ROOT = Path(__file__).resolve().parents[1]
_CLOCK = [1_700_000_000_000]


def _params(method: str, seed: int, **over: str) -> dict[str, str]:
    shaped = method == "spot"
    p = {
        "method": method,
        "seed": str(seed),
        "budget": "tiny",
        "iql.steps": "200",
        "reward.kind": "none" if method == "oracle" else ("mr" if method == "mr" else "pt"),
        "shaping.kind": "cosine" if shaped else "none",
        "shaping.weight": "1.0",
        "subgoal.group": "top",
        "subgoal.top_k": "10.0",
        "labels.num_queries": "40",
        "cvae.loss": "mse_cos",
        "tracking.experiment": "whatever",
    }
    p.update(over)
    return p


def _bins(offset: float) -> dict:
    """An extrapolation_error.json payload: 3 bins, in-distribution error 0.1*b, OOD 1 + offset - 0.2*b."""
    return {
        "edges": [0.0, 0.25, 0.5, 0.75],
        "count": [[5, 5, 5], [10, 10, 10]],
        "mean_error": [[0.0, 0.1, 0.2], [1 + offset, 0.8 + offset, 0.6 + offset]],
        "groups": ["in_distribution", "ood"],
    }


def _run(
    client,
    exp_id: str,
    *,
    method: str,
    dataset: str,
    seed: int,
    score: float | None,
    source: str = "recipe",
    status: str = "FINISHED",
    params: dict | None = None,
    times: dict | None = None,
    bins: dict | None = None,
    png: Path | None = None,
) -> str:
    from mlflow.entities import Metric, Param, RunTag

    _CLOCK[0] += 1000
    tags = {
        "method": method,
        "dataset": dataset,
        "dataset_source": source,
        "dataset_size": "tiny",
        "label_source": "script",
        "seed": str(seed),
        "budget": "tiny",
        "git_commit": "fixture",
    }
    run = client.create_run(exp_id, start_time=_CLOCK[0], tags=tags)
    rid = run.info.run_id
    values = {} if score is None else {"eval/score_final": score, "eval/score_best": score + 1}
    values.update(times or {})
    metrics = [Metric(k, float(v), _CLOCK[0], 0) for k, v in values.items()]
    if bins is not None:
        for b in range(3):
            metrics += [
                Metric("diag/extrap_bin_in", bins["mean_error"][0][b], _CLOCK[0], b),
                Metric("diag/extrap_bin_ood", bins["mean_error"][1][b], _CLOCK[0], b),
            ]
        client.log_dict(rid, bins, "extrapolation_error.json")
    if png is not None:
        client.log_artifact(rid, str(png))
    client.log_batch(
        rid,
        metrics=metrics,
        params=[Param(k, v) for k, v in (params or _params(method, seed)).items()],
        tags=[RunTag("failure_reason", "boom")] if status == "FAILED" else [],
    )
    client.set_terminated(rid, status=status, end_time=_CLOCK[0] + 500)
    return rid


def _times(seed: int, reward: bool = True) -> dict[str, float]:
    t = {"time/iql_s": 100.0, "time/eval_s": 20.0, "time/total_s": 150.0 + seed}
    if reward:
        t.update(
            {
                "time/reward_s": 10.0 * (seed + 1),
                "time/relabel_s": 1.0,
                "time/subgoals_s": 2.0,
                "time/cvae_s": 3.0,
                "time/shaping_s": 4.0,
            }
        )
    return t


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """URI of a store with experiments t1 (Table 1/8, Fig. 2), t2, t3, t4, t7 and mixed."""
    from mlflow.tracking import MlflowClient

    root = tmp_path_factory.mktemp("mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    ids = {name: tracking.experiment_id(name, uri) for name in ("t1", "t2", "t3", "t4", "t7", "mixed")}
    # a run as `spot sweep` leaves it: artifacts served as mlflow-artifacts:/, on disk beside the db
    served = client.create_experiment("served", artifact_location="mlflow-artifacts:/7")
    rid = client.create_run(
        served, tags={"method": "pt", "dataset": "hopper-medium-replay", "dataset_source": "recipe", "seed": "0"}
    ).info.run_id
    client.set_terminated(rid)
    on_disk = root / "artifacts" / "7" / rid / "artifacts"
    on_disk.mkdir(parents=True)
    (on_disk / "extrapolation_error.json").write_text(json.dumps(_bins(0.0)))
    e = ids["t1"]
    hmr, wmr = "hopper-medium-replay", "walker2d-medium-replay-v2"
    # a first spot seed-0 run, replaced by the later run of the same cell and seed
    _run(client, e, method="spot", dataset=hmr, seed=0, score=10.0, times=_times(0))
    png = root / "subgoal_projection.png"
    Figure(figsize=(1, 1)).savefig(png)
    for seed, score in enumerate((80.0, 85.0, 90.0)):
        _run(
            client,
            e,
            method="spot",
            dataset=hmr,
            seed=seed,
            score=score,
            times=_times(seed),
            bins=_bins(-0.5 + 0.1 * seed),
            png=png if seed == 0 else None,
        )
    for seed, score in enumerate((50.0, 52.0, 60.0)):
        _run(client, e, method="pt", dataset=hmr, seed=seed, score=score, times=_times(seed), bins=_bins(0.0))
    for seed, score in enumerate((95.0, 97.0)):
        _run(client, e, method="oracle", dataset=hmr, seed=seed, score=score, times=_times(seed, reward=False))
    for seed, score in enumerate((81.0, 83.0)):
        _run(client, e, method="mr", dataset=hmr, seed=seed, score=score, times=_times(seed))
    for seed, score in enumerate((10.0, 20.0)):  # same dataset read from a file: never averaged with recipe
        _run(client, e, method="spot", dataset=hmr, seed=seed, score=score, source="file", times=_times(seed))
    for seed, score in enumerate((70.0, 74.0)):
        _run(client, e, method="spot", dataset=wmr, seed=seed, score=score, times=_times(seed))
    _run(client, e, method="pt", dataset=wmr, seed=0, score=70.0, times=_times(0))
    _run(client, e, method="spot", dataset=hmr, seed=3, score=0.0, status="FAILED")
    _run(client, e, method="spot", dataset=hmr, seed=4, score=None, status="KILLED")

    hme = "hopper-medium-expert"
    for group, scores in (("top", (98.0, 100.0)), ("bottom", (50.0, 60.0))):
        for seed, score in enumerate(scores):
            _run(
                client,
                ids["t2"],
                method="spot",
                dataset=hme,
                seed=seed,
                score=score,
                params=_params("spot", seed, **{"subgoal.group": group}),
            )
    for kind, weight, scores in (
        ("cosine", "0.5", (75.0, 77.0)),
        ("cosine", "1.0", (78.0, 80.0)),
        ("potential", "0.5", (70.0, 72.0)),
    ):
        for seed, score in enumerate(scores):
            _run(
                client,
                ids["t3"],
                method="spot",
                dataset="walker2d-medium-replay",
                seed=seed,
                score=score,
                params=_params("spot", seed, **{"shaping.kind": kind, "shaping.weight": weight}),
            )
    for method, queries, scores in (
        ("pt", "100", (74.0, 76.0)),
        ("spot", "100", (98.0, 102.0)),
        ("spot", "50", (84.0, 86.0)),
    ):
        for seed, score in enumerate(scores):
            _run(
                client,
                ids["t4"],
                method=method,
                dataset=hme,
                seed=seed,
                score=score,
                params=_params(method, seed, **{"labels.num_queries": queries}),
            )
    for loss, scores in (("mse", (40.0, 38.0)), ("mse_cos", (60.0, 59.0))):
        for seed, score in enumerate(scores):
            _run(
                client,
                ids["t7"],
                method="spot",
                dataset="can_mh_low_dim",
                seed=seed,
                score=score,
                params=_params("spot", seed, **{"cvae.loss": loss}),
            )
    for seed, steps in ((0, "200"), (1, "20000")):
        _run(
            client,
            ids["mixed"],
            method="spot",
            dataset=hmr,
            seed=seed,
            score=80.0,
            params=_params("spot", seed, **{"iql.steps": steps}),
        )
    return uri


@pytest.fixture(scope="module")
def t1_runs(store):
    return load.load_runs(store, ["t1"])


def test_paper_dataset_names():
    assert paper.paper_dataset_name("hopper-medium-replay-v2") == "hopper-medium-replay"
    assert paper.paper_dataset_name("can_mh_low_dim") == "can-mh"
    assert paper.paper_dataset_name("lift-ph") == "lift-ph"
    assert paper.paper_dataset_name("my-own-data") == "my-own-data"


def test_load_runs_and_failed(t1_runs):
    assert len(t1_runs) == 18
    failed = select.not_finished(t1_runs)
    assert sorted(failed["status"]) == ["FAILED", "KILLED"]
    assert failed.loc[failed["status"] == "FAILED", "failure_reason"].item() == "boom"
    # the store's runs are tagged git_commit (as before the bookkeeping tags moved under spot.)
    assert {"params.shaping.weight", "metrics.eval/score_final", "tags.spot.git_commit"} <= set(t1_runs.columns)


def test_table1_cells(t1_runs):
    t = tables.build_table(t1_runs, 1)
    row = t.loc[("hopper-medium-replay", "recipe")]
    # spot: seed 0 re-run (10 -> 80) replaced; failed/killed runs not counted
    assert row[("spot", "n")] == 3 and row[("spot", "mean")] == pytest.approx(85.0)
    assert row[("spot", "std")] == pytest.approx(5.0)  # sample std of 80, 85, 90
    assert row[("pt", "mean")] == pytest.approx(54.0)
    assert row[("pt", "std")] == pytest.approx(math.sqrt(28.0))
    assert row[("spot", "paper")] == pytest.approx(85.08) and row[("spot", "paper_std")] == pytest.approx(1.32)
    assert row[("spot", "diff")] == pytest.approx(85.0 - 85.08)
    assert row[("pt", "diff")] == pytest.approx(54.0 - 52.15)
    # best: >= 95% of the best non-oracle mean (85): spot and mr (82); oracle (96) never bold
    assert row[("spot", "best")] and row[("mr", "best")]
    assert not row[("pt", "best")] and not row[("oracle", "best")]
    # the paper's cells we did not run are shown with n = 0
    assert row[("ipl", "n")] == 0 and np.isnan(row[("ipl", "mean")]) and row[("ipl", "paper")] == pytest.approx(74.96)
    # the file-source runs of the same dataset form their own row
    file_row = t.loc[("hopper-medium-replay", "file")]
    assert file_row[("spot", "mean")] == pytest.approx(15.0) and file_row[("spot", "n")] == 2
    assert np.isnan(file_row[("pt", "mean")])
    walker = t.loc[("walker2d-medium-replay", "recipe")]
    assert walker[("pt", "n")] == 1 and np.isnan(walker[("pt", "std")])
    avg = t.loc[("average", "recipe")]
    assert avg[("spot", "mean")] == pytest.approx((85.0 + 72.0) / 2) and avg[("spot", "n")] == 2
    assert avg[("spot", "paper")] == pytest.approx((85.08 + 76.89) / 2)
    assert np.isnan(avg[("oracle", "mean")])  # oracle ran on one dataset only
    notes = " ".join(t.attrs["notes"])
    assert "2 runs not FINISHED (FAILED: 1, KILLED: 1)" in notes
    assert (
        "same config and seed: 1" in notes
        and "runs: 15 from experiment(s) t1" in notes
        and "sample std (ddof=1)" in notes
        and "dataset source file" in notes
    )


def test_table1_population_std(t1_runs):
    t = tables.build_table(t1_runs, 1, ddof=0)
    assert t.loc[("hopper-medium-replay", "recipe"), ("spot", "std")] == pytest.approx(math.sqrt(50.0 / 3))
    assert "population std (ddof=0)" in " ".join(t.attrs["notes"])


def test_formats_parse(t1_runs):
    t = tables.build_table(t1_runs, 1)
    csv = pd.read_csv(io.StringIO(table_format.format_table(t, "csv")))
    line = csv[(csv["dataset"] == "hopper-medium-replay") & (csv["source"] == "recipe")].iloc[0]
    assert line["spot/mean"] == pytest.approx(85.0) and line["spot/paper"] == pytest.approx(85.08)
    md = table_format.format_table(t, "md")
    assert "| dataset | source | Oracle | MR | PT | IPL | HPL | SPOT |" in md
    assert "**85.00 ± 5.00** (3) CI 80.00–90.00 [85.08 ± 1.32, Δ -0.08]" in md  # 80, 85, 90: CI of the mean
    latex = table_format.format_table(t, "latex")
    assert "\\begin{tabular}" in latex and "\\end{tabular}" in latex
    assert "\\textbf{85.00 $\\pm$ 5.00} (3)" in latex
    with pytest.raises(SpotError, match="unknown format"):
        table_format.format_table(t, "html")


def test_table8_sums(t1_runs):
    t = tables.build_table(t1_runs, 8)
    row = t.loc[("spot", "hopper-medium-replay", "recipe")]
    # SPOT: reward model = 10 (seed+1) + 1, + 2 + 3 + 4 (subgoals, CVAE, shaping) over seeds 0..2 = 20, 30, 40
    assert row[("reward_model_s", "mean")] == pytest.approx(30.0)
    assert row[("reward_model_s", "std")] == pytest.approx(10.0)
    assert row[("offline_rl_s", "mean")] == pytest.approx(120.0)
    assert row[("total_s", "mean")] == pytest.approx(150.0)
    assert row[("wall_s", "mean")] == pytest.approx(151.0)
    # without shaping (PT, MR) the subgoal/CVAE/shaping stages are diagnostics, not reward model:
    # 10 (seed+1) + 1 over seeds 0..2 = 11, 21, 31
    assert t.loc[("pt", "hopper-medium-replay", "recipe"), ("reward_model_s", "mean")] == pytest.approx(21.0)
    oracle = t.loc[("oracle", "hopper-medium-replay", "recipe")]
    assert oracle[("reward_model_s", "mean")] == 0.0 and oracle[("total_s", "mean")] == pytest.approx(120.0)
    walker = t.loc[("spot", "walker2d-medium-replay", "recipe")]
    assert walker[("reward_model_s", "paper")] == 7634 and walker[("offline_rl_s", "paper")] == 4077
    assert walker[("total_s", "paper")] == 11711
    assert walker[("total_s", "diff")] == pytest.approx(walker[("total_s", "mean")] - 11711)
    assert not t.xs("best", axis=1, level="field").to_numpy().any()


def test_tables_2_3_4_7(store):
    t2 = tables.build_table(load.load_runs(store, ["t2"]), 2)
    top = t2.loc[("top-10", "recipe")]
    assert top[("hopper-medium-expert", "mean")] == pytest.approx(99.0)
    assert top[("hopper-medium-expert", "paper")] == pytest.approx(99.37)
    assert top[("hopper-medium-expert", "best")]  # Table 2 marks the best per column
    assert not t2.loc[("bottom-10", "recipe"), ("hopper-medium-expert", "best")]
    assert t2.loc[("top-10-20", "recipe"), ("hopper-medium-expert", "n")] == 0  # paper only

    t3 = tables.build_table(load.load_runs(store, ["t3"]), 3)
    cos = t3.loc[("walker2d-medium-replay", "cosine", "recipe")]
    assert cos[(1.0, "mean")] == pytest.approx(79.0) and cos[(1.0, "paper")] == pytest.approx(77.51)
    assert cos[(0.5, "mean")] == pytest.approx(76.0) and cos[(0.5, "paper")] == pytest.approx(75.30)
    assert cos[(1.0, "best")] and cos[(0.5, "best")]  # 76 >= 0.95 * 79
    assert t3.loc[("walker2d-medium-replay", "potential", "recipe"), (0.5, "paper")] == pytest.approx(74.45)
    assert ("walker2d-medium-replay", "?", "recipe") in t3.index  # paper values of unknown shaping kind

    t4 = tables.build_table(load.load_runs(store, ["t4"]), 4)
    assert t4.loc[("hopper-medium-expert", "spot", 50, "recipe"), ("score", "mean")] == pytest.approx(85.0)
    assert t4.loc[("hopper-medium-expert", "spot", 50, "recipe"), ("score", "paper")] == pytest.approx(85.99)
    assert t4.loc[("hopper-medium-expert", "pt", 30, "recipe"), ("score", "n")] == 0

    t7 = tables.build_table(load.load_runs(store, ["t7"]), 7)
    can = t7.loc[("can-mh", "recipe")]
    assert can[("mse", "mean")] == pytest.approx(39.0) and can[("mse", "paper")] == pytest.approx(39.22)
    assert can[("mse_cos", "paper")] == pytest.approx(59.56) and can[("mse_cos", "best")]
    assert not can[("mse", "best")]


def test_mixed_cells_refused(store):
    runs = load.load_runs(store, ["mixed"])
    with pytest.raises(SpotError, match="iql.steps in {200, 20000}"):
        tables.build_table(runs, 1)
    t = tables.build_table(runs, 1, allow_mixed=True)
    assert t.loc[("hopper-medium-replay", "recipe"), ("spot", "n")] == 2
    assert any("mixed params" in n for n in t.attrs["notes"])


def test_default_experiments(store):
    assert tables.default_experiments(1, store) is None  # no sweep experiment: all experiments
    tracking.experiment_id("table4_queries-smoke", store)
    assert tables.default_experiments(4, store) == ["table4_queries-smoke"]
    tracking.experiment_id("other_table4", store)  # another experiment's runs are never a table's default
    assert tables.default_experiments(4, store) == ["table4_queries-smoke"]
    tracking.experiment_id("table4_queries", store)  # the paper-budget sweep's before its smoke launch
    assert tables.default_experiments(4, store) == ["table4_queries"]


def test_errors(store, t1_runs):
    with pytest.raises(SpotError, match="no MLflow experiment named 'nope'"):
        load.load_runs(store, ["nope"])
    with pytest.raises(SpotError, match="unknown table 5"):
        tables.build_table(t1_runs, 5)
    with pytest.raises(SpotError, match="no run logged the metric"):
        tables.build_table(t1_runs, 1, metric="eval/nothing")


def test_fig2(store, t1_runs, tmp_path):
    from spot import figures

    with pytest.raises(SpotError, match="source"):
        figures.extrapolation_bins(t1_runs, store, dataset="hopper-medium-replay")
    bins = figures.extrapolation_bins(t1_runs, store, dataset="hopper-medium-replay", source="recipe")
    assert set(bins["origin"]) == {"artifact"} and bins["run_id"].nunique() == 6
    s = figures.summarize_extrapolation(bins)
    spot_ood0 = s[(s["method"] == "spot") & (s["group"] == "ood") & (s["bin"] == 0)].iloc[0]
    assert spot_ood0["mean_error"] == pytest.approx(np.mean([0.5, 0.6, 0.7]))
    assert spot_ood0["std"] == pytest.approx(0.1) and spot_ood0["n_runs"] == 3
    assert spot_ood0["centre"] == pytest.approx(0.125)
    png = figures.plot_fig2(bins, tmp_path / "fig2.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fig2_from_metrics(store, t1_runs, tmp_path):
    """Runs without the JSON artifact: bins come from the diag/extrap_bin_* metric histories."""
    from mlflow.tracking import MlflowClient

    from spot import figures

    pt_run = t1_runs.loc[(t1_runs["method"] == "pt") & (t1_runs["dataset"] == "hopper-medium-replay"), "run_id"].iloc[0]
    bins = figures._bins_from_metrics(MlflowClient(store), pt_run)
    assert [(b["group"], b["bin"], b["mean_error"]) for b in bins][:3] == [
        ("in_distribution", 0, 0.0),
        ("in_distribution", 1, 0.1),
        ("in_distribution", 2, 0.2),
    ]
    frame = pd.DataFrame([{**b, "run_id": "x", "method": "pt", "dataset": "d", "source": "recipe"} for b in bins])
    assert figures.plot_fig2(frame, tmp_path / "fig2m.png").exists()


def test_cli_tables(store, capsys, tmp_path):
    from spot import cli

    assert cli.main(["tables", "--table", "1", "--experiment", "t1", "--tracking-uri", store]) == 0
    assert "| dataset | source |" in capsys.readouterr().out
    out = tmp_path / "t7.tex"
    assert (
        cli.main(
            [
                "tables",
                "--table",
                "7",
                "--experiment",
                "t7",
                "--tracking-uri",
                store,
                "--format",
                "latex",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "\\begin{tabular}" in out.read_text()
    assert cli.main(["tables", "--table", "1", "--experiment", "mixed", "--tracking-uri", store]) == 2
    assert "--allow-mixed" in capsys.readouterr().err
    png = tmp_path / "f2.png"
    assert (
        cli.main(
            ["figures", "fig2", "--experiment", "t1", "--tracking-uri", store, "--source", "recipe", "--out", str(png)]
        )
        == 2
    )  # two datasets: pick one
    assert "--dataset" in capsys.readouterr().err
    assert (
        cli.main(
            [
                "figures",
                "fig2",
                "--experiment",
                "t1",
                "--tracking-uri",
                store,
                "--source",
                "recipe",
                "--dataset",
                "hopper-medium-replay",
                "--out",
                str(png),
            ]
        )
        == 0
    )
    assert png.exists()
    runs = load.load_runs(store, ["t1"])
    with_png = runs.loc[(runs["method"] == "spot") & (runs["metrics.eval/score_final"] == 80.0), "run_id"].item()
    fig4 = tmp_path / "f4.png"
    assert cli.main(["figures", "fig4", "--tracking-uri", store, "--run-id", with_png, "--out", str(fig4)]) == 0
    assert fig4.read_bytes()[:4] == b"\x89PNG"


def test_notebooks_execute(store, tmp_path, monkeypatch):
    """The analysis/ notebooks (jupytext percent format) run top to bottom as scripts on the fixture."""
    monkeypatch.setenv("SPOT_TRACKING_URI", store)
    monkeypatch.setenv("SPOT_TABLE_EXPERIMENTS", "1=t1;2=t2;3=t3;4=t4;7=t7;8=t1")
    monkeypatch.setenv("SPOT_FIG2_EXPERIMENTS", "t1")
    monkeypatch.setenv("SPOT_FIG2_DATASET", "hopper-medium-replay")
    monkeypatch.setenv("SPOT_FIG2_SOURCE", "recipe")
    monkeypatch.setenv("SPOT_ANALYSIS_OUT", str(tmp_path))
    monkeypatch.delenv("SPOT_CVAE", raising=False)
    runpy.run_path(str(ROOT / "analysis" / "tables.py"), run_name="__main__")
    runpy.run_path(str(ROOT / "analysis" / "figures.py"), run_name="__main__")
    for n in tables.TABLES:
        for ext in ("md", "tex", "csv"):
            assert (tmp_path / f"table{n}.{ext}").stat().st_size > 0
    assert (tmp_path / "fig2.png").exists() and (tmp_path / "fig4.png").exists()


def test_fig3_render(tmp_path):
    """Fig. 3 rendering, in a fresh process that picks MuJoCo's headless backend (runtime.configure)."""
    code = (
        "import numpy as np, gymnasium as gym\n"
        "from spot import figures, runtime\n"
        "runtime.configure()\n"
        "env = gym.make('Hopper-v5'); o, _ = env.reset(seed=0)\n"
        "o2 = o.copy(); o2[1] = -0.5\n"
        f"figures.render_state_and_subgoal('hopper-medium-expert', o, o2, r'{tmp_path / 'fig3.png'}', "
        "width=96, height=96)\n"
        "img = figures.render_observations('Hopper-v5', np.stack([o, o2]), width=64, height=64)\n"
        "assert img.shape == (2, 64, 64, 3) and not np.array_equal(img[0], img[1])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "fig3.png").read_bytes()[:4] == b"\x89PNG"


def test_fig2_reads_served_artifacts(store):
    """Sweep runs have mlflow-artifacts:/ URIs; with no server running they are read from disk."""
    from spot import figures

    bins = figures.extrapolation_bins(load.load_runs(store, ["served"]), store)
    assert set(bins["origin"]) == {"artifact"} and len(bins) == 6
