"""Seeds as a vmap axis: spot.run.multiseed.run against one spot.pipeline.run per seed."""

import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

from spot import SpotError, cache, config, pipeline, sweep
from spot.run import multiseed
from spot.tracking import MemoryTracker, locking

TINY = [
    "budget=tiny",
    "data.name=drawer-open",
    "iql.steps=150",
    "iql.chunk=100",
    "eval.every=100",
    "eval.episodes=1",
    "labels.num_queries=30",
    "labels.segment_length=25",
]
SEEDS = (0, 3)


def _cfg(seed: int, *overrides: str):
    return config.load(None, [*TINY, f"seed={seed}", *overrides])


def _params(tracker: MemoryTracker, tmp_path: Path, name: str):
    path = tmp_path / f"{name}.npz"
    path.write_bytes(tracker.artifacts["models/policy.npz"])
    return cache.read_entry(path)


def _series(tracker: MemoryTracker, name: str) -> list[tuple[int, float]]:
    return tracker.metrics[name]


@pytest.mark.slow  # 20-60 s of CPU each (two tiny one-seed runs and their vmapped pair)
@pytest.mark.parametrize("method", ["oracle", "spot"])
def test_vmapped_seeds_equal_one_run_per_seed(method, tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """Two seeds as one vmap trial against one run per seed, in one stage cache. Oracle: IQL for
    both seeds in one program; every seed's curve, chunk metrics, final metrics and saved policy
    equal its one-seed run's to float tolerance. SPOT: the reward models and the CVAEs
    are trained as one vmapped program too, under keys of their own (never the one-seed runs'
    entries), equal to one-seed training up to rounding that Adam amplifies (~1e-3), so IQL
    downstream is compared at that tolerance. The two seeds differ from each other."""
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    learned = method != "oracle"
    single = {s: MemoryTracker(f"single-{s}") for s in SEEDS}
    single_out = {s: pipeline.run(_cfg(s, f"method={method}"), progress=False, tracker=single[s]) for s in SEEDS}
    vmapped = {s: MemoryTracker(f"vmap-{s}") for s in SEEDS}
    evals: dict[int, list[float]] = {s: [] for s in SEEDS}
    with warnings.catch_warnings():  # a vmapped model whose key differs from its stage's is not used: fail
        warnings.filterwarnings("error", message=r"stage '\w+': a value computed for key")
        outs = multiseed.run(
            [_cfg(s, f"method={method}") for s in SEEDS],
            progress=False,
            trackers=[vmapped[s] for s in SEEDS],
            on_eval=[lambda m, s=s: evals[s].append(m["score"]) for s in SEEDS],
        )
    assert [o["run_id"] for o in outs] == [f"vmap-{s}" for s in SEEDS]  # one run per seed, in order
    for s, out in zip(SEEDS, outs, strict=True):
        a, b = single[s], vmapped[s]
        assert b.tags["seed_mode"] == "vmap" and b.tags["vmap.seeds"] == "0,3"
        if learned:  # trained here for both seeds as one program, stored apart from the one-seed entries
            assert b.tags["cache.reward"] == "miss" and b.tags["stage.reward.source"] == "computed"
            assert b.tags["vmap.reward"] == "0,3" and b.tags["stage.reward.key"] != a.tags["stage.reward.key"]
            assert cache.load(b.tags["stage.reward.key"])[0]  # the next vmap trial of these seeds reuses it
            for name in ("reward/train_loss", "reward/eval_loss", "reward/eval_acc"):
                np.testing.assert_allclose(
                    [v for _, v in _series(b, name)], [v for _, v in _series(a, name)], rtol=1e-4, atol=1e-5
                )
        if method == "spot":  # and the CVAEs, also as one program
            assert b.tags["vmap.cvae"] == "0,3" and b.tags["cache.cvae"] == "miss"
            assert b.tags["stage.cvae.key"] != a.tags["stage.cvae.key"]
            for name in ("cvae/loss", "cvae/heldout_loss"):
                np.testing.assert_allclose(
                    [v for _, v in _series(b, name)], [v for _, v in _series(a, name)], rtol=1e-3, atol=1e-4
                )
        if not learned:
            assert "vmap.reward" not in b.tags and "vmap.cvae" not in b.tags
        curve_a, curve_b = _series(a, "eval/score"), _series(b, "eval/score")
        assert [st for st, _ in curve_b] == [st for st, _ in curve_a] == [0, 100, 150]
        np.testing.assert_allclose([v for _, v in curve_b], [v for _, v in curve_a], atol=1e-4)
        assert evals[s] == [v for _, v in curve_b]
        # A vmapped reward model differs from its one-seed twin in the last bits, and in the
        # directions the preference loss cannot see (a constant added to r_hat) Adam makes that
        # ~1e-3 (tests/test_reward.py): IQL then sees rewards that differ at that level.
        tol = {"rtol": 5e-3, "atol": 5e-4} if learned else {"rtol": 1e-4, "atol": 1e-5}
        for name in ("iql/critic_loss", "iql/actor_loss", "iql/value_loss", "iql/q_mean"):
            assert [st for st, _ in _series(b, name)] == [st for st, _ in _series(a, name)] == [100, 150]
            np.testing.assert_allclose(
                [v for _, v in _series(b, name)], [v for _, v in _series(a, name)], **tol, err_msg=name
            )
        np.testing.assert_allclose(out["eval/score_final"], single_out[s]["eval/score_final"], atol=1e-4)
        pa, pb = _params(a, tmp_path, f"a{s}"), _params(b, tmp_path, f"b{s}")
        leaves_a, leaves_b = jax.tree.leaves(pa), jax.tree.leaves(pb)
        assert len(leaves_a) == len(leaves_b) > 0
        if learned:  # Adam lets a few weights move ~1e-3 apart: compare the policy as a whole
            flat_a, flat_b = (np.concatenate([np.ravel(x) for x in leaves]) for leaves in (leaves_a, leaves_b))
            assert np.linalg.norm(flat_b - flat_a) <= 5e-3 * np.linalg.norm(flat_a)
        else:
            for x, y in zip(leaves_a, leaves_b, strict=True):
                np.testing.assert_allclose(y, x, **tol)
        assert "learning_curve.png" in b.artifacts and "models/policy.json" in b.artifacts
    # the seeds are not copies of one another
    q = [[v for _, v in _series(vmapped[s], "iql/q_mean")] for s in SEEDS]
    assert q[0] != q[1]


@pytest.mark.slow  # a one-seed Oracle run and a three-method vmapped program (~40 s on 2 cores)
def test_methods_as_members_of_one_program(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """Oracle, PT and SPOT at seed 0 as one vmapped IQL program: Oracle's member equals a one-seed
    Oracle run; SPOT's reward model is PT's (the same stage-cache entry, trained once); each run
    is tagged with every member."""
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    single = MemoryTracker("single")
    pipeline.run(_cfg(0, "method=oracle"), progress=False, tracker=single)
    trackers = {m: MemoryTracker(m) for m in ("oracle", "pt", "spot")}
    outs = multiseed.run([_cfg(0, f"method={m}") for m in trackers], progress=False, trackers=list(trackers.values()))
    assert [o["run_id"] for o in outs] == ["oracle", "pt", "spot"]
    for t in trackers.values():
        assert t.tags["vmap.members"] == "oracle:0,pt:0,spot:0" and t.tags["vmap.seeds"] == "0,0,0"
    pt, spot = trackers["pt"].tags, trackers["spot"].tags
    assert pt["cache.reward"] == "miss" and spot["cache.reward"] == "hit"
    assert spot["stage.reward.key"] == pt["stage.reward.key"]
    curve, want = _series(trackers["oracle"], "eval/score"), _series(single, "eval/score")
    assert [st for st, _ in curve] == [st for st, _ in want] == [0, 100, 150]
    np.testing.assert_allclose([v for _, v in curve], [v for _, v in want], atol=1e-4)
    for name in ("iql/critic_loss", "iql/q_mean"):
        np.testing.assert_allclose(
            [v for _, v in _series(trackers["oracle"], name)],
            [v for _, v in _series(single, name)],
            rtol=1e-4,
            atol=1e-5,
        )
    # the members learn from their own rewards: PT's and SPOT's critics differ from Oracle's
    q = {m: [v for _, v in _series(t, "iql/q_mean")] for m, t in trackers.items()}
    assert q["pt"] != q["oracle"] and q["spot"] != q["pt"]


def test_vmap_refuses_ipl_and_mixed_configs():
    with pytest.raises(SpotError, match="method 'ipl' trains its own policy .*seed_mode: sequential"):
        multiseed.check([_cfg(0, "method=ipl"), _cfg(1, "method=ipl")])
    with pytest.raises(SpotError, match="seed 1's config differs from seed 0's"):
        multiseed.check([_cfg(0, "method=oracle"), _cfg(1, "method=oracle", "iql.lr=0.001")])
    with pytest.raises(SpotError, match=r"seeds \[2, 2\] repeat"):
        multiseed.check([_cfg(2, "method=oracle"), _cfg(2, "method=oracle")])
    # methods may differ in what makes their reward, not in the IQL program they share
    kinds = multiseed.check(
        [_cfg(0, "method=oracle"), _cfg(0, "method=pt"), _cfg(1, "method=spot", "shaping.weight=0.5")]
    )
    assert len(kinds) == 3
    with pytest.raises(SpotError, match=r"pt seed 0's config differs from seed 0's in eval\.\*"):
        multiseed.check([_cfg(0, "method=oracle"), _cfg(0, "method=pt", "eval.episodes=3")])
    with pytest.raises(SpotError, match="method 'ipl' trains its own policy"):
        multiseed.check([_cfg(0, "method=oracle"), _cfg(0, "method=ipl")])


# --------------------------------------------------------------------------- in a sweep
SWEEP_FILE = "name: ms\nbase: {method: oracle, budget: tiny}\ngrid: {data.name: [drawer-open]}\nseeds: [0, 1]\n"


def _sweep(tmp_path: Path, text: str):
    path = tmp_path / "ms.yaml"
    path.write_text(text)
    return sweep.load(path)


def test_seed_modes_expand_to_trials(tmp_path):
    trials = _sweep(tmp_path, SWEEP_FILE).trials()  # default: one trial per seed
    assert [(t.seeds, t.vmap) for t in trials] == [((0,), False), ((1,), False)]
    (seq,) = _sweep(tmp_path, SWEEP_FILE + "seed_mode: sequential\n").trials()
    assert (seq.seeds, seq.vmap) == ((0, 1), False) and "vmap" not in seq.to_config()
    (vm,) = _sweep(tmp_path, SWEEP_FILE + "seed_mode: vmap\n").trials()
    assert (vm.seeds, vm.vmap) == ((0, 1), True) and vm.to_config()["vmap"] is True
    with pytest.raises(
        SpotError,
        match=r"trial data.name=drawer-open: seed_mode vmap trains IQL over seeds; "
        r"method 'ipl'",
    ):
        _sweep(tmp_path, SWEEP_FILE.replace("oracle", "ipl") + "seed_mode: vmap\n")
    (ipl,) = _sweep(tmp_path, SWEEP_FILE.replace("oracle", "ipl") + "seed_mode: sequential\n").trials()
    assert ipl.seeds == (0, 1)


@pytest.mark.slow  # about 40 s: two tiny oracle seeds in one MLflow store
def test_a_vmap_trial_logs_one_run_per_seed_and_skips_them_when_finished(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    from mlflow.tracking import MlflowClient

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    s = _sweep(
        tmp_path,
        SWEEP_FILE.replace("budget: tiny}", "budget: tiny, iql.steps: 120, eval.every: 100, eval.episodes: 1}")
        + "seed_mode: vmap\n",
    )
    (trial,) = s.trials()
    locking.prepare_store(uri)
    client = MlflowClient(uri)
    exp = client.create_experiment("ms")
    parent = client.create_run(exp).info.run_id
    ctx = sweep.SweepContext("sweep-1", "ms", "ms", exp, parent, uri, s.axis_keys)
    reports: list[dict] = []
    finals = sweep.run_trial(trial.overrides, list(trial.seeds), ctx, trial_id="t1", report=reports.append, vmap=True)
    assert [f["seed"] for f in finals] == [0, 1] and all(f["skipped"] == 0 for f in finals)
    runs = {int(r.data.tags["seed"]): r for r in client.search_runs([exp], "tags.spot.sweep_id = 'sweep-1'")}
    assert sorted(runs) == [0, 1]
    for seed, run in runs.items():
        assert run.info.status == "FINISHED" and run.data.tags["spot.seed_mode"] == "vmap"
        assert run.data.tags["spot.trial_key"] == sweep.run_key(trial.overrides, seed)
        assert run.data.tags["mlflow.parentRunId"] == parent
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/score")]
        assert steps == [0, 100, 120]
        assert [r["score"] for r in reports if r.get("seed") == seed and "score" in r] == [
            m.value for m in client.get_metric_history(run.info.run_id, "eval/score")
        ]
    assert runs[0].data.metrics["eval/score_final"] == finals[0]["score_final"]

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished seed ran again")

    again = sweep.run_trial(
        trial.overrides, list(trial.seeds), ctx, trial_id="t2", report=lambda m: None, run_fn=must_not_run, vmap=True
    )
    assert [(f["seed"], f["skipped"], f["run_id"]) for f in again] == [(s, 1, runs[s].info.run_id) for s in (0, 1)]


def test_a_failed_vmap_trial_records_a_failed_run_per_seed(tmp_path):
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    s = _sweep(tmp_path, SWEEP_FILE + "seed_mode: vmap\n")
    (trial,) = s.trials()
    locking.prepare_store(uri)
    client = MlflowClient(uri)
    exp = client.create_experiment("ms")
    ctx = sweep.SweepContext("sweep-2", "ms", "ms", exp, client.create_run(exp).info.run_id, uri, s.axis_keys)

    def broken(cfgs, **kwargs):
        raise ValueError("no dataset today")

    with pytest.raises(RuntimeError, match="seed 0: ValueError: no dataset today; seed 1: ValueError"):
        sweep.run_trial(trial.overrides, [0, 1], ctx, trial_id="t", report=lambda m: None, run_fn=broken, vmap=True)
    runs = client.search_runs([exp], "tags.spot.sweep_id = 'sweep-2'")
    assert sorted(int(r.data.tags["seed"]) for r in runs) == [0, 1]
    assert all(r.info.status == "FAILED" and "no dataset today" in r.data.tags["failure_reason"] for r in runs)


def test_a_dataset_is_opened_once_per_process_until_its_file_changes(spot_dirs, tiny_drawer):
    """pipeline.open_dataset: the seeds of a sequential trial (and runs in one notebook) share the arrays."""
    import os

    cfg = _cfg(0, "method=oracle")
    ds, card = pipeline.open_dataset(cfg)
    again, card2 = pipeline.open_dataset(_cfg(1, "method=oracle"))  # another seed, same data
    assert again is ds and card2 == card and card2 is not card
    st = os.stat(tiny_drawer)
    os.utime(tiny_drawer, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # the file changed: opened again
    fresh, _ = pipeline.open_dataset(cfg)
    assert fresh is not ds and fresh.fingerprint() == ds.fingerprint()
    assert pipeline.open_dataset(cfg)[0] is fresh
