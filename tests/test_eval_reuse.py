"""Issue 40: evaluation envs kept across envs in a reused process (spot.evaluation's pool), and each
env's sizes read once per env (spot.envs._env_sizes).

A sweep process runs trials of several datasets one after another (lift-mh, can-ph, drawer-open,
...). The pool keeps the envs of every env it evaluated, within MAX_LIVE per family and POOL_MB in
all, so coming back to an env reuses its envs instead of building them again. The episodes must be
those of new envs: the reference here is an independent loop over newly built envs
(``spot.envs.make_env`` + ``reset(seed)`` + ``step``), written out in the test, not the pool's code.
"""

from __future__ import annotations

import numpy as np
import pytest

from spot import envs, evaluation


def _policy(act_dim: int, seed: int):
    """A deterministic policy that moves the system, each row's action from that row alone."""
    w = np.random.default_rng(seed).normal(size=(act_dim, 64))

    def policy(obs):
        flat = np.zeros((obs.shape[0], 64))
        flat[:, : min(64, obs.shape[1])] = obs[:, :64]
        return np.tanh(np.stack([w @ row for row in flat]))

    return policy


def _fresh_episodes(policy, name: str, episodes: int, seed: int, max_steps: int):
    """Returns and lengths of episodes ``seed + i``, each in a newly built env: the reference."""
    returns, lengths = [], []
    for i in range(episodes):
        env = envs.make_env(name, seed + i)
        try:
            obs, _ = env.reset(seed=seed + i)
            total, n = 0.0, 0
            for _ in range(max_steps):
                action = np.clip(
                    np.asarray(policy(np.asarray(obs, np.float32)[None]), np.float64)[0],
                    env.action_space.low,
                    env.action_space.high,
                )
                obs, r, terminated, truncated, _ = env.step(action)
                total, n = total + float(r), n + 1
                if terminated or truncated:
                    break
            returns.append(total)
            lengths.append(n)
        finally:
            env.close()
    return np.array(returns), np.array(lengths)


@pytest.fixture
def builds(monkeypatch):
    """The ``(name, seed)`` of every env the pool builds; the pool empty before and after."""
    built: list[tuple[str, int]] = []
    make = envs.make_env
    monkeypatch.setattr(evaluation, "make_env", lambda n, s: built.append((n, s)) or make(n, s))
    evaluation.clear_env_pool()
    yield built
    evaluation.clear_env_pool()


def test_coming_back_to_an_env_reuses_its_envs_and_gives_new_envs_episodes(builds):
    """lift-ph, drawer-open, hopper (gymnasium stepper), lift-mh (Lift's env again) and drawer-open
    again: each env is built once, and every episode equals the one of a newly built env."""
    pytest.importorskip("robosuite")
    steps = 25
    plan = [
        ("lift-ph", 7, 2, 3),
        ("drawer-open", 4, 2, 5),
        ("hopper-medium-replay", 3, 1, 7),
        ("lift-mh", 7, 2, 3),  # another dataset of Lift: the same envs
        ("drawer-open", 4, 1, 6),  # seed 6 was kept from the first drawer-open evaluation
    ]
    for name, act_dim, episodes, seed in plan:
        policy = _policy(act_dim, seed)
        got = evaluation.evaluate(policy, name, episodes, seed=seed, max_steps=steps, stepper="gymnasium")
        want_returns, want_lengths = _fresh_episodes(policy, name, episodes, seed, steps)
        np.testing.assert_array_equal(got["returns"], want_returns)
        np.testing.assert_array_equal(got["lengths"], want_lengths)
    assert builds == [
        ("lift-ph", 3),
        ("lift-ph", 4),
        ("drawer-open", 5),
        ("drawer-open", 6),
        ("hopper-medium-replay", 7),
    ]
    assert {k[1] for k in evaluation._POOL} == {"Lift", "drawer-open-v3", "Hopper-v5"}


def test_the_sequential_reference_reuses_kept_envs_too(builds):
    policy = _policy(4, 1)
    first = evaluation.evaluate_sequential(policy, "drawer-open", 2, seed=11, max_steps=20)
    evaluation.evaluate_sequential(_policy(3, 2), "hopper-medium-expert", 1, seed=0, max_steps=20)
    again = evaluation.evaluate_sequential(policy, "plate-slide", 1, seed=11, max_steps=20)  # another env, same seed
    batched = evaluation.evaluate(policy, "drawer-open", 2, seed=11, max_steps=20, stepper="gymnasium")
    assert builds == [("drawer-open", 11), ("drawer-open", 12), ("hopper-medium-expert", 0), ("plate-slide", 11)]
    np.testing.assert_array_equal(batched["returns"], first["returns"])
    np.testing.assert_array_equal(batched["lengths"], first["lengths"])
    want = _fresh_episodes(policy, "plate-slide", 1, 11, 20)
    np.testing.assert_array_equal(again["returns"], want[0])


def test_the_pool_stays_within_its_bounds_least_recently_used_closed_first(builds, monkeypatch):
    """MAX_LIVE of a family alive at once (kept ones included) and POOL_MB for all kept envs; the
    envs of the wave about to run are never closed."""
    closed: list[tuple] = []
    monkeypatch.setitem(evaluation.MAX_LIVE, "locomotion", 3)
    monkeypatch.setitem(evaluation.ENV_MB, "locomotion", 10)
    monkeypatch.setitem(evaluation.ENV_MB, "metaworld", 30)
    monkeypatch.setattr(evaluation, "POOL_MB", 60)

    def pool():
        return [(k[1], k[3]) for k in evaluation._POOL]

    def watch():
        for key, env in evaluation._POOL.items():
            if not getattr(env, "_watched", False):
                close = env.close
                env.close = lambda key=key, close=close: closed.append((key[1], key[3])) or close()
                env._watched = True

    hopper, walker = _policy(3, 0), _policy(6, 0)
    evaluation.evaluate(hopper, "hopper-medium-replay", 2, seed=0, max_steps=5, stepper="gymnasium")
    watch()
    evaluation.evaluate(walker, "walker2d-medium-replay", 1, seed=0, max_steps=5, stepper="gymnasium")
    watch()
    assert pool() == [("Hopper-v5", 0), ("Hopper-v5", 1), ("Walker2d-v5", 0)] and not closed
    evaluation.evaluate(walker, "walker2d-medium-expert", 2, seed=1, max_steps=5, stepper="gymnasium")  # 3 alive
    watch()
    assert closed == [("Hopper-v5", 0), ("Hopper-v5", 1)]
    assert pool() == [("Walker2d-v5", 0), ("Walker2d-v5", 1), ("Walker2d-v5", 2)]
    evaluation.evaluate(_policy(4, 0), "drawer-open", 1, seed=0, max_steps=5, stepper="gymnasium")  # 30 + 30 MB
    watch()
    assert pool() == [("Walker2d-v5", 0), ("Walker2d-v5", 1), ("Walker2d-v5", 2), ("drawer-open-v3", 0)]
    assert closed == [("Hopper-v5", 0), ("Hopper-v5", 1)]  # another family's envs are kept within POOL_MB
    monkeypatch.setattr(evaluation, "POOL_MB", 40)
    evaluation.evaluate(walker, "walker2d-medium-expert", 1, seed=1, max_steps=5, stepper="gymnasium")
    watch()
    assert closed[2:] == [("Walker2d-v5", 0), ("Walker2d-v5", 2)]  # 10 + 30 + 10 + 10 MB > 40: LRU first
    assert pool() == [("drawer-open-v3", 0), ("Walker2d-v5", 1)]
    evaluation.evaluate(walker, "walker2d-medium-expert", 2, seed=2, max_steps=5, stepper="gymnasium")
    assert closed[4:] == [("drawer-open-v3", 0)]  # the wave's 20 MB and Walker 1's 10 leave no room for 30
    assert pool() == [("Walker2d-v5", 1), ("Walker2d-v5", 2), ("Walker2d-v5", 3)]
    assert builds.count(("walker2d-medium-expert", 2)) == 2  # built again after it was closed


def test_env_sizes_are_read_once_per_env(monkeypatch):
    built: list[str] = []
    make = envs.make_env
    monkeypatch.setattr(envs, "make_env", lambda n, s: built.append(n) or make(n, s))
    monkeypatch.setattr(envs, "_SIZES", {})
    names = ["hopper-medium-replay", "hopper-medium-expert", "walker2d-medium-replay", "hopper-medium-replay-v2"]
    sizes = [envs._env_sizes(n) for n in names]
    assert built == ["hopper-medium-replay", "walker2d-medium-replay"]
    assert sizes[0] == sizes[1] == sizes[3] and sizes[0][:3] == ("Hopper-v5", 11, 3)
    assert sizes[2][:3] == ("Walker2d-v5", 17, 6)
    assert sizes[0][3:] == ((-1.0,) * 3, (1.0,) * 3)
