"""SAC's stop rule (target return with a step cap; deterministic or stochastic returns, one or more
evaluations in a row) and checkpoint/resume, at size tiny in Hopper-v5."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest

from spot import SpotError
from spot.recipes import locomotion, locomotion_sac, sac, sac_train

CFG = locomotion.SIZES["tiny"].sac_config("hopper")  # 3000 steps, eval every 500


class _Killed(Exception):
    pass


def _assert_same_run(a: sac_train.SACResult, b: sac_train.SACResult, steps: int | None = None) -> None:
    """``b`` equals ``a`` bit for bit (up to ``steps`` environment steps of ``a``)."""
    snaps_a = [s for s in a.snapshots if steps is None or s.step <= steps]
    assert [s.step for s in b.snapshots] == [s.step for s in snaps_a]
    assert [s.eval_return for s in b.snapshots] == [s.eval_return for s in snaps_a]
    for x, y in zip(snaps_a, b.snapshots, strict=True):
        jax.tree.map(np.testing.assert_array_equal, x.actor_params, y.actor_params)
    for key, rows in a.replay.items():
        np.testing.assert_array_equal(rows[:steps], b.replay[key], err_msg=key)


@pytest.fixture(scope="module")
def full():
    """The uninterrupted tiny run, no stop rule."""
    return sac_train.train_sac("Hopper-v5", CFG, 0, progress=False)


@pytest.mark.slow
def test_target_return_stops_at_the_first_evaluation_reaching_it(full):
    returns = [s.eval_return for s in full.snapshots]
    assert returns[-1] > returns[0]  # the tiny run learns something, or this test says nothing
    target = returns[3]
    stop = next(s.step for s in full.snapshots if s.eval_return >= target)
    assert stop < CFG.total_steps
    stopped = sac_train.train_sac("Hopper-v5", dataclasses.replace(CFG, target_return=target), 0, progress=False)
    assert stopped.snapshots[-1].step == stop and len(stopped.replay["rewards"]) == stop
    assert stopped.target_reached is True and full.target_reached is None
    _assert_same_run(full, stopped, steps=stop)  # the stop rule changes nothing before the stop


def test_target_reached_compares_the_last_evaluation():
    snaps = [sac_train.Snapshot(500, 10.0, 0.0, None), sac_train.Snapshot(1000, 40.0, 0.0, None)]

    def result(target):
        return sac_train.SACResult("Hopper-v5", 0, dataclasses.replace(CFG, target_return=target), snaps, {}, {})

    assert result(40.0).target_reached is True  # reached: >=
    assert result(40.5).target_reached is False  # the cap came first


def test_stop_rule_reads_the_chosen_policys_returns_over_consecutive_evaluations():
    # (step, deterministic return, stochastic return): the stochastic policy scores less, as Hopper's did
    snaps = [
        sac_train.Snapshot(k * 500, det, 0.0, None, sto, 1.0)
        for k, (det, sto) in enumerate([(50, 10), (60, 35), (45, 31)], 1)
    ]

    def reached(upto, target, policy, evals):
        cfg = dataclasses.replace(CFG, target_return=target, stop_policy=policy, stop_evals=evals)
        return sac_train.stop_reached(snaps[:upto], cfg)

    assert reached(1, 40.0, "deterministic", 1) and not reached(1, 40.0, "stochastic", 1)  # 50 >= 40 > 10
    assert not reached(2, 30.0, "stochastic", 2)  # 10, 35: the first of the two misses
    assert reached(3, 30.0, "stochastic", 2) and not reached(3, 32.0, "stochastic", 2)  # 35, 31
    assert reached(3, 45.0, "deterministic", 2) and not reached(3, 46.0, "deterministic", 2)  # 60, 45
    assert not reached(1, 0.0, "deterministic", 2)  # fewer evaluations than the rule needs
    assert not sac_train.stop_reached(snaps, CFG)  # no target: never
    unmeasured = [sac_train.Snapshot(500, 99.0, 0.0, None)]  # a stochastic rule needs stochastic returns
    assert not sac_train.stop_reached(unmeasured, dataclasses.replace(CFG, target_return=1.0, stop_policy="stochastic"))
    result = sac_train.SACResult(
        "Hopper-v5", 0, dataclasses.replace(CFG, target_return=30.0, stop_evals=2), snaps, {}, {}
    )
    assert result.target_reached is True  # 60 and 45 both >= 30


def test_stop_rule_fields_are_checked_and_left_out_of_a_runs_identity_at_their_defaults():
    with pytest.raises(SpotError, match="stop_policy = 'mean'; expected one of deterministic, stochastic"):
        dataclasses.replace(CFG, stop_policy="mean")
    with pytest.raises(SpotError, match="stop_evals = 0"):
        dataclasses.replace(CFG, stop_evals=0)
    with pytest.raises(SpotError, match="shape a stop rule, but target_return is None"):
        dataclasses.replace(CFG, stop_policy="stochastic")  # tiny has no target
    with pytest.raises(SpotError, match=r"StopRule.policy = 'mean'"):
        locomotion_sac.StopRule(3000.0, 1000, policy="mean")
    with pytest.raises(SpotError, match="expected a finite target, a positive cap and at least one evaluation"):
        locomotion_sac.StopRule(3000.0, 1000, evals=0)
    # runs cached before the fields existed keep their cache names: at the defaults the identity is the old asdict
    old = {k: v for k, v in dataclasses.asdict(CFG).items() if k not in ("stop_policy", "stop_evals")}
    assert sac.identity(CFG) == old
    sturdy = dataclasses.replace(CFG, target_return=1.0, stop_policy="stochastic", stop_evals=2)
    assert sac.identity(sturdy) == {**old, "target_return": 1.0, "stop_policy": "stochastic", "stop_evals": 2}


@pytest.mark.slow
def test_a_stochastic_two_in_a_row_rule_stops_where_its_returns_say_and_resumes_bit_for_bit(full, tmp_path):
    # first the whole run with the rule's evaluations and a target it never meets: the sampled-action
    # evaluations ride beside the deterministic ones and change nothing else
    never = dataclasses.replace(CFG, target_return=1e9, stop_policy="stochastic", stop_evals=2)
    capped = sac_train.train_sac("Hopper-v5", never, 0, progress=False)
    assert capped.target_reached is False and capped.snapshots[-1].step == CFG.total_steps
    _assert_same_run(full, capped)
    stoch = [s.stochastic_return for s in capped.snapshots]
    # a target that some pair of consecutive evaluations before the last meets: the smaller of the best pair
    pairs = [min(stoch[i - 1], stoch[i]) for i in range(1, len(stoch) - 1)]
    target = max(pairs)
    stop = capped.snapshots[1 + pairs.index(target)].step  # the first pair that meets it
    cfg = dataclasses.replace(never, target_return=target)
    run = sac_train.train_sac("Hopper-v5", cfg, 0, progress=False)
    assert run.snapshots[-1].step == stop < CFG.total_steps and run.target_reached is True
    assert [s.stochastic_return for s in run.snapshots] == stoch[: len(run.snapshots)]
    _assert_same_run(full, run, steps=stop)
    ckpt = tmp_path / "run.ckpt"

    def kill_at_1000(step, metrics):
        assert "eval/stochastic_return_mean" in metrics
        if step == 1000:
            raise _Killed

    with pytest.raises(_Killed):
        kw = {"on_eval": kill_at_1000, "checkpoint": ckpt, "checkpoint_every": 500}
        sac_train.train_sac("Hopper-v5", never, 0, progress=False, **kw)
    with pytest.raises(SpotError, match="belongs to another run"):  # the rule is part of the run's identity
        sac_train.train_sac("Hopper-v5", dataclasses.replace(never, stop_evals=1), 0, progress=False, checkpoint=ckpt)
    resumed = sac_train.train_sac("Hopper-v5", never, 0, progress=False, checkpoint=ckpt, checkpoint_every=500)
    assert resumed.resumed_from == (500,)
    assert [s.stochastic_return for s in resumed.snapshots] == stoch
    _assert_same_run(capped, resumed)


@pytest.mark.slow
def test_a_killed_run_resumes_from_its_checkpoint_bit_for_bit(full, tmp_path):
    ckpt = tmp_path / "run.ckpt"

    def kill_at_2500(step, metrics):
        if step == 2500:
            raise _Killed

    with pytest.raises(_Killed):
        sac_train.train_sac(
            "Hopper-v5", CFG, 0, progress=False, on_eval=kill_at_2500, checkpoint=ckpt, checkpoint_every=1000
        )
    assert ckpt.exists()  # written at steps 1000 and 2000; the run died after the 2500 evaluation
    other = tmp_path / "other.ckpt"
    other.write_bytes(ckpt.read_bytes())
    with pytest.raises(SpotError, match="belongs to another run"):
        sac_train.train_sac("Hopper-v5", CFG, 1, progress=False, checkpoint=other)  # seed 1, not 0
    resumed = sac_train.train_sac("Hopper-v5", CFG, 0, progress=False, checkpoint=ckpt, checkpoint_every=1000)
    assert resumed.resumed_from == (2000,)
    _assert_same_run(full, resumed)
    assert resumed.timing["checkpoint"] > 0 and resumed.timing["peak_rss_mb"] > 0


def test_checkpoint_interval_must_follow_evaluations():
    with pytest.raises(SpotError, match="checkpoint_every"):
        sac_train.train_sac("Hopper-v5", CFG, 0, progress=False, checkpoint_every=700)


def test_paper_size_trains_to_d4rl_expert_level():
    spec = locomotion.SIZES["paper"]
    hopper, walker = spec.sac_config("hopper"), spec.sac_config("walker2d")
    assert (hopper.target_return, walker.target_return) == (3000.0, 4000.0)
    assert hopper.total_steps >= 1_000_000 and walker.total_steps >= 1_000_000  # caps, not lengths
    assert spec.transitions == 1_000_000 and spec.medium_fraction == pytest.approx(1 / 3)
    assert locomotion.SIZES["tiny"].sac_config("hopper").target_return is None
    for size in locomotion.SIZES.values():
        for env in locomotion.ENV_IDS:
            assert size.checkpoint_every % size.sac_config(env).eval_every == 0


def test_paper_fast_keeps_papers_rows_and_targets_with_a_smaller_sac():
    paper, fast = locomotion.SIZES["paper"], locomotion.SIZES["paper-fast"]
    assert (fast.transitions, fast.medium_fraction) == (paper.transitions, paper.medium_fraction)
    # the same targets and caps; Hopper's paper-fast rule reads the stochastic policy twice in a row
    assert {e: (r.target, r.cap) for e, r in fast.stop.items()} == {e: (r.target, r.cap) for e, r in paper.stop.items()}
    assert fast.stop["walker2d"] == paper.stop["walker2d"] == locomotion_sac.StopRule(4000.0, 3_000_000)
    hopper = fast.sac_config("hopper")
    assert (hopper.stop_policy, hopper.stop_evals) == ("stochastic", 2)
    assert (paper.sac_config("hopper").stop_policy, paper.sac_config("hopper").stop_evals) == ("deterministic", 1)
    for env in locomotion.ENV_IDS:
        p, f = paper.sac_config(env), fast.sac_config(env)
        assert (f.target_return, f.total_steps, f.eval_every, f.eval_episodes) == (
            p.target_return,
            p.total_steps,
            p.eval_every,
            p.eval_episodes,
        )
        assert (f.hidden_dims, f.batch_size, f.actor_lr, f.critic_lr, f.temperature_lr) == (
            (128, 128),
            128,
            1e-3,
            1e-3,
            1e-3,
        )
        assert (p.hidden_dims, p.batch_size, p.actor_lr) == ((256, 256), 256, 3e-4)
    # the cache name ends in a hash of the SAC settings: a paper-fast run is never taken for a paper one
    digests = [
        locomotion_sac.sac_cache_path(Path("c"), "walker2d", s, 0).stem.rsplit("__", 1)[1]
        for s in ("paper", "paper-fast")
    ]
    assert digests[0] != digests[1]


def test_paper_fast_is_a_locomotion_size_only(tmp_path, monkeypatch):
    from spot import config
    from spot.data import registry

    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path))
    for name, recipe in (("drawer-open", "metaworld"), ("lift-ph", "robosuite")):
        with pytest.raises(
            SpotError, match=f"size 'paper-fast' is not built for dataset '{name}' \\({recipe} recipe\\)"
        ):
            registry.build(name, "paper-fast", 0, progress=False)
    assert list(tmp_path.iterdir()) == []  # refused before any lock or file
    with pytest.raises(SpotError, match="data.size=paper-fast is a size of the locomotion recipes"):
        config.resolve({"data.name": "drawer-open", "data.size": "paper-fast"})
    assert config.resolve({"data.name": "walker2d-medium-replay", "data.size": "paper-fast"}).data.size == "paper-fast"
