"""The analysis/ notebooks as a researcher runs them: jupytext -> .ipynb -> papermill, on a small store.

The store has a ``table1-smoke`` experiment only (the sweep's smoke launch), so the notebooks'
default choice of runs is the CLI's fallback (``table1`` absent -> ``table1-smoke``), and a
``scratch`` experiment whose runs would change the numbers if the notebooks read every experiment.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from matplotlib.figure import Figure

from spot import tracking

jupytext = pytest.importorskip("jupytext")
papermill = pytest.importorskip("papermill")
from test_tables import _bins, _params, _run, _times  # noqa: E402  (the fake-run helpers of the tables tests)

ROOT = Path(__file__).resolve().parents[1]
HMR = "hopper-medium-replay"


@pytest.fixture(scope="module")
def smoke_store(tmp_path_factory):
    from mlflow.tracking import MlflowClient

    root = tmp_path_factory.mktemp("nb-mlflow")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    smoke = tracking.experiment_id("table1-smoke", uri)
    scratch = tracking.experiment_id("scratch", uri)
    png = root / "subgoal_projection.png"
    Figure(figsize=(1, 1)).savefig(png)
    for seed, score in enumerate((80.0, 85.0, 90.0)):
        _run(
            client,
            smoke,
            method="spot",
            dataset=HMR,
            seed=seed,
            score=score,
            times=_times(seed),
            bins=_bins(-0.5),
            png=png if seed == 1 else None,
        )
    for seed, score in enumerate((50.0, 52.0, 60.0)):
        _run(client, smoke, method="pt", dataset=HMR, seed=seed, score=score, times=_times(seed), bins=_bins(0.0))
    _run(client, smoke, method="spot", dataset=HMR, seed=3, score=None, status="FAILED")
    # later runs of the same cells in another experiment: a re-run replaces, so reading them would show
    for seed in range(3):
        _run(
            client,
            scratch,
            method="spot",
            dataset=HMR,
            seed=seed,
            score=0.0,
            times=_times(seed),
            params=_params("spot", seed, **{"iql.steps": "5"}),
        )
    return uri


def _execute(name: str, tmp_path: Path, **parameters) -> dict:
    """analysis/<name>.py -> .ipynb (jupytext) -> executed .ipynb (papermill); returns the notebook."""
    notebook = jupytext.read(ROOT / "analysis" / f"{name}.py")
    assert notebook.metadata["kernelspec"]["name"] == "python3"
    tagged = [c for c in notebook.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and all(f"\n{k}: " in "\n" + tagged[0].source for k in parameters)
    src, dst = tmp_path / f"{name}.ipynb", tmp_path / f"{name}-run.ipynb"
    jupytext.write(notebook, src)
    papermill.execute_notebook(
        str(src), str(dst), parameters=parameters, cwd=str(tmp_path), progress_bar=False, kernel_name="python3"
    )
    return json.loads(dst.read_text())


def _outputs(nb: dict, mime: str) -> list[str]:
    found = []
    for cell in nb["cells"]:
        for out in cell.get("outputs", []):
            data = out.get("data", {}).get(mime)
            if data is not None:
                found.append("".join(data) if isinstance(data, list) else data)
    return found


def _stdout(nb: dict) -> str:
    return "".join(
        "".join(o.get("text", "")) for c in nb["cells"] for o in c.get("outputs", []) if o.get("name") == "stdout"
    )


def test_tables_notebook_papermill(smoke_store, tmp_path):
    out = tmp_path / "out"
    nb = _execute("tables", tmp_path, tracking_uri=smoke_store, out_dir=str(out))
    html = _outputs(nb, "text/html")
    assert any("<table" in h and "dataframe" in h for h in html)  # pandas DataFrames, inline
    (table1,) = [m for m in _outputs(nb, "text/markdown") if m.startswith("**Table 1:") and "|" in m]
    # the fallback: table1 absent -> table1-smoke (not every experiment: scratch's 0.0 would replace seeds)
    assert "from experiment(s) table1-smoke" in table1 and "scratch" not in table1
    assert "85.00 ± 5.00" in table1  # spot: mean/std of 80, 85, 90
    assert len(_outputs(nb, "image/png")) == 1  # ours vs paper
    assert (out / "ours_vs_paper.png").read_bytes()[:4] == b"\x89PNG"
    csv = (out / "table1.csv").read_text()
    assert "table1-smoke" not in csv and csv.splitlines()[0].startswith("dataset,source,")
    for ext in ("md", "tex", "csv"):
        assert (out / f"table1.{ext}").stat().st_size > 0 and (out / f"table8.{ext}").stat().st_size > 0


def test_figures_notebook_papermill(smoke_store, tmp_path):
    out = tmp_path / "out"
    nb = _execute("figures", tmp_path, tracking_uri=smoke_store, out_dir=str(out), cvae="")
    assert "7 runs from table1-smoke" in _stdout(nb)
    assert any("<table" in h for h in _outputs(nb, "text/html"))  # the Fig. 2 numbers
    images = _outputs(nb, "image/png")
    assert len(images) == 2  # Fig. 2 and Fig. 4 inline (Fig. 3 needs a CVAE)
    assert (out / "fig2.png").read_bytes()[:4] == b"\x89PNG" and (out / "fig4.png").exists()
    assert "Fig. 3 not drawn" in _stdout(nb)
