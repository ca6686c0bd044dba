"""Take the UI screenshots of this folder from a store that ``lambda.yaml`` was swept into.

    cd /work/tmp-shots   # any folder outside the repo
    SPOT_DATA_DIR=/work/cache/data spot sweep <repo>/experiments/ui-screenshots/lambda.yaml --smoke \\
        --tracking-uri sqlite:////work/tmp-shots/spot_runs/mlflow.db --storage /work/tmp-shots/ray
    python <repo>/experiments/ui-screenshots/take.py sqlite:////work/tmp-shots/spot_runs/mlflow.db OUT

``spot ui`` serves the store on 127.0.0.1 and headless Chromium (the same flags and helpers as
tests/test_ui_browser.py) loads the link the sweep printed, the λ=0.5 trial's run page and
MLflow's metric page with both trials' ``eval/score``. Each page's DOM is checked for what its
caption in NOTES.md claims, and a PNG over 300 KB is downscaled. The newest sweep launch in the
store's ``lambda-smoke`` experiment is used.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from urllib.parse import quote, urlencode

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_ui_browser import BROWSER, CHROMIUM, dom_of, start_ui, workspace_labels  # noqa: E402

MAX_BYTES = 300_000
EXPERIMENT = "lambda-smoke"


def newest_sweep(uri: str) -> tuple[str, str, dict[str, str]]:
    """The experiment id, the newest launch's sweep id and ``{run name: run id}`` of its trials."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(EXPERIMENT)
    parents = client.search_runs(
        [exp.experiment_id], "tags.`spot.role` = 'sweep'", order_by=["attributes.start_time DESC"], max_results=1
    )
    sweep_id = parents[0].data.tags["spot.sweep_id"]
    trials = client.search_runs([exp.experiment_id], f"tags.`mlflow.parentRunId` = '{parents[0].info.run_id}'")
    return exp.experiment_id, sweep_id, {r.info.run_name: r.info.run_id for r in trials}


def metric_url(experiment_id: str, run_ids: list[str], metric: str, base: str) -> str:
    """MLflow's metric page (its route ``/metric/*``, the query its own links carry): ``metric`` of
    ``run_ids`` against the step, one curve a run, points shown, in the model-training workspace."""
    query = {
        "runs": json.dumps(run_ids),
        "metric": json.dumps(metric),
        "experiments": json.dumps([experiment_id]),
        "plot_metric_keys": json.dumps([metric]),
        "plot_layout": "{}",
        "x_axis": "step",
        "y_axis_scale": "linear",
        "line_smoothness": "1",
        "show_point": "true",
        "deselected_curves": "[]",
        "last_linear_y_axis_range": "[]",
        "workflowType": "machine_learning",
    }
    return f"{base.rstrip('/')}/#/metric/{quote(metric, safe='')}?{urlencode(query, quote_via=quote)}"


def shoot(url: str, png: Path, size: tuple[int, int]) -> str:
    """The page's DOM after its scripts ran, and its screenshot (``size``: width, height) at ``png``."""
    flags = [f for f in BROWSER if not f.startswith("--window-size")] + ["--window-size={},{}".format(*size)]
    dom = subprocess.run([CHROMIUM, *flags, "--dump-dom", url], capture_output=True, text=True, timeout=180).stdout
    subprocess.run([CHROMIUM, *flags, f"--screenshot={png}", url], capture_output=True, timeout=180, check=True)
    return dom


def shrink(png: Path) -> None:
    """A ``png`` over MAX_BYTES re-saved as an optimised palette PNG, downscaled until it is under."""
    from PIL import Image

    if png.stat().st_size < MAX_BYTES:
        return
    with Image.open(png) as im:
        im = im.convert("RGB")
    scale = 1.0
    while True:
        size = (round(im.width * scale), round(im.height * scale))
        im.resize(size, Image.LANCZOS).quantize(256).save(png, optimize=True)
        if png.stat().st_size < MAX_BYTES or scale < 0.5:
            return
        scale *= 0.85


def check(doms: dict[str, str], sweep_id: str) -> None:
    """What the captions claim, read from the pages' DOM."""
    for name in ("spot λ=0.5 s0", "spot λ=1.0 s0"):
        assert name in doms["sweep"], f"sweep link: no row {name}"
    for col in ("tags.`method`", "tags.`axis.shaping.weight`", "metrics.`eval/score_final`"):
        assert f'col-id="{col}"' in doms["sweep"], f"sweep link: no column {col}"
    run = doms["run"]
    for tag in ("spot.sweep_id", "spot.trial_key", "spot.stage.reward.source", "axis.shaping.weight", sweep_id):
        assert tag in run, f"run page: no {tag}"
    for old in (">sweep_id<", ">trial_key<", ">attempt<"):
        assert old not in run, f"run page: an old bare tag name {old}"
    labels = workspace_labels(run)
    assert set(labels) == {"GenAI", "Model training"} and labels["GenAI"] != labels["Model training"], labels
    chart = doms["metrics"]
    assert "eval/score" in chart and "spot λ=0.5 s0" in chart and "spot λ=1.0 s0" in chart, "metric page"
    assert workspace_labels(chart) == labels, "metric page: not in the Model training workspace"


def main(uri: str, out: Path) -> None:
    from spot import tracking
    from spot.sweep.mlflow_server import free_port

    exp_id, sweep_id, trials = newest_sweep(uri)
    run_id = trials["spot λ=0.5 s0"]
    ids = [trials[name] for name in sorted(trials)]
    proc, base = start_ui(uri, free_port())
    try:
        out.mkdir(parents=True, exist_ok=True)
        run = tracking.run_url(exp_id, run_id, base)
        doms = {
            "sweep": shoot(tracking.sweep_url(exp_id, sweep_id, base), out / "sweep-link.png", (2200, 900)),
            "run": shoot(run, out / "run-page.png", (1400, 1250)),
            "metrics": shoot(metric_url(exp_id, ids, "eval/score", base), out / "eval-score.png", (1800, 900)),
            "run-genai": dom_of(run.replace("=machine_learning", "=genai")),
        }
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    check(doms, sweep_id)
    for png in ("sweep-link.png", "run-page.png", "eval-score.png"):
        shrink(out / png)
        print(png, (out / png).stat().st_size, "bytes")
    print("sweep", sweep_id, "run", run_id, "experiment", exp_id)


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]).resolve())
