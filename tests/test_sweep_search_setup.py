"""What a search sweep shows and records before it runs (issue 42's leftovers for ``search:``).

- ``spot sweep FILE --dry-run`` shows the searcher, its ``num_samples``, every searched key's
  domain, the fixed part (base and seeds), the scheduler with its metric, mode and every option it
  runs with, and the trial and run counts, not one ``(base)`` trial.
- The launch's parent MLflow run records that setup as params.
- A ``smoke:`` block lowers ``num_samples`` and the scheduler's limits; its errors name the key.

Fast: the dry run (in process), the parent run on a SQLite store in tmp_path, the smoke block's
validation. Slow: a real ``--smoke`` launch of a search sweep whose smoke block cuts 12 configs to
2 and ASHA's ``max_t`` to 2 results.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from spot import SpotError, cli
from spot.sweep import search as search_lib
from spot.sweep import spec

SEARCH = """
name: iql-search
base: {method: spot, budget: small, data.name: hopper-medium-replay}
metric: eval/score
mode: max
search:
  algorithm: optuna
  num_samples: 16
  seed: 3
  space:
    iql.temperature: {loguniform: [0.5, 10]}
    shaping.weight: {choice: [0.1, 0.5, 1.0]}
    iql.expectile: {uniform: [0.6, 0.9]}
    labels.num_queries: {randint: [50, 200]}
scheduler: {name: asha, grace_period: 2, max_t: 40}
seeds: [0, 1, 2]
seed_mode: sequential
smoke:
  base: {budget: tiny}
  search: {num_samples: 2}
  scheduler: {max_t: 4}
  seeds: [0]
"""

# What the file above declares, written out by hand (not read back from the code).
SPACE = {
    "iql.temperature": "loguniform [0.5, 10]",
    "shaping.weight": "choice [0.1, 0.5, 1.0]",
    "iql.expectile": "uniform [0.6, 0.9]",
    "labels.num_queries": "randint [50, 200]",
}


def _write(tmp_path: Path, text: str, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _dry_run(capsys, path: Path, *extra: str) -> list[str]:
    assert cli.main(["sweep", str(path), "--dry-run", *extra]) == 0
    return capsys.readouterr().out.splitlines()


# --------------------------------------------------------------------------- (a) the dry run
def test_dry_run_of_a_search_sweep_shows_what_will_run(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, SEARCH)
    out = _dry_run(capsys, path)
    text = "\n".join(out)
    assert "(base)" not in text  # not the template trial
    # 16 proposed configs, each running seeds 0, 1, 2 in its trial (sequential): 48 runs
    assert re.search(r"^sweep 'iql-search' \(.*s\.yaml\): search: optuna, 16 trials, 48 runs, seed_mode seq", out[0])
    assert re.search(
        r"searcher: Optuna's TPE \(ray\.tune\.search\.optuna\.OptunaSearch\), seed 3, num_samples 16", text
    )
    for key, domain in SPACE.items():
        assert re.search(rf"^\s+{re.escape(key)}\s+{re.escape(domain)}", text, flags=re.M), (key, text)
    assert "space (4 keys):" in text
    assert "fixed: method=spot budget=small data.name=hopper-medium-replay" in text
    assert "16 proposed configs x seeds [0, 1, 2] = 48 runs (3 seeds per trial" in text
    assert "metric: eval/score (uses the online evaluation), mode max" in text
    # the scheduler with its metric, mode and every option it runs with: reduction_factor is spot's default
    asha = "ASHA (ray.tune.schedulers.ASHAScheduler) on eval/score (max): grace_period 2, reduction_factor 2, max_t 40"
    assert asha in text
    assert "ASHA compares trials at 2, 4, 8, 16, 32 results" in text  # 2 * 2**k up to 40
    assert list(tmp_path.iterdir()) == [path]  # nothing launched, nothing written


def test_dry_run_of_a_smoke_search_shows_its_smaller_budget(tmp_path, capsys):
    out = _dry_run(capsys, _write(tmp_path, SEARCH), "--smoke")
    text = "\n".join(out)
    assert re.search(r"^sweep 'iql-search-smoke' .*: search: optuna, 2 trials, 2 runs,", out[0])
    assert "num_samples 2: proposes 2 configs" in text
    assert "fixed: method=spot budget=tiny data.name=hopper-medium-replay" in text
    assert "2 proposed configs x seeds [0] = 2 runs (1 seed per trial" in text
    assert "on eval/score (max): grace_period 2, reduction_factor 2, max_t 4" in text
    assert "ASHA compares trials at 2, 4 results" in text


@pytest.mark.parametrize(
    "grace, max_t, factor", [(1, 1000, 2), (2, 40, 2), (1, 8, 2), (3, 81, 3), (1, 1, 2), (4, 100, 4), (2, 2, 2)]
)
def test_the_asha_rungs_shown_are_tunes(grace, max_t, factor):
    """The rungs the dry run prints are those of the ASHAScheduler the launch builds."""
    from spot.sweep import dryrun

    built = search_lib.scheduler(
        search_lib.Scheduler("asha", {"grace_period": grace, "max_t": max_t, "reduction_factor": factor})
    )
    (bracket,) = built._brackets  # one bracket (Tune's default)
    assert dryrun.asha_rungs(grace, max_t, factor) == sorted(int(t) for t, _ in bracket._rungs)


def test_dry_run_of_a_grid_with_a_scheduler_lists_trials_and_the_scheduler(tmp_path, capsys):
    text = (
        "base: {method: oracle, budget: tiny, data.name: drawer-open}\ngrid: {iql.expectile: [0.7, 0.9]}\n"
        "seeds: [0, 1]\nmetric: eval/score\nmode: max\nscheduler: {name: median, grace_period: 2}\n"
    )
    out = _dry_run(capsys, _write(tmp_path, text))
    assert re.search(r": 4 trials, 4 runs, seed_mode trials", out[0])  # 2 configs x 2 seeds, a trial each
    assert any(
        "median stopping (ray.tune.schedulers.MedianStoppingRule) on eval/score (max): grace_period 2, "
        "min_samples_required 3" in ln
        for ln in out
    )
    trials = [ln.split()[1:] for ln in out if re.match(r"^\s+\d+\s", ln)]
    assert trials == [
        ["iql.expectile=0.7", "seeds=[0]"],
        ["iql.expectile=0.9", "seeds=[0]"],
        ["iql.expectile=0.7", "seeds=[1]"],
        ["iql.expectile=0.9", "seeds=[1]"],
    ]


def test_counts_are_trials_and_runs_of_each_kind(tmp_path):
    grid = "base: {method: oracle, budget: tiny, data.name: drawer-open}\ngrid: {iql.expectile: [0.7, 0.8, 0.9]}\n"
    assert search_lib.counts(spec.load(_write(tmp_path, grid + "seeds: [0, 1]\n"))) == (6, 6)  # a trial per seed
    assert search_lib.counts(spec.load(_write(tmp_path, grid + "seeds: [0, 1]\nseed_mode: vmap\n"))) == (3, 6)
    assert search_lib.counts(spec.load(_write(tmp_path, SEARCH))) == (16, 48)
    assert search_lib.counts(spec.load(_write(tmp_path, SEARCH), smoke=True)) == (2, 2)


# --------------------------------------------------------------------------- (b) the parent run's params
@pytest.mark.parametrize("smoke", [False, True])
def test_the_parent_run_records_the_search_setup(tmp_path, smoke):
    from mlflow.tracking import MlflowClient

    from spot import tracking
    from spot.sweep.mlflow_server import sqlite_uri
    from spot.sweep.parent import open_parent

    sweep = spec.load(_write(tmp_path, SEARCH), smoke=smoke)
    uri = sqlite_uri(tmp_path / "mlflow.db")
    client = MlflowClient(uri)
    exp_id = tracking.experiment_id(sweep.experiment, uri)
    state = {"sweep_id": "iql-search-test"}
    run_id = open_parent(client, exp_id, sweep, state, resume=False)
    params = client.get_run(run_id).data.params
    n, max_t, seeds = (2, 4, 1) if smoke else (16, 40, 3)
    expected = {
        "sweep.metric": "eval/score",
        "sweep.mode": "max",
        "sweep.trials": str(n),  # the proposed configs, not the one template trial
        "sweep.runs": str(n * seeds),
        "search.algorithm": "optuna",
        "search.num_samples": str(n),
        "search.seed": "3",
        **{f"search.space.{k}": v for k, v in SPACE.items()},
        "scheduler.name": "asha",
        "scheduler.grace_period": "2",
        "scheduler.reduction_factor": "2",  # spot's default, recorded as it runs
        "scheduler.max_t": str(max_t),
        "scheduler.time_attr": "training_iteration",
    }
    assert {k: params.get(k) for k in expected} == expected
    assert params["base.method"] == "spot"  # the template is still there
    assert state["parent_run_id"] == run_id


def test_a_grid_sweeps_parent_params_are_unchanged_without_a_scheduler(tmp_path):
    grid = spec.load(
        _write(tmp_path, "base: {method: oracle, budget: tiny, data.name: drawer-open}\ngrid: {iql.expectile: [0.7]}\n")
    )
    assert search_lib.parent_params(grid) == {}


# --------------------------------------------------------------------------- (c) the smoke block
def test_the_smoke_block_lowers_num_samples_and_the_schedulers_limits(tmp_path):
    path = _write(tmp_path, SEARCH)
    full, smoke = spec.load(path), spec.load(path, smoke=True)
    assert full.search.num_samples == 16 and smoke.search.num_samples == 2
    assert smoke.search.space == full.search.space and smoke.search.seed == full.search.seed == 3
    assert full.scheduler.options == {"grace_period": 2, "max_t": 40}
    assert smoke.scheduler.options == {"grace_period": 2, "max_t": 4}  # the file's grace period kept
    built = search_lib.scheduler(smoke.scheduler)  # what Tune gets
    assert built._max_t == 4 and built._brackets[0]._rungs[-1][0] == 2
    # a median rule's grace period and sample count
    median = SEARCH.replace("{name: asha, grace_period: 2, max_t: 40}", "{name: median, grace_period: 6}").replace(
        "scheduler: {max_t: 4}", "scheduler: {grace_period: 1, min_samples_required: 2}"
    )
    sched = spec.load(_write(tmp_path, median), smoke=True).scheduler
    assert sched.options == {"grace_period": 1, "min_samples_required": 2}
    built = search_lib.scheduler(sched)
    assert built._grace_period == 1 and built._min_samples_required == 2
    # the spec hash of a smoke launch is its own (its record is <name>-smoke's anyway)
    assert full.spec_hash() != smoke.spec_hash()


SMOKE_BASE = SEARCH.split("smoke:")[0].replace("seeds: [0, 1, 2]\nseed_mode: sequential\n", "")


@pytest.mark.parametrize(
    "smoke, match",
    [
        (
            "search: {num_samples: 17}",
            r"'smoke.search.num_samples': expected an integer from 1 to search.num_samples \(16\), got 17",
        ),
        ("search: {num_samples: 0}", r"'smoke.search.num_samples': expected an integer from 1"),
        ("search: {num_samples: true}", r"'smoke.search.num_samples': expected an integer"),
        ("search: {num_sample: 2}", r"'smoke.search.num_sample': unknown key; did you mean 'num_samples'"),
        ("search: {space: {iql.temperature: {uniform: [1, 2]}}}", r"'smoke.search.space': unknown key"),
        ("search: 2", r"'smoke.search': expected a mapping with keys num_samples"),
        ("scheduler: {max_t: 1}", r"'smoke.scheduler.max_t': expected at least grace_period \(2\)"),
        ("scheduler: {grace_period: 41}", r"'smoke.scheduler.grace_period': expected at most max_t \(40\)"),
        ("scheduler: {max_t: 0}", r"'smoke.scheduler.max_t': expected an integer >= 1"),
        ("scheduler: {reduction_factor: 1}", r"'smoke.scheduler.reduction_factor': expected an integer >= 2"),
        ("scheduler: {min_samples_required: 2}", r"'smoke.scheduler.min_samples_required': unknown key"),
        ("scheduler: {name: median}", r"'smoke.scheduler.name': a smoke launch keeps the file's scheduler \(asha\)"),
        ("scheduler: {max_t: 2.5}", r"'smoke.scheduler.max_t': expected an integer >= 1, got 2.5"),
        ("serach: {num_samples: 2}", r"'smoke.serach': unknown key; did you mean 'search'"),
    ],
)
def test_bad_smoke_search_blocks_name_the_key(tmp_path, smoke, match):
    path = _write(tmp_path, f"{SMOKE_BASE}smoke:\n  {smoke}\n")
    for as_smoke in (False, True):  # the smoke block is checked whether or not it is applied
        with pytest.raises(SpotError, match=rf"^sweep file '{re.escape(str(path))}': {match}"):
            spec.load(path, smoke=as_smoke)


@pytest.mark.parametrize(
    "text, match",
    [
        (
            "base: {method: oracle, budget: tiny, data.name: drawer-open}\ngrid: {iql.expectile: [0.7]}\n"
            "smoke: {search: {num_samples: 1}}\n",
            r"'smoke.search': the file has no 'search:' block for it to shrink",
        ),
        (
            SMOKE_BASE.replace("scheduler: {name: asha, grace_period: 2, max_t: 40}\n", "")
            + "smoke: {scheduler: {max_t: 3}}\n",
            r"'smoke.scheduler': the file has no 'scheduler:' block for it to shorten",
        ),
        (
            # without a max_t in the file, ASHA runs to spot's default 1000: a smoke grace period above it
            SMOKE_BASE.replace("grace_period: 2, max_t: 40", "grace_period: 2")
            + "smoke: {scheduler: {grace_period: 1001}}\n",
            r"'smoke.scheduler.grace_period': expected at most max_t \(1000\)",
        ),
    ],
)
def test_a_smoke_block_without_what_it_changes_is_refused(tmp_path, text, match):
    with pytest.raises(SpotError, match=match):
        spec.load(_write(tmp_path, text))


def test_the_cli_refuses_a_bad_smoke_block_in_one_line(tmp_path, capsys):
    path = _write(tmp_path, f"{SMOKE_BASE}smoke:\n  search: {{num_samples: 99}}\n")
    assert cli.main(["sweep", str(path), "--dry-run", "--smoke"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: sweep file") and "'smoke.search.num_samples'" in err[0], err


# --------------------------------------------------------------------------- a real smoke launch
LAUNCH = """
name: searchsmoke
base: {method: oracle, budget: small, data.name: drawer-open}
metric: eval/score
mode: max
search:
  algorithm: optuna
  num_samples: 12
  space: {iql.temperature: {loguniform: [0.5, 10]}}
scheduler: {name: asha, grace_period: 4, max_t: 1000}
resources: {cpu: 1, gpu: 0}
smoke:
  base: {budget: tiny, iql.steps: 200, eval.every: 50, eval.episodes: 1}
  search: {num_samples: 2}
  scheduler: {grace_period: 2, max_t: 2}
  max_concurrent: 1
  fast_compile: true
"""


@pytest.mark.slow
def test_a_smoke_launch_of_a_search_sweep_runs_its_smaller_budget(tmp_path, spot_dirs, tiny_drawer):
    """``--smoke``: 2 proposed configs instead of 12, and ASHA's max_t of 2 results stops each trial
    at its second evaluation (step 50 of 200); the parent run records the smoke launch's setup."""
    from mlflow.tracking import MlflowClient

    from spot.sweep.mlflow_server import sqlite_uri

    path = _write(tmp_path, LAUNCH, "searchsmoke.yaml")
    env = {
        **os.environ,
        "SPOT_CACHE_DIR": str(tmp_path / "cache"),
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax"),
        "SPOT_CPU_SLOTS_DIR": str(tmp_path / "slots"),
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("MLFLOW_TRACKING_URI", None)
    out = subprocess.run(
        [sys.executable, "-m", "spot.cli", "sweep", str(path), "--smoke"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = out.stdout[-4000:] + out.stderr[-4000:]
    assert "2 trials, 2 runs" in out.stdout, log
    client = MlflowClient(sqlite_uri(tmp_path / "spot_runs" / "mlflow.db"))
    exp = client.get_experiment_by_name("searchsmoke-smoke")
    runs = client.search_runs([exp.experiment_id], max_results=100)
    parents = [r for r in runs if "search.num_samples" in r.data.params]
    children = [r for r in runs if r not in parents]
    assert len(parents) == 1 and len(children) == 2, ([r.info.run_name for r in runs], log)
    for r in children:  # stopped at max_t: the second result is the evaluation at step 50
        steps = sorted(m.step for m in client.get_metric_history(r.info.run_id, "eval/score"))
        assert steps == [0, 50], (steps, log)
        assert r.info.status == "KILLED" and "eval/score_final" not in r.data.metrics, log
        assert 0.5 <= float(r.data.params["iql.temperature"]) <= 10
    params = parents[0].data.params
    assert params["search.num_samples"] == "2" and params["sweep.trials"] == "2"
    assert params["scheduler.max_t"] == "2" and params["scheduler.grace_period"] == "2"
    assert out.returncode == 1, log  # no run finished: each was stopped at max_t
