"""SAC's stop rule (target return with a step cap) and checkpoint/resume, at size tiny in Hopper-v5."""

import dataclasses
from pathlib import Path

import jax
import numpy as np
import pytest

from spot import SpotError
from spot.policy import sac
from spot.recipes import locomotion

CFG = locomotion.SIZES["tiny"].sac_config("hopper")  # 3000 steps, eval every 500


class _Killed(Exception):
    pass


def _assert_same_run(a: sac.SACResult, b: sac.SACResult, steps: int | None = None) -> None:
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
    return sac.train_sac("Hopper-v5", CFG, 0, progress=False)


@pytest.mark.slow
def test_target_return_stops_at_the_first_evaluation_reaching_it(full):
    returns = [s.eval_return for s in full.snapshots]
    assert returns[-1] > returns[0]  # the tiny run learns something, or this test says nothing
    target = returns[3]
    stop = next(s.step for s in full.snapshots if s.eval_return >= target)
    assert stop < CFG.total_steps
    stopped = sac.train_sac("Hopper-v5", dataclasses.replace(CFG, target_return=target), 0, progress=False)
    assert stopped.snapshots[-1].step == stop and len(stopped.replay["rewards"]) == stop
    assert stopped.target_reached is True and full.target_reached is None
    _assert_same_run(full, stopped, steps=stop)  # the stop rule changes nothing before the stop


def test_target_reached_compares_the_last_evaluation():
    snaps = [sac.Snapshot(500, 10.0, 0.0, None), sac.Snapshot(1000, 40.0, 0.0, None)]

    def result(target):
        return sac.SACResult("Hopper-v5", 0, dataclasses.replace(CFG, target_return=target), snaps, {}, {})

    assert result(40.0).target_reached is True  # reached: >=
    assert result(40.5).target_reached is False  # the cap came first


@pytest.mark.slow
def test_a_killed_run_resumes_from_its_checkpoint_bit_for_bit(full, tmp_path):
    ckpt = tmp_path / "run.ckpt"

    def kill_at_2500(step, metrics):
        if step == 2500:
            raise _Killed

    with pytest.raises(_Killed):
        sac.train_sac("Hopper-v5", CFG, 0, progress=False, on_eval=kill_at_2500, checkpoint=ckpt, checkpoint_every=1000)
    assert ckpt.exists()  # written at steps 1000 and 2000; the run died after the 2500 evaluation
    other = tmp_path / "other.ckpt"
    other.write_bytes(ckpt.read_bytes())
    with pytest.raises(SpotError, match="belongs to another run"):
        sac.train_sac("Hopper-v5", CFG, 1, progress=False, checkpoint=other)  # seed 1, not 0
    resumed = sac.train_sac("Hopper-v5", CFG, 0, progress=False, checkpoint=ckpt, checkpoint_every=1000)
    assert resumed.resumed_from == (2000,)
    _assert_same_run(full, resumed)
    assert resumed.timing["checkpoint"] > 0 and resumed.timing["peak_rss_mb"] > 0


def test_checkpoint_interval_must_follow_evaluations():
    with pytest.raises(SpotError, match="checkpoint_every"):
        sac.train_sac("Hopper-v5", CFG, 0, progress=False, checkpoint_every=700)


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
    assert (fast.transitions, fast.stop, fast.medium_fraction) == (paper.transitions, paper.stop, paper.medium_fraction)
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
        locomotion.sac_cache_path(Path("c"), "walker2d", s, 0).stem.rsplit("__", 1)[1] for s in ("paper", "paper-fast")
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
