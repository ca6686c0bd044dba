"""Search and early stopping in sweep files (issue 42, item 4): ``search:``, ``scheduler:``,
``metric``/``mode``.

Fast: the blocks' validation (one line naming the key), the expansion of a search sweep, the
trial's reports to Tune (carried metrics, a stop turned into a KILLED run's reason). Slow: a real
``spot sweep`` (Ray Tune, Optuna's searcher, ASHA, a loopback MLflow server, the pipeline at the
tiny budget) whose searcher proposes configs inside the declared ranges and whose scheduler stops
at least one trial early, recorded in MLflow as KILLED with the reason.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from spot import SpotError
from spot.sweep import reports, spec
from spot.sweep.trial import trial_overrides
from tests.test_sweep import _finished_child_runs

GOOD = """
name: srch
base: {method: oracle, budget: tiny, data.name: drawer-open}
metric: eval/score
mode: max
search:
  algorithm: optuna
  num_samples: 3
  space: {iql.temperature: {loguniform: [0.5, 10]}, iql.expectile: {choice: [0.7, 0.9]}}
scheduler: {name: asha, grace_period: 1, reduction_factor: 2}
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.yaml"
    path.write_text(text)
    return path


def test_a_search_sweep_loads(tmp_path):
    sweep = spec.load(_write(tmp_path, GOOD))
    assert sweep.metric == "eval/score" and sweep.mode == "max"
    assert sweep.search.algorithm == "optuna" and sweep.search.num_samples == 3
    assert sweep.search.space == {"iql.temperature": ("loguniform", [0.5, 10]), "iql.expectile": ("choice", [0.7, 0.9])}
    assert sweep.scheduler.name == "asha" and sweep.scheduler.options == {"grace_period": 1, "reduction_factor": 2}
    assert sweep.axis_keys == ("iql.temperature", "iql.expectile")  # tags, summary columns
    # one template trial, which the searcher's values complete
    (trial,) = sweep.trials()
    assert trial.axes == {} and trial.overrides == {"method": "oracle", "budget": "tiny", "data.name": "drawer-open"}
    # a proposed value wins over the template (as HyperOpt gives it: a numpy scalar)
    np = pytest.importorskip("numpy")
    config = {"trial": trial.to_config(), "search": {"iql.temperature": np.float64(2.5), "iql.expectile": 0.7}}
    over = trial_overrides(config)
    assert over["iql.temperature"] == 2.5 and type(over["iql.temperature"]) is float and over["method"] == "oracle"
    # the search block is part of what a resumed launch must match
    other = spec.load(_write(tmp_path, GOOD.replace("num_samples: 3", "num_samples: 4")))
    assert other.spec_hash() != sweep.spec_hash()


def test_a_scheduler_goes_with_a_grid(tmp_path):
    text = (
        "base: {method: oracle, budget: tiny, data.name: drawer-open}\ngrid: {iql.expectile: [0.7, 0.9]}\n"
        "metric: eval/score\nmode: max\nscheduler: {name: median, grace_period: 2, min_samples_required: 2}\n"
    )
    sweep = spec.load(_write(tmp_path, text))
    assert sweep.search is None and len(sweep.trials()) == 2
    assert sweep.scheduler.name == "median" and sweep.scheduler.options == {
        "grace_period": 2,
        "min_samples_required": 2,
    }


BASE = "base: {method: oracle, budget: tiny, data.name: drawer-open}\n"
SEARCH = "search: {algorithm: optuna, num_samples: 2, space: {iql.temperature: {loguniform: [0.5, 10]}}}\n"
OBJ = "metric: eval/score\nmode: max\n"


@pytest.mark.parametrize(
    "text, match",
    [
        (BASE + SEARCH, r"'metric': missing: 'search:' needs the metric"),
        (BASE + SEARCH + "metric: eval/score\n", r"'mode': expected max or min, got <missing>|'mode': expected max"),
        (
            BASE + SEARCH + "metric: eval/scor\nmode: max\n",
            r"'metric': expected one of eval/score, reward/best_eval_acc",
        ),
        (BASE + OBJ, r"'metric': only goes with 'search:' or 'scheduler:'"),
        (BASE + OBJ + SEARCH.replace("optuna", "optunaa"), r"'search.algorithm': expected one of optuna, hyperopt"),
        (BASE + OBJ + SEARCH.replace("num_samples: 2, ", ""), r"'search.num_samples': missing"),
        (BASE + OBJ + SEARCH.replace("num_samples: 2", "num_samples: 0"), r"'search.num_samples': expected an integer"),
        (
            BASE + OBJ + SEARCH.replace("algorithm", "algoritm"),
            r"'search.algoritm': unknown key; did you mean 'algorithm'",
        ),
        (
            BASE + OBJ + SEARCH.replace("[0.5, 10]", "[10, 0.5]"),
            r"'search.space.iql.temperature.loguniform': expected low < high",
        ),
        (
            BASE + OBJ + SEARCH.replace("[0.5, 10]", "[0, 10]"),
            r"'search.space.iql.temperature.loguniform': expected low > 0",
        ),
        (
            BASE + OBJ + SEARCH.replace("[0.5, 10]", "[0.5]"),
            r"'search.space.iql.temperature.loguniform': expected \[low, high\]",
        ),
        (
            BASE + OBJ + SEARCH.replace("[0.5, 10]", "[0.5, .nan]"),
            r"'search.space.iql.temperature.loguniform': expected \[low, high\]",
        ),
        (
            BASE + OBJ + SEARCH.replace("loguniform", "normal"),
            r"'search.space.iql.temperature': expected one of \{uniform",
        ),
        (
            BASE + OBJ + SEARCH.replace("{loguniform: [0.5, 10]}", "{choice: []}"),
            r"'search.space.iql.temperature.choice': expected a non-empty list",
        ),
        (
            BASE + OBJ + SEARCH.replace("iql.temperature", "iql.temprature"),
            r"unknown config key 'iql.temprature'; did you mean 'iql.temperature'",
        ),
        (BASE + OBJ + SEARCH.replace("iql.temperature", "seed"), r"'search.space.seed': may not be searched"),
        (
            BASE + OBJ + SEARCH + "grid: {iql.expectile: [0.7, 0.9]}\n",
            r"'grid': goes with 'search:' only as the searcher's space",
        ),
        (BASE.replace("}", ", iql.temperature: 3}") + OBJ + SEARCH, r"'base.iql.temperature': is also searched"),
        (BASE + OBJ + SEARCH + "seeds: [0, 1]\n", r"'seed_mode': a searcher proposes one config per trial"),
        (
            BASE + OBJ + "scheduler: {name: hyperband}\n",
            r"'scheduler.name': expected one of asha, median, got 'hyperband'",
        ),
        (
            BASE + OBJ + "scheduler: {name: asha, grace: 1}\n",
            r"'scheduler.grace': unknown key; did you mean 'grace_period'",
        ),
        (
            BASE + OBJ + "scheduler: {name: asha, reduction_factor: 1}\n",
            r"'scheduler.reduction_factor': expected an integer >= 2",
        ),
        (
            BASE + OBJ + "scheduler: {name: asha, grace_period: 4, max_t: 2}\n",
            r"'scheduler.max_t': expected at least grace_period",
        ),
        (BASE + OBJ + "scheduler: {name: median, reduction_factor: 2}\n", r"'scheduler.reduction_factor': unknown key"),
        (
            BASE + "metric: reward/best_eval_acc\nmode: max\nscheduler: {name: asha}\n",
            r"'metric': reward/best_eval_acc is the reward model's, but trial \(base\) \(method oracle\) trains none",
        ),
        (  # the ends of the space are resolved before anything starts
            BASE + OBJ + SEARCH.replace("iql.temperature: {loguniform: [0.5, 10]}", "eval.every: {randint: [0, 5]}"),
            r"trial eval.every=0: config key 'eval.every'",
        ),
    ],
)
def test_bad_search_blocks_name_file_and_key(tmp_path, text, match):
    with pytest.raises(SpotError, match=match) as info:
        spec.load(_write(tmp_path, text))
    assert "\n" not in str(info.value) and "s.yaml" in str(info.value)


def test_reports_carry_metrics_skip_until_the_metric_and_name_the_stop():
    sent: list[dict] = []
    rep = reports.Reports(sent.append, "eval/score", "ASHA")
    on_eval = reports.evaluated(3, rep)
    assert on_eval.takes_reward_metrics
    on_eval({"reward/best_eval_acc": 0.75, "reward/best_eval_loss": 0.5})  # before any evaluation: not sent
    assert sent == []
    on_eval({"step": 50, "score": 12.5})
    assert sent == [
        {
            "seed": 3,
            "reward/best_eval_acc": 0.75,
            "reward/best_eval_loss": 0.5,
            "score": 12.5,
            "eval/score": 12.5,
            "iql_step": 50,
        }
    ]

    def stop(metrics: dict) -> None:  # what Ray's tune.report does in a trial the scheduler stopped
        if metrics["iql_step"] > 150:
            raise SystemExit(0)

    rep = reports.Reports(stop, "eval/score", "ASHA")
    rep({"eval/score": 1.0, "iql_step": 150})
    rep({"eval/score": 1.5, "iql_step": 150})  # (carried: the next report is at the same step)
    with pytest.raises(reports.StoppedEarly, match=r"^stopped early by ASHA at step 200$") as info:
        rep({"eval/score": 2.0, "iql_step": 200})
    assert str(info.value) == "stopped early by ASHA at step 200"
    assert isinstance(info.value, KeyboardInterrupt)  # the run ends KILLED (spot.tracking.start_run)
    # without a metric (a grid sweep without a scheduler) every report is sent
    sent.clear()
    reports.Reports(sent.append)({"seed": 0, "score_final": 3.0})
    assert sent == [{"seed": 0, "score_final": 3.0}]


# --------------------------------------------------------------------------- a real launch
SWEEP = """
name: searchtest
base:
  method: oracle
  budget: tiny
  data.name: hopper-medium-replay
  iql.steps: 200
  eval.every: 50
  eval.episodes: 1
metric: eval/score
mode: max
search:
  algorithm: optuna
  num_samples: 4
  space:
    iql.temperature: {loguniform: [0.5, 10]}
    iql.expectile: {choice: [0.6, 0.7, 0.9]}
scheduler: {name: asha, grace_period: 1, reduction_factor: 2, max_t: 100}
resources: {cpu: 1, gpu: 0}
max_concurrent: 1
fast_compile: true
"""


@pytest.mark.slow
def test_searcher_proposes_and_asha_stops_a_trial(tmp_path, spot_dirs):
    from mlflow.tracking import MlflowClient

    from spot.sweep.mlflow_server import sqlite_uri

    path = tmp_path / "searchtest.yaml"
    path.write_text(SWEEP)
    env = {
        **os.environ,
        "SPOT_CACHE_DIR": str(tmp_path / "cache"),
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax"),
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("MLFLOW_TRACKING_URI", None)
    out = subprocess.run(
        [sys.executable, "-m", "spot.cli", "sweep", str(path)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = out.stdout[-4000:] + out.stderr[-4000:]
    assert "4 trials" in out.stdout, log
    client = MlflowClient(sqlite_uri(tmp_path / "spot_runs" / "mlflow.db"))
    exp = client.get_experiment_by_name("searchtest")
    runs = [r for r in client.search_runs([exp.experiment_id], max_results=100) if "spot.trial_key" in r.data.tags]
    assert len(runs) == 4, log
    # the searcher's proposals: inside the declared ranges, different from each other, and what ran
    temps = [float(r.data.params["iql.temperature"]) for r in runs]
    expectiles = [float(r.data.params["iql.expectile"]) for r in runs]
    assert all(0.5 <= t <= 10 for t in temps) and len(set(temps)) == 4, temps
    assert set(expectiles) <= {0.6, 0.7, 0.9}, expectiles
    assert all(math.isclose(float(r.data.tags["axis.iql.temperature"]), t) for r, t in zip(runs, temps, strict=True))
    # ASHA stopped at least one trial: its run is KILLED with the reason, and ended before its last evaluation
    stopped = [r for r in runs if r.info.status == "KILLED"]
    assert stopped, [(r.info.status, r.data.tags.get("failure_reason")) for r in runs]
    for r in stopped:
        reason = r.data.tags["failure_reason"]
        assert re.fullmatch(r"stopped early by ASHA at step \d+", reason), reason
        steps = [m.step for m in client.get_metric_history(r.info.run_id, "eval/score")]
        assert steps and max(steps) < 200 and int(reason.rsplit(" ", 1)[1]) == max(steps)
        assert "eval/score_final" not in r.data.metrics
    finished = [r for r in runs if r.info.status == "FINISHED"]
    assert finished and all("eval/score_final" in r.data.metrics for r in finished)
    assert all(r.info.status in ("FINISHED", "KILLED") for r in runs), [r.info.status for r in runs]
    # the launch's summary lists the proposed configs and the stopped runs as what they are
    assert "KILLED" in out.stdout and "iql.temperature" in out.stdout, log


@pytest.mark.slow
def test_resume_continues_the_searcher(tmp_path, spot_dirs):
    """SIGKILL a search launch after its first finished run, then --resume: the searcher's state
    is restored (4 configs in all, not 4 more), and each proposed config ends once."""
    import signal
    import time

    from mlflow.tracking import MlflowClient

    from spot.sweep.mlflow_server import sqlite_uri

    path = tmp_path / "searchresume.yaml"
    path.write_text(SWEEP.replace("name: searchtest", "name: searchresume"))
    env = {**os.environ, "SPOT_CACHE_DIR": str(tmp_path / "cache"), "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax")}
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = [sys.executable, "-m", "spot.cli", "sweep", str(path)]
    db = tmp_path / "spot_runs" / "mlflow.db"
    with open(tmp_path / "launch.log", "wb") as log:
        proc = subprocess.Popen(
            cmd, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )
        deadline = time.monotonic() + 600
        while _finished_child_runs(db) < 1:
            assert proc.poll() is None, (tmp_path / "launch.log").read_text()[-3000:]
            assert time.monotonic() < deadline, (tmp_path / "launch.log").read_text()[-3000:]
            time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    resumed = subprocess.run([*cmd, "--resume"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    log = resumed.stdout[-4000:] + resumed.stderr[-3000:]
    assert "resuming launch" in resumed.stdout and "runs finished" in resumed.stdout, log
    client = MlflowClient(sqlite_uri(db))
    exp = client.get_experiment_by_name("searchresume")
    runs = [r for r in client.search_runs([exp.experiment_id], max_results=100) if "spot.trial_key" in r.data.tags]
    by_key: dict[str, list] = {}
    for r in runs:
        by_key.setdefault(r.data.tags["spot.trial_key"], []).append(r)
    assert len(by_key) == 4, (len(by_key), log)  # num_samples configs in all, over both launches
    for key, key_runs in by_key.items():
        ended = [
            r
            for r in key_runs
            if r.info.status == "FINISHED"
            or re.fullmatch(r"stopped early by ASHA at step \d+", r.data.tags.get("failure_reason", ""))
        ]
        assert len(ended) == 1, (key, [(r.info.status, r.data.tags.get("failure_reason")) for r in key_runs])
        assert 0.5 <= float(ended[0].data.params["iql.temperature"]) <= 10
    assert not [r for r in runs if r.info.status == "RUNNING"]
    # the same Tune experiment, restored (a new one would hold trials of its own beside the first's)
    import json

    from ray import tune

    sweep_id = json.loads((tmp_path / "spot_runs" / "ray" / "searchresume.json").read_text())["sweep_id"]
    trials = tune.ExperimentAnalysis(str(tmp_path / "spot_runs" / "ray" / sweep_id)).trials
    assert len(trials) == 4 and all(t.status == "TERMINATED" for t in trials), [t.status for t in trials]
    # every ended run belongs to one of them (a run cut off by the kill may belong to a trial
    # proposed after Tune's last experiment checkpoint: the restored searcher proposes it again)
    ids = {str(t.trial_id) for t in trials}
    ended = [r for r in runs if r.info.status == "FINISHED" or "stopped early" in r.data.tags.get("failure_reason", "")]
    assert {r.data.tags["spot.trial_id"] for r in ended} == ids


@pytest.mark.parametrize("algorithm", ["optuna", "hyperopt"])
def test_each_searcher_proposes_inside_the_space(tmp_path, algorithm):
    """The installed optuna/hyperopt work with the installed Ray: each proposes values inside the
    declared domains, and the same seed proposes the same values (no Ray cluster needed)."""
    from spot.sweep import search as search_lib

    sweep = spec.load(_write(tmp_path, GOOD.replace("optuna", algorithm)))

    def proposals() -> list[dict]:
        searcher = search_lib.searcher(sweep.search)
        searcher.set_search_properties("eval/score", "max", {"search": search_lib.space(sweep.search)})
        out = []
        for i in range(5):
            config = searcher.suggest(f"t{i}")
            out.append(trial_overrides({"trial": sweep.trials()[0].to_config(), **config}))
            searcher.on_trial_complete(f"t{i}", {"eval/score": float(i)})
        return out

    first = proposals()
    for over in first:
        assert 0.5 <= over["iql.temperature"] <= 10 and over["iql.expectile"] in (0.7, 0.9)
    assert len({o["iql.temperature"] for o in first}) == 5
    assert proposals() == first


@pytest.mark.slow
def test_a_run_reports_the_reward_models_held_out_metrics(spot_dirs, tiny_drawer):
    """A trial's on_eval gets the reward model's held-out accuracy and loss after the reward stage
    (the values logged as reward/best_eval_*), then each evaluation's score: what a scheduler on an
    offline-safe metric reads."""
    from spot import config, pipeline
    from spot.tracking import MemoryTracker

    cfg = config.load(
        None,
        [
            "budget=tiny",
            "data.name=drawer-open",
            "method=mr",
            "iql.steps=100",
            "eval.every=100",
            "eval.episodes=1",
            "labels.num_queries=30",
            "labels.segment_length=25",
        ],
    )
    sent: list[dict] = []
    tracker = MemoryTracker("reward-metrics")
    pipeline.run(
        cfg,
        progress=False,
        tracker=tracker,
        on_eval=reports.evaluated(0, reports.Reports(sent.append, "reward/best_eval_acc")),
    )
    logged = {k: v[-1][1] for k, v in tracker.metrics.items() if k in ("reward/best_eval_acc", "reward/best_eval_loss")}
    assert set(logged) == {"reward/best_eval_acc", "reward/best_eval_loss"}
    assert sent, "no report carried the reward model's metric"
    assert not any("eval/score" in s for s in sent[:1])  # the first report: after the reward stage
    for report in sent:
        assert report["reward/best_eval_acc"] == pytest.approx(logged["reward/best_eval_acc"])
        assert report["reward/best_eval_loss"] == pytest.approx(logged["reward/best_eval_loss"])
    assert [s["iql_step"] for s in sent if "iql_step" in s] == [s["iql_step"] for s in sent[1:]]
    assert len(sent) >= 2
