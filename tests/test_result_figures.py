"""Pictures of results (issue 42, item 3) from the committed results of experiments/lab-hopper-full-replay:
``spot figures curves|claims|profile``, ``spot report --html`` (loaded in headless Chromium where it
is installed) and the curves figure a finished sweep logs to its parent run.

Expected numbers are derived here from the CSV text with pandas, independently of
:mod:`spot.results.load` and :mod:`spot.results.figures_curves`."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "experiments" / "lab-hopper-full-replay"
RESULTS = STUDY / "results"
MAGIC = {"png": b"\x89PNG", "pdf": b"%PDF", "svg": b"<?xml"}


def _csv_points() -> pd.DataFrame:
    """Every (finished run, step, value) of the committed CSVs, parsed here from the text."""
    df = pd.concat([pd.read_csv(f, dtype=str) for f in sorted(RESULTS.glob("*.csv"))], ignore_index=True)
    df = df[(df["status"] == "FINISHED") & df["curve.eval/score"].notna()]
    rows = [
        (run_id, method, int(item.split(":")[0]), float(item.split(":")[1]))
        for run_id, method, curve in zip(df["run_id"], df["method"], df["curve.eval/score"], strict=True)
        for item in curve.split(";")
    ]
    return pd.DataFrame(rows, columns=["run_id", "method", "step", "value"])


@pytest.fixture(scope="module")
def built():
    """The study's claims file, runs and report rows (built once: the report takes a while)."""
    from spot.results import claims, load, report

    claims_file = claims.load(claims.study_file(STUDY))
    runs = load.read(list(claims_file.results))
    return claims_file, runs, report.build(runs, claims_file)


def test_curves_plot_the_mean_over_seeds_at_each_step(tmp_path):
    from spot.results import figures_curves as fc
    from spot.results import load

    runs = load.read(RESULTS)
    points = _csv_points()
    assert not runs["run_id"].duplicated().any()  # so the finished runs are the FINISHED rows
    summary = fc.summarize_curves(fc.curve_points(runs))
    fig = fc.draw_curves(summary)
    (ax,) = fig.axes
    lines = {ln.get_label().split(" (n=")[0]: ln for ln in ax.lines}
    assert set(lines) == {"MR", "Oracle", "PT", "SPOT"}
    for method, label, step in (("mr", "MR", 50000), ("spot", "SPOT", 100000), ("pt", "PT", 20000)):
        x, y = lines[label].get_xdata(), lines[label].get_ydata()
        want = points[(points["method"] == method) & (points["step"] == step)]["value"]
        assert len(want) >= 3
        assert y[list(x).index(step)] == pytest.approx(want.mean(), abs=1e-9)
        row = summary[(summary["group"] == label) & (summary["step"] == step)].iloc[0]
        assert row["n"] == len(want) and row["low"] <= want.mean() <= row["high"]
        assert row["low"] >= want.min() and row["high"] <= want.max()  # a CI of the mean stays within the runs


def test_curves_and_profile_commands_write_each_format(tmp_path, capsys):
    from spot import cli

    for ext, head in MAGIC.items():
        out = tmp_path / f"curves.{ext}"
        argv = ["figures", "curves", "--results", str(RESULTS), "--by", "shaping.weight", "--out", str(out)]
        assert cli.main(argv) == 0
        assert out.stat().st_size > 1000 and out.read_bytes().startswith(head), ext
    out = tmp_path / "profile.png"
    assert cli.main(["figures", "profile", str(STUDY), "--experiment", "lab_hopper_fr_pf", "--out", str(out)]) == 0
    assert out.read_bytes().startswith(MAGIC["png"])
    bad = tmp_path / "bad.png"
    assert cli.main(["figures", "curves", "--results", str(RESULTS), "--by", "no.such", "--out", str(bad)]) == 2
    assert "--by no.such" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["curves.pdf", "curves.png", "curves.svg", "profile.png"]


def test_profile_is_the_fraction_of_runs_above_tau():
    from spot.results import figures_curves as fc
    from spot.results import load

    runs = load.read(RESULTS)
    df = pd.concat([pd.read_csv(f) for f in sorted(RESULTS.glob("*.csv"))], ignore_index=True)
    df = df[df["status"] == "FINISHED"]
    taus = np.array([0.0, 10.0, 30.0, 60.0])
    prof = fc.profile(fc.final_scores(runs), taus, n_resamples=500)
    fig = fc.draw_profile(prof)
    lines = {ln.get_label().split(" (")[0]: ln for ln in fig.axes[0].lines}
    for method, label in (("mr", "MR"), ("spot", "SPOT"), ("oracle", "Oracle")):
        scores = df[df["method"] == method]["metrics.eval/score_final"].to_numpy()
        want = [(scores > t).mean() for t in taus]
        np.testing.assert_allclose(lines[label].get_ydata(), want)
        band = prof[prof["group"] == label]
        assert len(scores) >= 3 and (band["runs"] == len(scores)).all()
        assert (band["low"] <= band["fraction"] + 1e-12).all() and (band["fraction"] <= band["high"] + 1e-12).all()


def test_claims_plot_draws_the_report_rows(built, tmp_path):
    from spot.results import figures_report

    _, _, report = built
    fig = figures_report.draw_claims(report.rows)
    with_effect = [r for r in report.rows if r.effect is not None]
    stats_order = list(dict.fromkeys(r.stat for r in with_effect))
    assert figures_report.plotted_effects(fig) == [
        [r.effect.value for r in with_effect if r.stat == s] for s in stats_order
    ]
    assert len(with_effect) >= 10 and stats_order[0] == "last"


def test_claims_command(tmp_path, capsys):
    from spot import cli

    out = tmp_path / "claims.svg"
    assert cli.main(["figures", "claims", str(STUDY), "--out", str(out)]) == 0
    assert out.read_bytes().startswith(MAGIC["svg"]) and out.stat().st_size > 5000
    assert "1P last spot vs mr" in capsys.readouterr().out


@pytest.fixture(scope="module")
def html_report(tmp_path_factory):
    """``spot report STUDY --out report.md --html report.html``: the page's path (built once)."""
    from spot import cli

    folder = tmp_path_factory.mktemp("html")
    md, page = folder / "report.md", folder / "report.html"
    assert cli.main(["report", str(STUDY), "--out", str(md), "--html", str(page)]) == 0
    assert md.read_text() == (STUDY / "report_hopper_fr_pf.md").read_text()  # --html leaves the report as it was
    return page


def test_html_report_is_one_self_contained_page(html_report):
    text = html_report.read_text()
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(images) == 3  # claims, curves, profile
    assert all(base64.b64decode(b).startswith(MAGIC["png"]) for b in images)
    assert not re.search(r"(src|href)=\"(?!data:)", text) and "<script" not in text and "<link" not in text
    assert text.count("<table>") >= 4 and "<th>effect [95% CI]</th>" in text
    assert "<td>spot vs mr</td>" in text


def test_html_text_is_escaped():
    from spot.results import figures_report

    page = figures_report.markdown_html("### a `b`\n\n| a | b |\n|---|---|\n| 1 | <x> |\n- <i>\n")
    assert page == (
        "<h3>a <code>b</code></h3>\n<table><thead><tr><th>a</th><th>b</th></tr></thead>"
        "<tbody><tr><td>1</td><td>&lt;x&gt;</td></tr></tbody></table>\n<ul><li>&lt;i&gt;</li></ul>"
    )


def test_html_report_in_a_real_browser(html_report, tmp_path):
    from matplotlib.image import imread

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if not browser:
        pytest.skip("chromium not installed: apt-get install chromium")
    shot = tmp_path / "shot.png"
    cmd = [browser, "--headless", "--disable-gpu", "--no-sandbox", f"--user-data-dir={tmp_path / 'profile'}"]
    cmd += [f"--screenshot={shot}", "--window-size=1200,2000", html_report.as_uri()]
    env = {"HOME": str(tmp_path), "PATH": "/usr/bin:/bin"}
    subprocess.run(cmd, check=True, capture_output=True, timeout=180, env=env)
    pixels = imread(str(shot))[..., :3]
    assert pixels.shape[:2] == (2000, 1200)
    assert pixels.std() > 0.05  # not a blank page: the figures are drawn (a white page has 0)
    assert (pixels.max(axis=2) - pixels.min(axis=2)).max() > 0.3  # and in colour: the plotted lines


def test_finished_sweep_logs_its_curves_to_the_parent_run(tmp_path):
    from mlflow import MlflowClient
    from mlflow.entities import Metric

    from spot.sweep.parent import CURVES_ARTIFACT, log_curves_figure
    from spot.sweep.trial import SweepContext

    uri = f"sqlite:///{tmp_path / 'm.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("sw", artifact_location=(tmp_path / "art").as_uri())
    parent = client.create_run(exp, tags={"sweep_id": "sw-1", "spot.role": "sweep"}).info.run_id
    for lam in ("0.5", "1.0"):
        for seed in range(3):
            tags = {"sweep_id": "sw-1", "method": "spot", "dataset": "hopper-medium-replay", "seed": str(seed)}
            run = client.create_run(exp, tags=tags).info.run_id
            client.log_batch(
                run,
                metrics=[Metric("eval/score", float(s) * float(lam) + seed, 0, s) for s in (0, 10, 20)],
                params=[],
            )
            client.log_param(run, "shaping.weight", lam)
            client.set_terminated(run, "FINISHED")
    ctx = SweepContext("sw-1", "sw", "sw", exp, parent, uri, ("shaping.weight",))
    assert log_curves_figure(client, ctx) == CURVES_ARTIFACT
    (art,) = client.list_artifacts(parent)
    assert art.path == CURVES_ARTIFACT and art.file_size > 1000
    ctx = SweepContext("sw-2", "sw", "sw", exp, parent, "sqlite:////nonexistent/dir/m.db", ("shaping.weight",))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert log_curves_figure(client, ctx) is None  # a warning, never a failed sweep
    assert any("no curves figure" in str(w.message) for w in caught)
