"""Batched evaluation (issue 40): the episodes of a run, and those of the seeds of a vmapped trial,
step together with one policy call per env step, and every episode's return and length equal, to
the last digit, what it gets when the episodes run one after another (spot.evaluation.evaluate_sequential
with the plain ``iql.act`` on one observation at a time)."""

import jax
import numpy as np
import pytest

from spot import config, evaluation
from spot.policy import iql
from spot.run import policy_stages

HOPPER = "hopper-medium-replay"  # Hopper-v5, 11-D observations, 3-D actions
DRAWER = "drawer-open"  # Meta-World, 39-D observations, 4-D actions: the cheap env of test_envs
SIZES = {HOPPER: (11, 3), DRAWER: (39, 4)}
MAX_STEPS = {HOPPER: 0, DRAWER: 40}  # Hopper to its own horizon (a random-init policy falls early)


@pytest.fixture(scope="module")
def iql_cfg():
    return config.load(None, []).iql  # the default actor: 256-256 MLP, Gaussian mean


def _actors(name, cfg, seeds):
    """Random-init IQL actors, one per seed, stacked on a leading axis (as a vmapped trial's), the
    output layer scaled by 0.03: small actions, so Hopper stands for about 80-110 steps and the
    episodes end at different steps (at scale 1 every episode falls at step 15 or 16)."""
    obs_dim, act_dim = SIZES[name]
    keys = jax.numpy.stack([jax.random.key(s) for s in seeds])
    params = iql.init_state(keys, obs_dim, act_dim, cfg).actor.params
    head = jax.tree.map(lambda a: a * 0.03, params["params"]["Dense_0"])
    return {"params": {**params["params"], "Dense_0": head}}


def _one(params, s):
    return jax.tree.map(lambda a: a[s], params)


def _sequential(params, cfg, name, episodes, seed):
    """The reference: one episode after another, the plain actor on one observation per step."""
    return evaluation.evaluate_sequential(
        lambda o: np.asarray(iql.act(params, o, cfg)), name, episodes, seed, max_steps=MAX_STEPS[name]
    )


def _assert_same(batched, sequential):
    assert batched["returns"].tolist() == sequential["returns"].tolist()  # exactly, every digit
    assert batched["lengths"].tolist() == sequential["lengths"].tolist()
    for key in ("score_mean", "score_std", "return_mean", "return_std", "episode_length_mean"):
        assert batched[key] == sequential[key], key


@pytest.mark.parametrize("name", [HOPPER, DRAWER])
@pytest.mark.parametrize("episodes", [1, 3, 10])
def test_a_runs_batched_episodes_equal_its_sequential_ones(name, episodes, iql_cfg):
    params = _one(_actors(name, iql_cfg, [0]), 0)
    batched = evaluation.evaluate(
        policy_stages.eval_policy(params, iql_cfg), name, episodes, 100, max_steps=MAX_STEPS[name]
    )
    sequential = _sequential(params, iql_cfg, name, episodes, 100)
    _assert_same(batched, sequential)
    assert len(batched["returns"]) == episodes
    if name == HOPPER and episodes == 10:
        # not a vacuous comparison: episodes end at different steps, all before the horizon, so
        # the batch keeps running with ended episodes masked
        lengths = batched["lengths"]
        assert len(set(lengths.tolist())) > 5 and lengths.min() > 50 and lengths.max() < 1000


def test_a_vmapped_trials_seeds_evaluated_together_equal_each_seed_alone(iql_cfg, monkeypatch):
    """Several seeds' params (stacked, as train_iql holds them), each with its own evaluation seed;
    two members share a seed (Oracle and PT of seed 0 in one program): their envs are separate."""
    seeds = [0, 1, 2, 3]
    eval_seeds = [10_000, 20_000, 10_000, 30_000]
    params = _actors(HOPPER, iql_cfg, seeds)
    policy = policy_stages.eval_policy(params, iql_cfg, runs=True)
    together = evaluation.evaluate_runs(policy, HOPPER, 10, eval_seeds)
    assert len(together) == len(seeds)
    for s, res in enumerate(together):
        _assert_same(res, _sequential(_one(params, s), iql_cfg, HOPPER, 10, eval_seeds[s]))
    assert together[0]["returns"].tolist() != together[2]["returns"].tolist()  # same envs, other policy
    # waves: at most 5 envs alive, so 1 episode per run at a time; the same numbers
    monkeypatch.setitem(evaluation.MAX_LIVE, "locomotion", 5)
    waves = evaluation.evaluate_runs(policy, HOPPER, 3, eval_seeds, stepper="gymnasium")  # kept gymnasium envs
    for s, res in enumerate(waves):
        assert res["returns"].tolist() == together[s]["returns"][:3].tolist()
        assert res["lengths"].tolist() == together[s]["lengths"][:3].tolist()
    assert sum(k[0] == "locomotion" for k in evaluation._POOL) <= 5  # the family's; other envs' stay kept


def test_one_policy_call_per_env_step_for_all_runs_and_episodes():
    """The batch keeps its shape while episodes end (one compiled program); the policy is called
    once per step of the longest episode, not once per episode step."""
    shapes = []

    def policy(obs):
        shapes.append(obs.shape)
        # an episode's action from its own observation only: push forward until the torso tilts
        return np.where(obs[..., 1:2] > 0, -0.5, 0.5) * np.ones(3)

    res = evaluation.evaluate_runs(policy, HOPPER, 4, [7, 8], max_steps=300)
    lengths = np.array([r["lengths"] for r in res])
    assert len(shapes) == lengths.max() and set(shapes) == {(2, 4, 11)}
    assert lengths.sum() > len(shapes)  # many env steps per policy call
    for s, seed in enumerate([7, 8]):
        alone = evaluation.evaluate_sequential(policy, HOPPER, 4, seed, max_steps=300)
        assert alone["returns"].tolist() == res[s]["returns"].tolist()


def test_evaluate_runs_checks_its_arguments():
    def zeros(obs):
        return np.zeros((*obs.shape[:-1], 3))

    with pytest.raises(evaluation.SpotError, match="at least one run"):
        evaluation.evaluate_runs(zeros, HOPPER, 1, [])
    with pytest.raises(evaluation.SpotError, match="episodes must be >= 1"):
        evaluation.evaluate_runs(zeros, HOPPER, 0, [0])
    with pytest.raises(evaluation.SpotError, match="max_steps must be >= 0"):
        evaluation.evaluate_sequential(zeros, HOPPER, 1, 0, max_steps=-1)
    with pytest.raises(evaluation.SpotError, match=r"shape \(1, 2, 2\)"):
        evaluation.evaluate_runs(lambda obs: np.zeros((*obs.shape[:-1], 2)), HOPPER, 2, [0])


def test_spot_bench_eval_prints_both_rates_and_their_ratio(capsys):
    from spot import cli

    assert cli.main(["bench", "eval", "--small", "--episodes", "2", "--seeds", "2"]) in (0, None)
    out = capsys.readouterr().out
    assert "2 run(s) x 2 episodes" in out
    rates = {}
    for line in out.splitlines():
        key, _, value = line.strip().partition(" ")
        if key.endswith("_steps_s") or key.startswith("ratio") or key == "env_steps":
            rates[key] = float(value.replace(",", ""))
    assert set(rates) >= {"batched_steps_s", "sequential_steps_s", "ratio", "env_steps"}
    assert rates["env_steps"] == 2 * 2 * 30  # --small cuts episodes at 30 steps
    assert rates["ratio"] == pytest.approx(rates["batched_steps_s"] / rates["sequential_steps_s"], rel=1e-3)
    assert "same_episodes      True" in out
    assert cli.main(["bench", "iql", "--episodes", "3"]) == 2
    assert "--episodes goes with 'spot bench eval'" in capsys.readouterr().err
