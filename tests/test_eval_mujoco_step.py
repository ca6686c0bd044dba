"""MuJoCo stepped directly for evaluation (issue 40, item 2; ``eval.stepper: mujoco``,
spot.mujoco_step): every episode equals gymnasium's env's episode with the same seed and policy,
return and length to the last digit, and envs without a direct stepper fall back to gymnasium.

The reference is gymnasium's own env (``spot.envs.make_env`` / ``spot.evaluation.evaluate_sequential``),
not this module's formulas: the checks hold only if the stepper reproduces gymnasium's reset noise,
physics, reward, health check and observation bit for bit."""

import json
import re
import threading

import jax
import numpy as np
import pytest

from spot import SpotError, config, evaluation, mujoco_step
from spot.envs import make_env
from spot.policy import iql
from spot.run import policy_stages

# dataset name -> (obs dim, act dim, evaluation horizon here): HalfCheetah never falls, so its
# episodes are cut at 300 steps; Hopper and Walker2d run to their own end (a fall).
LOCOMOTION = {
    "hopper-medium-replay": (11, 3, 0),
    "walker2d-medium-replay": (17, 6, 0),
    "halfcheetah-medium": (17, 6, 300),
}


@pytest.fixture(scope="module")
def iql_cfg():
    return config.load(None, []).iql  # the default actor: 256-256 MLP, Gaussian mean


def _actor(name, cfg, seed, head_scale):
    """A random-init IQL actor, its output layer scaled by ``head_scale`` (small actions: the
    walkers stand for tens to a hundred steps, and episodes end at different steps)."""
    obs_dim, act_dim, _ = LOCOMOTION[name]
    params = iql.init_state(jax.random.key(seed), obs_dim, act_dim, cfg).actor.params
    head = jax.tree.map(lambda a: a * head_scale, params["params"]["Dense_0"])
    return {"params": {**params["params"], "Dense_0": head}}


@pytest.mark.parametrize("name", list(LOCOMOTION))
def test_batched_mujoco_episodes_equal_gymnasiums_one_after_another(name, iql_cfg):
    """10 episodes of a fixed random-weights policy: the direct stepper (all episodes together)
    against gymnasium's envs one episode at a time, and against gymnasium's envs batched."""
    horizon = LOCOMOTION[name][2]
    params = _actor(name, iql_cfg, 0, 0.03)
    policy = policy_stages.eval_policy(params, iql_cfg)  # each row's action computed alone
    direct = evaluation.evaluate(policy, name, 10, 10_000, max_steps=horizon, stepper="mujoco")
    gym_batched = evaluation.evaluate(policy, name, 10, 10_000, max_steps=horizon, stepper="gymnasium")
    sequential = evaluation.evaluate_sequential(policy, name, 10, 10_000, max_steps=horizon)
    for other in (sequential, gym_batched):
        assert direct["returns"].tolist() == other["returns"].tolist()  # exactly: every digit
        assert direct["lengths"].tolist() == other["lengths"].tolist()
        for key in ("score_mean", "score_std", "return_mean", "return_std", "episode_length_mean"):
            assert direct[key] == other[key], key
    lengths = direct["lengths"]
    if horizon:  # never terminates: every episode runs to the cut
        assert lengths.tolist() == [horizon] * 10
    else:  # not vacuous: episodes fall at different steps, the batch runs on with ended ones masked
        assert len(set(lengths.tolist())) >= 3 and lengths.min() > 10 and lengths.max() < 1000
    assert len(set(direct["returns"].tolist())) == 10


@pytest.mark.parametrize("name", list(LOCOMOTION))
def test_reset_and_each_step_equal_gymnasiums(name):
    """Reset observations of several seeds, then every step's observation, reward and termination
    under random actions, against a gymnasium env per seed; Hopper and Walker2d until they fall
    (the healthy reward is not paid on the terminating step)."""
    seeds = [0, 5, 123]
    envs = [make_env(name, s) for s in seeds]
    batch = mujoco_step.LocomotionBatch(name, len(seeds))
    obs = batch.reset(seeds)
    for j, (env, seed) in enumerate(zip(envs, seeds, strict=True)):
        assert obs[j].tolist() == env.reset(seed=seed)[0].tolist()
    rng = np.random.default_rng(0)
    running = np.ones(len(seeds), dtype=bool)
    terminations = 0
    for _ in range(400):
        idx = np.flatnonzero(running)
        if not len(idx):
            break
        actions = np.clip(rng.normal(0.0, 0.7, (len(idx), batch.action_space.shape[0])), -1.0, 1.0)
        o, rewards, terminated = batch.step(idx, actions)
        for k, j in enumerate(idx):
            g_obs, g_reward, g_terminated, _, _ = envs[j].step(actions[k])
            assert o[k].tolist() == g_obs.tolist()
            assert rewards[k] == g_reward
            assert bool(terminated[k]) == g_terminated
            terminations += bool(g_terminated)
        running[idx] = ~terminated
    if name.startswith("halfcheetah"):
        assert running.all()
    else:
        assert terminations == len(seeds)  # every episode's terminating step was compared
    for env in envs:
        env.close()


def test_physics_on_several_threads_gives_the_same_states():
    """Episodes stepped on 3 threads (each its own MjData) end where one thread takes them."""
    seeds = list(range(9))
    one = mujoco_step.LocomotionBatch("walker2d-medium", 9, threads=1)
    one.reset(seeds)
    one_states = []
    rng = np.random.default_rng(1)
    actions = [np.clip(rng.normal(0.0, 0.5, (9, 6)), -1.0, 1.0) for _ in range(30)]
    for a in actions:
        one_states.append([x.copy() for x in one.step(np.arange(9), a)])
    threaded = mujoco_step.LocomotionBatch("walker2d-medium", 9, threads=3)
    threaded.datas = [mujoco_step.mujoco.MjData(threaded.task.model) for _ in range(9)]  # not the kept ones
    threaded.reset(seeds)
    names, physics = set(), threaded._physics

    def recorded(idx, actions):
        names.add(threading.current_thread().name.split("_")[0])
        physics(idx, actions)

    threaded._physics = recorded
    for a, want in zip(actions, one_states, strict=True):
        got = threaded.step(np.arange(9), a)
        for g, w in zip(got, want, strict=True):
            assert g.tolist() == w.tolist()
    assert names == {"MainThread", "spot-mujoco"}  # the work was shared out


def test_kept_mujoco_data_give_the_episodes_of_new_ones(iql_cfg):
    """The stepper keeps its MjData for the next evaluation (spot.mujoco_step._datas): an
    evaluation after others (other policy, seeds and env) equals the first one."""
    name = "hopper-medium-replay"
    policy = policy_stages.eval_policy(_actor(name, iql_cfg, 1, 0.03), iql_cfg)
    first = evaluation.evaluate(policy, name, 3, 40, stepper="mujoco")
    other = policy_stages.eval_policy(_actor(name, iql_cfg, 2, 0.1), iql_cfg)
    evaluation.evaluate(other, name, 5, 0, stepper="mujoco")  # the kept data move on
    walker = policy_stages.eval_policy(_actor("walker2d-medium-replay", iql_cfg, 2, 0.03), iql_cfg)
    evaluation.evaluate(walker, "walker2d-medium-replay", 2, 0, stepper="mujoco")  # another model
    evaluation.evaluate(other, name, 4, 9, stepper="mujoco")
    again = evaluation.evaluate(policy, name, 3, 40, stepper="mujoco")
    assert again["returns"].tolist() == first["returns"].tolist()
    assert again["lengths"].tolist() == first["lengths"].tolist()


def test_other_envs_fall_back_to_gymnasium():
    assert [evaluation.stepper_used(n, "mujoco") for n in LOCOMOTION] == ["mujoco"] * 3
    assert evaluation.stepper_used("hopper-medium-replay", "gymnasium") == "gymnasium"
    assert evaluation.stepper_used("drawer-open", "mujoco") == "gymnasium"
    assert evaluation.stepper_used("lift-ph", "mujoco") == "gymnasium"
    assert not mujoco_step.supports("drawer-open")

    def policy(obs):  # each row's action from that row alone
        return np.tanh(obs[..., :4] * 3.0)

    fallback = evaluation.evaluate(policy, "drawer-open", 2, 3, max_steps=20, stepper="mujoco")
    gym = evaluation.evaluate(policy, "drawer-open", 2, 3, max_steps=20, stepper="gymnasium")
    assert fallback["returns"].tolist() == gym["returns"].tolist()
    evaluation.clear_env_pool()


def test_the_stepper_is_a_checked_config_key():
    assert config.load(None, []).eval.stepper == "mujoco"
    assert config.load(None, ["eval.stepper=gymnasium"]).eval.stepper == "gymnasium"
    with pytest.raises(SpotError, match="eval.stepper"):
        config.load(None, ["eval.stepper=physx"])
    with pytest.raises(SpotError, match="eval.stepper: expected one of mujoco, gymnasium, got 'physx'"):
        evaluation.evaluate(lambda o: np.zeros((o.shape[0], 3)), "hopper-medium", 1, 0, stepper="physx")


@pytest.mark.parametrize("stepper", ["mujoco", "gymnasium"])
def test_a_runs_evaluation_uses_its_configs_stepper(stepper, monkeypatch):
    """The policy stage's evaluation (spot.run.policy_stages) passes ``eval.stepper`` on."""
    from types import SimpleNamespace

    cfg = config.load(None, ["budget=tiny", f"eval.stepper={stepper}"])
    seen = []

    def fake_evaluate(policy_fn, name, episodes, seed, max_steps=0, stepper="unset"):
        seen.append(stepper)
        return {"score_mean": 1.0, "score_std": 0.0, "return_mean": 2.0, "episode_length_mean": 3.0}

    monkeypatch.setattr(evaluation, "evaluate", fake_evaluate)
    ctx = SimpleNamespace(cfg=cfg, env_name="hopper-medium-replay", log=lambda m, step: None, on_eval=None)
    ctx.progress = False
    policy_stages._evaluate_fn(ctx)(None, 0)
    assert seen == [stepper]


def test_spot_bench_eval_names_its_stepper(capsys):
    from spot import cli

    assert cli.main(["bench", "eval", "--small", "--episodes", "2"]) in (0, None)
    out = capsys.readouterr().out
    assert re.search(r"stepper +mujoco \(batched, physics on up to \d+ thread\(s\); sequential: gymnasium\)", out)
    assert "batched_gymnasium_steps_s" in out and "same_episodes      True" in out
    assert cli.main(["bench", "eval", "--small", "--episodes", "2", "--stepper", "gymnasium"]) in (0, None)
    out = capsys.readouterr().out
    assert "stepper            gymnasium" in out and "batched_gymnasium_steps_s" not in out
    assert cli.main(["bench", "iql", "--stepper", "mujoco"]) == 2
    assert "--stepper goes with 'spot bench eval'" in capsys.readouterr().err


def test_a_runs_scores_are_the_same_with_either_stepper(tmp_path, spot_dirs, monkeypatch):
    """A tiny Oracle run on Hopper, evaluated to the env's own horizon: every logged evaluation
    (eval/score, eval/return, eval/length at each evaluation step) and the final score are the same,
    to the last digit, with ``eval.stepper`` mujoco and gymnasium."""
    from spot.data import registry
    from spot.run import pipeline

    registry.build("hopper-medium-expert", "tiny", 0, progress=False)
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    logged = {}
    for stepper in ("mujoco", "gymnasium"):
        cfg = config.load(
            None,
            [
                "method=oracle",
                "budget=tiny",
                "data.name=hopper-medium-expert",
                "iql.steps=200",
                "eval.every=100",
                "eval.episodes=3",
                "eval.max_steps=0",
                f"eval.stepper={stepper}",
                f"tracking.record={tmp_path / stepper}",
            ],
        )
        out = pipeline.run(cfg, progress=False)
        (metrics,) = (tmp_path / stepper).glob("*/metrics.jsonl")  # the run's recorded metric history
        history = [json.loads(line) for line in metrics.read_text().splitlines()]
        evals = sorted((m["key"], m["step"], m["value"]) for m in history if m["key"].startswith("eval/"))
        logged[stepper] = (evals, {k: v for k, v in out.items() if k.startswith("eval/")})
    assert logged["mujoco"] == logged["gymnasium"]
    evals, final = logged["mujoco"]
    assert {(k, step) for k, step, _ in evals} >= {(f"eval/{k}", s) for k in ("score", "return") for s in (0, 100, 200)}
    assert "eval/score_final" in final
