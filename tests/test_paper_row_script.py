"""scripts/paper_cells_gpu.sh's CPU dry path (issue 40 item 4): the same one process at budget tiny
on a tiny dataset, with what it brings back (records, timings, the device); and its time limit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = ["iql.steps=100", "iql.chunk=50", "eval.every=50", "eval.episodes=1"]


def _script(
    out: Path, limit_s: int, tmp_path: Path, overrides: list[str] = TINY
) -> tuple[subprocess.CompletedProcess, float]:
    env = {
        **os.environ,
        "OUT": str(out),
        "LIMIT_S": str(limit_s),
        "POLL_S": "2",
        "BUDGET": "tiny",
        "DATA": "hopper-medium-replay",
        "SIZE": "tiny",
        "METHODS": "oracle,mr",
        "SEEDS": "0,1",
        "PY": sys.executable,
        "SPOT_CACHE_DIR": str(tmp_path / "cache"),
    }
    t0 = time.monotonic()
    done = subprocess.run(
        ["bash", str(ROOT / "scripts" / "paper_cells_gpu.sh"), *overrides],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    return done, time.monotonic() - t0


def _records(out: Path) -> dict[str, dict]:
    return {json.loads(p.read_text())["run_name"]: json.loads(p.read_text()) for p in out.glob("records/*/record.json")}


@pytest.mark.slow  # one tiny 4-run program (~100 s on 2 shared cores)
def test_the_dry_path_runs_one_process_and_brings_back_records_and_timings(tmp_path, spot_dirs):
    out = tmp_path / "out"
    done, _ = _script(out, 600, tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    records = _records(out)
    want = {f"{m} hopper-medium-replay s{s}" for m in ("oracle", "mr") for s in (0, 1)}
    assert set(records) == want and all(r["status"] == "FINISHED" for r in records.values())
    members = {t.get("spot.vmap.members", t.get("vmap.members")) for t in (r["tags"] for r in records.values())}
    assert members == {"oracle:0,oracle:1,mr:0,mr:1"}  # one program for the four runs
    for path in out.glob("records/*/metrics.jsonl"):
        keys = {json.loads(line)["key"] for line in path.read_text().splitlines()}
        assert {"eval/score", "eval/score_final", "time/iql_s", "time/total_s"} <= keys
    timings = (out / "timings.txt").read_text()
    assert "--- end: rc 0 after" in timings
    assert timings.count("FINISHED, iql step 100,") >= 4 and "reward_s" in timings  # MR's reward models, timed
    assert "jax" in (out / "device.txt").read_text()
    assert "recorded under" in (out / "run.log").read_text()


@pytest.mark.slow  # stopped by its limit after ~40 s
def test_the_limit_stops_the_process_and_its_records_end_killed(tmp_path, spot_dirs):
    """1M IQL updates cannot finish in 40 s: the records stop KILLED, with their curves so far."""
    out = tmp_path / "out"
    done, wall = _script(out, 40, tmp_path, [*TINY, "iql.steps=1000000", "iql.chunk=1000", "eval.every=500000"])
    assert done.returncode == 124, done.stdout[-3000:] + done.stderr[-3000:]
    assert wall < 40 + 30 + 20  # the limit, SIGKILL's grace, the script's own steps
    assert "--- end: rc 124 after" in (out / "timings.txt").read_text()
    records = _records(out)
    assert len(records) == 4 and all(r["status"] == "KILLED" for r in records.values())
