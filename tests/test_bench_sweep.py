"""Where a sweep trial's time goes (spot.phases, spot bench sweep) and trials in a reused process.

The phase clock is checked against hand-computed times on a fake clock; the real sweep (three tiny
Oracle trials, one at a time, so that Tune reuses one actor process) checks that every run carries
its trial's breakdown, that the phases add up to the trial's wall time, that the second and third
trials ran in the first one's process, and that a run in a reused process gives the numbers the
same config and seed give in a process of its own. No timing is asserted.
"""

from __future__ import annotations

import os
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from spot import phases
from spot.sweep.summary import PHASE_COLUMNS, Row, format_breakdown
from spot.tracking.processes import PID_TAG
from tests.conftest import run_cli

REPO = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------- the clock
class FakeTime:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def fake_time(monkeypatch):
    clock = FakeTime()
    monkeypatch.setattr(phases.time, "perf_counter", clock)
    monkeypatch.setattr(phases.time, "time", clock)
    return clock


def test_compile_spans_count_their_union():
    spans: list[list[float]] = []
    assert phases._add_span(spans, 2, 5) == 3  # an inner trace ends first
    assert phases._add_span(spans, 0, 10) == 7  # the outer one: only what the inner did not cover
    assert phases._add_span(spans, 12, 13) == 1
    assert phases._add_span(spans, 9, 12.5) == 2  # 10..12 is new
    assert spans == [[0, 13]]
    assert phases._add_span(spans, 3, 3) == 0


def test_phases_are_exclusive_and_add_up_to_the_wall_time(fake_time):
    with phases.measure("other") as clock:
        fake_time.now = 1
        with phases.phase("train"):
            fake_time.now = 3
            with phases.phase("evaluate"):
                fake_time.now = 6
            fake_time.now = 7
            phases._on_span(phases.COMPILE_EVENTS[2], 6.0, 7.0)  # a compilation in the train phase
            phases._on_span("/jax/some/other_event", 6.0, 7.0)  # not a compilation: ignored
            fake_time.now = 8
        with phases.phase("tracking"):
            fake_time.now = 8.5
        phases.timed_calls(type("C", (), {"log": lambda self: setattr(fake_time, "now", 9.5)})()).log()
        fake_time.now = 10
        spent = clock.read()
        assert clock.wall == clock.read_wall == 10
    # compile 6..7 = 1 s, taken from the phase it was reported in (train)
    assert spent == {
        "startup": 0,
        "data": 0,
        "compile": 1,
        "train": (3 - 1) + (8 - 6) - 1,
        "evaluate": 3,
        "tracking": 0.5 + 1,
        "other": 1 + 0.5,
    }
    assert sum(spent.values()) == 10
    with phases.phase("train"):  # outside measure(): nothing to charge, no error
        pass


def test_compile_listener_sees_a_real_jit_compilation():
    import jax
    import jax.numpy as jnp

    phases.listen_to_compiles()

    def f(x):
        return jnp.sin(x) * 3.0 + 1.0

    fn = jax.jit(f)
    x = jnp.arange(7.0)
    with phases.measure("train") as clock:
        fn(x).block_until_ready()
        first = clock.read()["compile"]
        fn(x).block_until_ready()  # compiled: no compile event
        second, wall = clock.read(), clock.read_wall
    assert 0 < first <= wall
    assert second["compile"] == first
    assert sum(second.values()) == pytest.approx(wall, rel=1e-9)


# --------------------------------------------------------------------------- the printed breakdown
def _row(trial_id: str, seed: int, timing: dict[str, float], device: str = "cpu:cpu") -> Row:
    return Row({"method": "oracle"}, seed, f"k{seed}", "FINISHED", 1.0, "", f"r{seed}", 1, trial_id, timing, device)


def _timing(startup, data, compile_, train, evaluate, tracking, other, cpu_s, cpus=1.0) -> dict[str, float]:
    values = dict(zip(PHASE_COLUMNS, (startup, data, compile_, train, evaluate, tracking, other), strict=True))
    t = {f"time/trial_{k}_s": float(v) for k, v in values.items()}
    wall = sum(values.values())
    t.update({"time/trial_wall_s": wall, "time/trial_cpu_s": cpu_s, "time/trial_cpus": cpus})
    t["trial/cpu_util"] = cpu_s / ((wall - startup) * cpus)
    return t


def test_breakdown_table_sums_trials_and_counts_a_multi_seed_trial_once():
    a = _timing(10, 1, 20, 40, 20, 5, 4, cpu_s=72)  # wall 100, function 90 s on 1 CPU: 80 %
    b = _timing(0, 0, 0, 30, 8, 2, 0, cpu_s=20)  # wall 40: 50 %
    rows = [_row("t1", 0, a), _row("t2", 1, b), _row("t2", 2, b)]  # t2: two seeds, one trial
    text = format_breakdown(rows, ("method",), fit=None, per_trial=True)
    lines = text.splitlines()
    assert lines[1].split() == ["trial", *PHASE_COLUMNS, "wall", "cpu%"]
    assert lines[3].split() == ["oracle,s0", "10.0", "1.0", "20.0", "40.0", "20.0", "5.0", "4.0", "100.0", "80"]
    assert lines[4].split() == ["oracle,s1,2", "0.0", "0.0", "0.0", "30.0", "8.0", "2.0", "0.0", "40.0", "50"]
    # totals: 140 s; CPU 92 s over 90 + 40 CPU-seconds of trial functions = 71 %
    assert lines[5].split() == [
        "total",
        "(2",
        "trials)",
        "10.0",
        "1.0",
        "20.0",
        "70.0",
        "28.0",
        "7.0",
        "4.0",
        "140.0",
        "71",
    ]
    assert lines[6].split() == ["share", "7%", "1%", "14%", "50%", "20%", "5%", "3%"]
    assert lines[-1] == "device (jax.devices()): cpu:cpu"
    fit = {"sweep/fit_wall_s": 60.0, "sweep/fit_cpu_s": 108.0, "sweep/cpus": 2.0, "sweep/cpu_util": 0.9}
    assert "CPU utilisation 90% of 2 cores" in format_breakdown(rows, ("method",), fit=fit)
    assert "oracle,s0" not in format_breakdown(rows, ("method",))  # totals only by default
    assert format_breakdown([_row("", 0, {})], ("method",)) == ""  # nothing timed, nothing printed


def test_cuda_extra_pins_jax_cuda_at_the_jaxlib_version_and_the_image_installs_it():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    jaxlib = next(d.split("==")[1] for d in project["dependencies"] if d.startswith("jaxlib=="))
    assert project["optional-dependencies"]["cuda"] == [f"jax[cuda12]=={jaxlib}"]
    assert '.[cuda]"' in (REPO / "docker" / "Dockerfile.cuda").read_text()


def test_bench_sweep_needs_a_file():
    out = run_cli("bench", "sweep")
    assert out.returncode == 2 and out.stderr.strip().startswith("error: spot bench sweep needs the sweep file")


def test_bench_seeds_go_with_iql_pt_and_eval_only():
    out = run_cli("bench", "cvae", "--small", "--seeds", "2")
    assert out.returncode == 2 and out.stderr.strip() == (
        "error: spot bench cvae: --seeds (seeds as a vmap axis) goes with iql, pt and eval"
    )


def test_reward_steps_of_vmapped_seeds_count_seed_steps(monkeypatch):
    """bench.reward_steps with 3 seeds times one vmapped chunk over states stacked on a seed axis
    and counts steps x seeds (the timer is replaced by fixed figures: 1 s, 3 CPU-seconds)."""
    import jax

    from spot import bench
    from spot.config import MRConfig
    from spot.reward.mr import MR

    seen = {}

    def fixed_timer(chunk, state, n, args, repeats):
        seen["leading"] = {np.shape(x)[0] for x in jax.tree.leaves(state.params)}
        seen["keys"] = np.shape(args[1])
        return {"elapsed_s": 1.0, "cpu_s": 3.0, "compile_s": 0.5}

    monkeypatch.setattr(bench, "_time_chunks", fixed_timer)
    out = bench.reward_steps(MR(MRConfig(hidden=(16, 16))), batch=8, length=5, steps=2, seeds=3)
    assert seen == {"leading": {3}, "keys": (3,)}
    assert out["steps_per_s"] == 6.0 and out["cpu_s_per_step"] == 0.5 and out["compile_s"] == 0.5


# --------------------------------------------------------------------------- a real sweep
TINY_SWEEP = """
name: benchtiny
base: {method: oracle, budget: tiny, data.name: drawer-open, data.size: tiny, iql.steps: 100, eval.every: 50,
       eval.episodes: 1}
seeds: [0, 1, 2]
resources: {cpu: 1, gpu: 0}
max_concurrent: 1
"""


@pytest.fixture(scope="module")
def benched(tmp_path_factory, spot_dirs, tiny_drawer):
    """``spot bench sweep`` of three one-seed trials, one at a time; returns the output and the runs."""
    from mlflow.tracking import MlflowClient

    root = tmp_path_factory.mktemp("bench")
    (root / "tiny.yaml").write_text(TINY_SWEEP)
    # CPU slots of its own: another test's sweep holding the node's slots would leave this one's
    # trials unpinned (time/trial_cpus 2, not 1)
    env = {
        "SPOT_CACHE_DIR": str(root / "cache"),
        "SPOT_CPU_SLOTS_DIR": str(root / "slots"),
        "SPOT_TRIAL_THREADS": "follow",  # not the default: the end-to-end check of the free CPUs' use
        "PYTHONUNBUFFERED": "1",
        "MLFLOW_TRACKING_URI": "",
    }
    out = run_cli("bench", "sweep", "tiny.yaml", cwd=root, env=env, timeout=900)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    client = MlflowClient(f"sqlite:///{root / 'spot_runs' / 'mlflow.db'}")
    exp = client.get_experiment_by_name("benchtiny")
    runs = [r for r in client.search_runs([exp.experiment_id]) if "spot.trial_key" in r.data.tags]
    runs = sorted(runs, key=lambda r: int(r.data.tags["seed"]))
    return {"stdout": out.stdout, "runs": runs, "client": client, "slots": root / "slots"}


@pytest.mark.slow
def test_every_run_carries_its_trials_breakdown_adding_up_to_the_wall_time(benched):
    runs = benched["runs"]
    assert len(runs) == 3
    for r in runs:
        m = r.data.metrics
        parts = [m[f"time/trial_{p}_s"] for p in PHASE_COLUMNS]
        assert all(p >= 0 for p in parts), parts
        assert sum(parts) == pytest.approx(m["time/trial_wall_s"], rel=1e-6)
        # the run itself (MLflow's start and end) lies within the trial's wall time
        assert (r.info.end_time - r.info.start_time) / 1000 <= m["time/trial_wall_s"] + 1e-3
        assert m["time/total_s"] <= m["time/trial_wall_s"]
        assert m["time/trial_train_s"] > 0 and m["time/trial_evaluate_s"] > 0 and m["time/trial_tracking_s"] > 0
        assert 0 < m["trial/cpu_util"] and 1 <= m["time/trial_cpus"] <= len(os.sched_getaffinity(0))
        if len(os.sched_getaffinity(0)) > 1:  # each trial ran alone: its threads followed the free CPUs
            assert m["time/trial_cpus"] > 1
        assert r.data.tags["spot.trial_device"].startswith("cpu:")
    assert sorted(p.name for p in benched["slots"].glob("cpu*"))  # the trials claimed their slots there
    # a fresh compilation cache: the first trial compiled its programs
    assert runs[0].data.metrics["time/trial_compile_s"] > 0


@pytest.mark.slow
def test_bench_sweep_prints_each_trial_the_totals_cpu_and_device(benched):
    out = benched["stdout"]
    report = out[out.index("[sweep] benchtiny: 3/3 runs finished in") :].splitlines()
    assert report[1] == "where the trials' time went (seconds):"
    assert report[2].split() == ["trial", *PHASE_COLUMNS, "wall", "cpu%"]
    trial_lines = report[4:7]
    assert [ln.split()[0] for ln in trial_lines] == ["s0", "s1", "s2"]
    for line in trial_lines:
        cells = [float(x) for x in line.split()[1:]]
        assert len(cells) == 9 and abs(sum(cells[:7]) - cells[7]) <= 0.05 * 8  # printed to 0.1 s
    assert report[7].startswith("total (3 trials)") and report[8].startswith("share")
    assert any(ln.startswith("device (jax.devices()): cpu:") for ln in report)
    assert re.search(r"^command: [\d.]+ CPU-seconds over [\d.]+ s: CPU utilisation \d+% of \d+ cores$", out, re.M)
    # the floor (3 runs x 100 IQL updates at a calibrated rate) and each phase's ratio to it
    assert re.search(
        r"^floor: 300 IQL updates at [\d,]+ updates/s = [\d.]+ s on \d+ cores \(rates measured now", out, re.M
    )
    assert re.search(r"^ratio to the floor .*: startup [\d.]+x .* outside -?[\d.]+x  = [\d.]+x \(", out, re.M)
    # spot sweep's own end (inside the command) prints the totals and the sweep's CPU utilisation
    head = out[: out.index("[sweep] benchtiny")]
    assert "total (3 trials)" in head and re.search(r"CPU utilisation \d+% of \d+ cores", head)


@pytest.mark.slow
def test_trials_reuse_one_process_and_give_a_fresh_process_numbers(benched, tmp_path, monkeypatch):
    """Tune reuses the first trial's actor for the next two (reuse_actors); a run there gives the
    same numbers as the same config and seed run in a process of its own (``spot run``)."""
    runs, client = benched["runs"], benched["client"]
    assert len({r.data.tags[PID_TAG] for r in runs}) == 1
    assert [r.data.tags["spot.trial_process"] for r in runs] == ["new", "reused", "reused"]
    reused = runs[2]
    env = {
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'alone.db'}",
        "SPOT_CACHE_DIR": str(tmp_path / "cache"),
        "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",  # as a 1-CPU trial
    }
    out = run_cli(
        "run",
        "method=oracle",
        "budget=tiny",
        "data.name=drawer-open",
        "data.size=tiny",
        "iql.steps=100",
        "eval.every=50",
        "eval.episodes=1",
        "seed=2",
        cwd=tmp_path,
        env=env,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    from mlflow.tracking import MlflowClient

    alone_client = MlflowClient(env["MLFLOW_TRACKING_URI"])
    (alone,) = alone_client.search_runs([e.experiment_id for e in alone_client.search_experiments()])
    keys = sorted(k for k in alone.data.metrics if k.startswith(("iql/", "eval/")))
    assert "eval/score_final" in keys and any(k.startswith("iql/") for k in keys)
    for key in keys:
        a = [(m.step, m.value) for m in alone_client.get_metric_history(alone.info.run_id, key)]
        b = [(m.step, m.value) for m in client.get_metric_history(reused.info.run_id, key)]
        assert [s for s, _ in a] == [s for s, _ in b], key
        assert [v for _, v in a] == pytest.approx([v for _, v in b], rel=1e-5, abs=1e-6), key


def test_bench_sac_times_the_three_parts_of_a_recipe_step_and_env_goes_with_sac_only():
    out = run_cli("bench", "sac", "--small", "--env", "hopper", "--size", "paper-fast")
    assert out.returncode == 0, out.stderr
    figures = {
        line.split()[0]: float(line.split()[1].replace(",", ""))
        for line in out.stdout.splitlines()[1:]
        if line.split()[0] != "device"
    }
    assert out.stdout.startswith(
        "[sac] SAC steps of the hopper recipe at size paper-fast (--small) (batch 64, (32, 32)"
    )
    parts_s = (figures["update_ms"] + figures["act_ms"] + figures["env_step_ms"]) / 1e3
    assert min(figures["update_ms"], figures["act_ms"], figures["env_step_ms"]) > 0
    assert figures["steps_per_s"] == pytest.approx(1 / parts_s, rel=0.01)  # printed to 3 decimals
    assert figures["hours_per_1m_steps"] == pytest.approx(1e6 * parts_s / 3600, rel=0.01)
    out = run_cli("bench", "iql", "--small", "--env", "hopper")
    assert out.returncode == 2 and out.stderr.strip() == "error: spot bench iql: --env goes with 'spot bench sac'"
    out = run_cli("bench", "sweep", "sweeps/quickstart.yaml", "--size", "paper-fast")
    assert out.returncode == 2 and out.stderr.strip() == "error: spot bench sweep: --size goes with 'spot bench sac'"
