"""The MLflow UI as a researcher sees it, in a real browser (headless Chromium): ``spot ui`` serves a
small store of spot's runs (a two-run λ sweep: a parent and its trials, logged by
``spot.tracking.start_run``), and the link a sweep prints and a run page are loaded, their DOM read
and screenshots taken. Skipped with a reason where Chromium is absent.

Run as a script to keep its screenshots: ``python tests/test_ui_browser.py OUT_DIR``. The pictures in
``experiments/ui-screenshots`` come from a real sweep instead (its ``take.py`` and NOTES.md).
"""

from __future__ import annotations

import os
import re
import selectors
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
BROWSER = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--window-size=1400,900",
    "--virtual-time-budget=15000",
    "--hide-scrollbars",
]
WEIGHTS = (0.5, 1.0)  # the swept λ (shaping.weight), one seed each


def make_store(folder: Path) -> tuple[str, str, str, str]:
    """A λ sweep of two runs logged by spot into ``folder/spot_runs/mlflow.db``; returns the store's
    URI, the experiment id, the sweep id and one trial's run id."""
    from mlflow.tracking import MlflowClient

    from spot import config as config_lib
    from spot import tracking

    uri = f"sqlite:///{folder / 'spot_runs' / 'mlflow.db'}"
    exp_id = tracking.experiment_id("lambda-sweep", uri)
    client = MlflowClient(uri)
    sweep_id = "lambda-20261207-180000-ab12"
    parent = client.create_run(exp_id, run_name=f"sweep {sweep_id}", tags={"spot.sweep_id": sweep_id}).info.run_id
    run_ids = []
    for weight in WEIGHTS:
        overrides = {"method": "spot", "budget": "tiny", "data.name": "hopper-medium-replay", "seed": 0}
        overrides.update({"shaping.weight": weight, "tracking.uri": uri, "tracking.experiment": "lambda-sweep"})
        cfg = config_lib.resolve(overrides)
        tags = {"sweep_id": sweep_id, "sweep_name": "lambda", "trial_key": f"w{weight}-s0"}
        tags.update({"attempt": uuid.uuid4().hex, "axis.shaping.weight": str(weight)})
        card = {"name": "hopper-medium-replay", "source": "built", "size": "tiny"}
        with tracking.start_run(cfg, card, extra_tags=tags, parent_run_id=parent, system_metrics=False) as tr:
            for step in range(0, 101, 25):
                tr.log_metrics({"eval/score": 20 + weight * step / 4}, step=step)
            tr.log_metrics({"eval/score_final": 20 + weight * 25, "eval/score_best": 20 + weight * 25})
            run_ids.append(tr.run_id)
    client.set_terminated(parent, "FINISHED")
    tracking.ui.share_sweep_view(client, exp_id, sweep_id, parent, ("shaping.weight",))
    return uri, exp_id, sweep_id, run_ids[0]


def start_ui(uri: str, port: int, timeout: float = 240.0) -> tuple[subprocess.Popen[str], str]:
    """``spot ui --tracking-uri URI --port PORT``; returns the process and the address it printed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "spot.cli", "ui", "--tracking-uri", uri, "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=ROOT,
    )
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline, seen = time.monotonic() + timeout, []
    while time.monotonic() < deadline and proc.poll() is None:
        if sel.select(timeout=1.0):
            line = proc.stdout.readline()
            seen.append(line)
            if m := re.match(r"MLflow UI: (http://127\.0\.0\.1:\d+)$", line.strip()):
                return proc, m[1]
    proc.kill()
    raise AssertionError(f"spot ui printed no address in {timeout} s: {''.join(seen)[-2000:]}")


def browse(url: str, png: Path) -> str:
    """The page's DOM after its scripts ran, and its screenshot at ``png``."""
    dom = subprocess.run([CHROMIUM, *BROWSER, "--dump-dom", url], capture_output=True, text=True, timeout=180)
    subprocess.run([CHROMIUM, *BROWSER, f"--screenshot={png}", url], capture_output=True, timeout=180, check=True)
    return dom.stdout


def dom_of(url: str) -> str:
    """The page's DOM after its scripts ran (no screenshot)."""
    return subprocess.run([CHROMIUM, *BROWSER, "--dump-dom", url], capture_output=True, text=True, timeout=180).stdout


WORKSPACES = ("GenAI", "Model training")


def workspace_labels(dom: str) -> dict[str, str]:
    """The class of each label of the sidebar's workspace switch (``GenAI`` | ``Model training``): the
    UI draws the chosen one in the default text colour and the other in the secondary one, so the
    two differ and swap between the workspaces."""
    found = re.findall(
        r'<div role="button" tabindex="0" class="[^"]*"><span class="([^"]*)">(GenAI|Model training)</span></div>', dom
    )
    return {label: cls for cls, label in found}


def not_blank(png: Path) -> bool:
    """Written, a browser-sized picture, and more than a few colours."""
    from PIL import Image

    if not png.exists() or png.stat().st_size < 5_000:
        return False
    with Image.open(png) as im:
        colours = im.convert("RGB").resize((350, 225)).getcolors(maxcolors=100_000)
        return im.size == (1400, 900) and colours is not None and len(colours) > 20


def screenshots(work: Path, out: Path) -> dict[str, str]:
    """The store, ``spot ui`` on it, the sweep's link and a run page in Chromium: ``{name: DOM}``."""
    from spot import tracking
    from spot.sweep.mlflow_server import free_port

    uri, exp_id, sweep_id, run_id = make_store(work)
    proc, base = start_ui(uri, free_port())
    try:
        out.mkdir(parents=True, exist_ok=True)
        return {
            "sweep": browse(tracking.sweep_url(exp_id, sweep_id, base), out / "sweep-link.png"),
            "run": browse(tracking.run_url(exp_id, run_id, base), out / "run-page.png"),
            # the same run page in the GenAI workspace: the workspace switch as it looks there
            "run-genai": dom_of(tracking.run_url(exp_id, run_id, base).replace("=machine_learning", "=genai")),
        }
    finally:
        proc.send_signal(signal.SIGINT)  # spot ui stops its server on Ctrl-C
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine (apt-get install chromium)")
def test_the_printed_link_and_a_run_page_in_a_real_browser(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    dom = screenshots(tmp_path, tmp_path / "shots")
    assert not_blank(tmp_path / "shots" / "sweep-link.png") and not_blank(tmp_path / "shots" / "run-page.png")
    # the link: the trials are rows of their own (named by the swept λ), with the chosen columns
    for name in ("spot λ=0.5 s0", "spot λ=1.0 s0"):
        assert name in dom["sweep"], dom["sweep"][-3000:]
    for col in ("tags.`method`", "metrics.`eval/score_final`", "metrics.`eval/score_paper`"):  # (the grid
        assert f'col-id="{col}"' in dom["sweep"]  # renders the columns in view; the others come on scrolling)
    # a run page: the model-training view, with its model metrics
    assert "spot λ=0.5 s0" in dom["run"] and "Model metrics" in dom["run"]
    # ... and its sidebar shows the Model training workspace chosen: its switch's labels are drawn as
    # on the GenAI page with the roles swapped (the chosen label there is GenAI)
    shown, genai = workspace_labels(dom["run"]), workspace_labels(dom["run-genai"])
    assert set(shown) == set(genai) == set(WORKSPACES), (shown, genai)
    assert shown["Model training"] != shown["GenAI"]
    assert shown["Model training"] == genai["GenAI"] and shown["GenAI"] == genai["Model training"]


if __name__ == "__main__":
    import tempfile

    target = Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else ROOT / "ui-shots"
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        os.environ.pop("MLFLOW_TRACKING_URI", None)
        doms = screenshots(Path(tmp), target)
        for name, text in doms.items():
            print(name, len(text), "characters of DOM")
