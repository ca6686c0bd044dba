"""The D4RL ``qlearning_dataset`` view and segment checks, against hand-built raw data."""

import dataclasses
import json

import numpy as np
import pytest

from spot import SpotError
from spot.data.dataset import RawDataset, raw_from_episodes


def _raw(n=10, timeouts=(), terminals=(), next_obs=False):
    obs = np.arange(n, dtype=np.float32)[:, None].repeat(2, axis=1)
    t = np.zeros(n, bool)
    t[list(terminals)] = True
    to = np.zeros(n, bool)
    to[list(timeouts)] = True
    return RawDataset(
        observations=obs,
        actions=np.zeros((n, 1), np.float32),
        rewards=np.arange(n, dtype=np.float32),
        terminals=t,
        timeouts=to,
        next_observations=obs + 100 if next_obs else None,
        name="hand",
    )


def test_qlearning_view_drops_timeouts_and_last_row():
    # episodes: rows 0-3 (timeout at 3), rows 4-6 (terminal at 6), rows 7-9
    ds = _raw(10, timeouts=[3], terminals=[6]).qlearning()
    np.testing.assert_array_equal(ds.raw_index, [0, 1, 2, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(ds.rewards, [0, 1, 2, 4, 5, 6, 7, 8])
    # without stored next_observations: observations[i + 1], as d4rl does
    np.testing.assert_array_equal(ds.next_observations[:, 0], [1, 2, 3, 5, 6, 7, 8, 9])
    np.testing.assert_array_equal(ds.terminals, [0, 0, 0, 0, 0, 1, 0, 0])
    np.testing.assert_array_equal(ds.episode_ids, [0, 0, 0, 1, 1, 1, 2, 2])
    starts, ends = ds.episode_bounds()
    np.testing.assert_array_equal(starts, [0, 3, 6])
    np.testing.assert_array_equal(ends, [3, 6, 8])
    np.testing.assert_array_equal(ds.episode_returns(), [3, 15, 15])


def test_fingerprint_covers_episode_ends_and_next_observations():
    base = _raw(10, timeouts=[3], terminals=[6]).qlearning()
    fp = base.fingerprint()
    assert len(fp) == 64 and _raw(10, timeouts=[3], terminals=[6]).qlearning().fingerprint() == fp
    assert dataclasses.replace(_raw(10, timeouts=[3], terminals=[6]), name="other").qlearning().fingerprint() == fp
    # only the terminal moves (row 6 -> 5): same rows, observations and rewards; other terminals and episodes
    moved = _raw(10, timeouts=[3], terminals=[5]).qlearning()
    np.testing.assert_array_equal(moved.observations, base.observations)
    np.testing.assert_array_equal(moved.rewards, base.rewards)
    assert moved.fingerprint() != fp
    # only the episode ids change (a terminal flag kept, the boundary after row 8 added by hand)
    ids = base.episode_ids.copy()
    ids[-1] += 1
    assert base.replace(episode_ids=ids).fingerprint() != fp
    # only the next observations change (stored ones instead of observations[i + 1])
    stored = _raw(10, timeouts=[3], terminals=[6], next_obs=True).qlearning()
    np.testing.assert_array_equal(stored.observations, base.observations)
    assert stored.fingerprint() != fp
    # an infos array, and a dtype change with the same values, count too
    assert base.replace(infos={"dense_reward": np.zeros(len(base), np.float32)}).fingerprint() != fp
    assert base.replace(rewards=base.rewards.astype(np.float64)).fingerprint() != fp


def test_transitions_view():
    ds = _raw(10, timeouts=[3], terminals=[6]).qlearning()
    t = ds.transitions()
    assert all(np.asarray(x).dtype == np.float32 for x in t)
    np.testing.assert_array_equal(t.obs[:, 0], [0, 1, 2, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(t.next_obs[:, 0], [1, 2, 3, 5, 6, 7, 8, 9])
    np.testing.assert_array_equal(t.rew, [0, 1, 2, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(t.mask, [1, 1, 1, 1, 1, 0, 1, 1])  # 1 - terminal: row 6 terminates
    relabelled = ds.transitions(np.full(8, 0.5))
    np.testing.assert_array_equal(relabelled.rew, np.full(8, 0.5, np.float32))
    with pytest.raises(SpotError, match=r"rewards have shape \(7,\); expected \(8,\)"):
        ds.transitions(np.zeros(7))


def test_stored_next_observations_are_used():
    ds = _raw(5, next_obs=True).qlearning()
    np.testing.assert_array_equal(ds.next_observations[:, 0], [100, 101, 102, 103])


def test_segments_past_end_or_across_episodes_are_refused():
    ds = _raw(10, timeouts=[3], terminals=[6]).qlearning()
    idx = ds.segment_index(np.array([0, 3]), 3, allow_cross_episode=False)
    np.testing.assert_array_equal(idx, [[0, 1, 2], [3, 4, 5]])
    with pytest.raises(SpotError, match=r"segment 1 starts at index 6 with length 3, past the end.*8 transitions"):
        ds.segment_index(np.array([0, 6]), 3)
    with pytest.raises(SpotError, match=r"segment 0 \(start 1, length 3\) crosses an episode end"):
        ds.segment_index(np.array([1]), 3, allow_cross_episode=False)
    ds.segment_index(np.array([1]), 3, allow_cross_episode=True)


@pytest.mark.parametrize(
    "change, fragment",
    [
        (dict(rewards=np.array([0, np.nan, 0, 0], np.float32)), "'rewards' contains NaN or inf"),
        (dict(observations=np.full((4, 2), np.inf, np.float32)), "'observations' contains NaN or inf"),
        (dict(actions=np.zeros((3, 1), np.float32)), "'actions' has 3 rows but 'observations' has 4"),
        (dict(rewards=np.zeros((4, 1), np.float32)), "'rewards' has shape (4, 1); expected rank 1"),
    ],
)
def test_bad_arrays_are_named(change, fragment):
    base = dict(
        observations=np.zeros((4, 2), np.float32),
        actions=np.zeros((4, 1), np.float32),
        rewards=np.zeros(4, np.float32),
        terminals=np.zeros(4, bool),
        timeouts=np.zeros(4, bool),
    )
    base.update(change)
    with pytest.raises(SpotError) as err:
        RawDataset(**base, name="bad")
    assert fragment in str(err.value) and "bad" in str(err.value)


def test_raw_from_episodes_layout():
    def ep(t, term):
        return dict(
            observations=np.zeros((t, 2)),
            actions=np.zeros((t, 1)),
            rewards=np.ones(t),
            next_observations=np.ones((t, 2)),
            terminals=np.eye(t)[-1] * term,
            timeouts=np.eye(t)[-1] * (1 - term),
        )

    raw = raw_from_episodes([ep(3, 0), ep(2, 1)], "eps")
    assert len(raw) == 5 and raw.timeouts.tolist() == [0, 0, 1, 0, 0] and raw.terminals.tolist() == [0, 0, 0, 0, 1]
    ds = raw.qlearning()
    assert len(ds) == 3 and ds.episode_returns().tolist() == [2.0, 1.0]


def test_infos_ride_along_episodes_and_the_qlearning_view():
    def ep(t, term, base):
        return dict(
            observations=np.zeros((t, 2)),
            actions=np.zeros((t, 1)),
            rewards=np.zeros(t),
            next_observations=np.ones((t, 2)),
            terminals=np.eye(t)[-1] * term,
            timeouts=np.eye(t)[-1] * (1 - term),
            infos={"dense_reward": base + np.arange(t)},
        )

    raw = raw_from_episodes([ep(3, 0, 10.0), ep(3, 1, 20.0)], "eps")
    np.testing.assert_array_equal(raw.infos["dense_reward"], [10, 11, 12, 20, 21, 22])
    ds = raw.qlearning()  # row 2 (timeout) and row 5 (last) dropped
    np.testing.assert_array_equal(ds.infos["dense_reward"], [10, 11, 20, 21])
    assert ds.replace(name="x").infos.keys() == {"dense_reward"}
    assert _raw().qlearning().infos == {}
    with pytest.raises(SpotError, match=r"episode 1 has infos \[\]; expected \['dense_reward'\]"):
        raw_from_episodes([ep(3, 0, 0.0), {k: v for k, v in ep(2, 1, 0.0).items() if k != "infos"}], "eps")
    with pytest.raises(SpotError, match=r"hand: 'infos/dense_reward' has shape \(9,\); expected 10 rows"):
        dataclasses.replace(_raw(), infos={"dense_reward": np.zeros(9)})


# --------------------------------------------------------------------------- registry cache
def test_registry_rebuilds_a_build_of_another_recipe_version(spot_dirs, monkeypatch):
    """A cached build whose card has another RECIPE_VERSION (or none: built before the recipe
    had one) is stale and rebuilt; a current one is reused. Fake recipe, no simulator."""
    import sys
    import types

    from spot.data import formats, registry

    calls = []

    def build(name, size, seed, cache_dir, progress=True):
        calls.append(name)
        return _raw(), {"recipe": "fake"}

    fake = types.ModuleType("spot.recipes.fake")
    fake.RECIPE_VERSION, fake.build = 3, build
    monkeypatch.setitem(sys.modules, "spot.recipes.fake", fake)
    monkeypatch.setitem(registry.REGISTRY, "fake-task", registry.Entry("fake-task", "test", "fake", "fake"))
    path = registry.build("fake-task", "tiny", 0, progress=False)
    assert registry.read_card(path)["recipe_version"] == 3 and len(calls) == 1
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 1  # current: reused
    # An old build: its card has no recipe_version.
    card = registry.read_card(path)
    del card["recipe_version"]
    registry.card_path(path).write_text(json.dumps(card))
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 2 and registry.read_card(path)["recipe_version"] == 3
    assert formats.read_d4rl_hdf5(path).metadata["spot_card"]["recipe_version"] == 3
    fake.RECIPE_VERSION = 4  # the recipe changed: rebuilt once
    registry.build("fake-task", "tiny", 0, progress=False)
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 3
    del fake.RECIPE_VERSION  # recipes without a version are never stale
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 3
    # a recipe whose versions differ per dataset and size: recipe_version(name, size) wins over RECIPE_VERSION
    fake.RECIPE_VERSION, fake.recipe_version = 4, lambda name, size: f"4+{size}"
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 4 and registry.read_card(path)["recipe_version"] == "4+tiny"
    registry.build("fake-task", "tiny", 0, progress=False)
    assert len(calls) == 4


def test_locomotion_versions_name_the_stop_rule_where_it_is_not_the_first_one():
    # the rule hopper's paper-fast data are built under (stochastic returns, two evaluations in a row) is in
    # their version, so a file built under the one-deterministic-evaluation rule is rebuilt, not reused
    from spot.recipes import locomotion

    v = locomotion.RECIPE_VERSION
    assert locomotion.recipe_version("hopper-medium-replay", "paper-fast") == f"{v}+stop-stochastic-2"
    assert locomotion.recipe_version("hopper-expert", "paper") == v  # the rule of every built Hopper file
    assert locomotion.recipe_version("walker2d-medium", "paper-fast") == v
    assert locomotion.recipe_version("hopper-medium", "tiny") == v  # no stop rule: a fixed length
