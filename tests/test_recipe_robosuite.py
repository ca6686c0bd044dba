"""The scripted robosuite recipe, built at the tiny size in the real simulator (Lift ph, Can mh)."""

import numpy as np
import pytest

from spot import SpotError
from spot.data import formats, registry
from spot.recipes import robosuite as recipe

pytestmark = pytest.mark.slow
pytest.importorskip("robosuite")


@pytest.fixture(scope="module")
def lift_ph(spot_dirs):
    """lift-ph tiny through the registry (3 demos, ~5 s), as a pipeline would build it."""
    path = registry.build("lift-ph", "tiny", 0, progress=False)
    return formats.read_d4rl_hdf5(path), registry.read_card(path)


@pytest.fixture(scope="module")
def can_mh(tmp_path_factory):
    """can-mh tiny (one demo per operator, ~20-30 s including the failed attempts)."""
    return recipe.build("can-mh", "tiny", seed=0, cache_dir=tmp_path_factory.mktemp("c"), progress=False)


def _episode_ends(raw):
    return np.flatnonzero(raw.terminals | raw.timeouts)


def _episode_starts(raw):
    return np.concatenate([[0], _episode_ends(raw)[:-1] + 1])


def _check_demos(raw, card, obs_dim, episodes):
    n = len(raw)
    assert raw.observations.shape == raw.next_observations.shape == (n, obs_dim)
    assert raw.actions.shape == (n, 7) and np.abs(raw.actions).max() <= 1.0
    assert (card["obs_dim"], card["act_dim"], card["transitions"]) == (obs_dim, 7, n)
    # Successful demos only, each ending at its first success: reward 1 and terminal there, else 0.
    assert not raw.timeouts.any()
    np.testing.assert_array_equal(raw.rewards, raw.terminals.astype(np.float32))
    ends = _episode_ends(raw)
    assert ends.size == card["episodes"] == episodes and ends[-1] == n - 1
    lengths = np.diff(np.concatenate([[-1], ends]))
    assert lengths.max() <= 500
    inner = np.setdiff1d(np.arange(n - 1), ends)
    np.testing.assert_array_equal(raw.next_observations[inner], raw.observations[inner + 1])
    return ends


def test_lift_ph_layout_and_success(lift_ph):
    raw, card = lift_ph
    ends = _check_demos(raw, card, 49, recipe.SIZES["tiny"]["ph"])
    # The robomimic layout of spot.envs: cube_pos first, table top at z = 0.8; every demo ends
    # with the cube lifted (robosuite Lift: cube above table + 0.04).
    assert np.all(raw.observations[_episode_starts(raw), 2] < 0.835)
    assert np.all(raw.next_observations[ends, 2] > 0.84)
    assert raw.metadata["episode_operator"] == ["ph"] * 3
    assert card["success_rate_per_operator"]["ph"] >= 0.75
    assert card["source"] == "recipe" and card["recipe"] == "scripted-robosuite"
    assert card["env"] == "Lift" and card["versions"]["robosuite"] == "1.5.1"


def test_registry_view_matches_the_evaluation_env(lift_ph, spot_dirs):
    from spot.envs import make_env

    ds, card = registry.load("lift-ph", "tiny", 0, progress=False)
    env = make_env("lift-ph", 0)
    try:
        assert ds.obs_dim == env.observation_space.shape[0] == 49
        assert ds.act_dim == env.action_space.shape[0] == 7
        # A fresh episode's first observation lies where the dataset's first observations do.
        first = env.reset(seed=5)[0]
        raw, _ = lift_ph
        spread = np.abs(raw.observations[_episode_starts(raw)] - first).max(axis=0)
        assert spread[38:45].max() < 0.1  # eef pos/quat, up to robosuite's initial joint noise
        assert spread[45:49].max() < 1e-3  # gripper qpos/qvel
    finally:
        env.close()
    # qlearning view: the last raw row (the last demo's success) is dropped, as in d4rl.
    assert ds.terminals.sum() == card["episodes"] - 1 and ds.rewards.sum() == card["episodes"] - 1


def test_lift_ph_deterministic(lift_ph, tmp_path):
    raw, _ = lift_ph
    again, _ = recipe.build("lift-ph", "tiny", seed=0, cache_dir=tmp_path, progress=False)
    for key in ("observations", "actions", "rewards", "terminals", "next_observations"):
        np.testing.assert_array_equal(getattr(raw, key), getattr(again, key))
    np.testing.assert_array_equal(raw.infos["dense_reward"], again.infos["dense_reward"])


def test_lift_ph_dense_reward_rises_to_the_success(lift_ph):
    raw, card = lift_ph
    assert card["recipe_version"] == recipe.RECIPE_VERSION == 2
    dense = raw.infos["dense_reward"]
    assert dense.shape == raw.rewards.shape and dense.dtype == np.float32
    ends = _episode_ends(raw)
    np.testing.assert_array_equal(dense[ends], 1.0)  # success: robosuite's reward_scale
    before = np.setdiff1d(np.arange(len(raw)), ends)
    # Lift's stages before success: reach in [0, 1] + grasp 0.25, over 2.25.
    assert dense[before].min() >= 0.0 and dense[before].max() <= 1.25 / 2.25
    for start, end in zip(_episode_starts(raw), ends, strict=True):
        episode = dense[start:end]  # up to the success step
        quarters = [q.mean() for q in np.array_split(episode, 4)]
        assert np.all(np.diff(quarters) > 0), quarters  # approach, descend, grasp, lift
        assert episode[0] < 0.05 and episode[-1] > 0.5  # far from the cube / grasping it
        assert np.mean(np.diff(episode) > -0.01) > 0.9  # almost never falls back
    np.testing.assert_array_equal(raw.rewards, raw.terminals)  # the sparse reward is unchanged


def test_robosuite_preset_labels_on_lift_ph_are_decided_and_follow_the_dense_return(lift_ph, spot_dirs):
    from spot import config
    from spot.data import labels

    ds, _ = registry.load("lift-ph", "tiny", 0, progress=False)
    lc = config.resolve({"data.name": "lift-ph", "budget": "tiny"}).labels
    assert (lc.score, lc.tie_threshold) == ("dense", 0.0)
    kw = dict(teacher=lc.teacher, tie_threshold=lc.tie_threshold, seed=lc.seed)
    sparse = labels.scripted_teacher(ds, 500, lc.segment_length, score="reward", **kw)
    dense = labels.scripted_teacher(ds, 500, lc.segment_length, score=lc.score, **kw)
    assert np.mean(sparse.labels == 0.5) > 0.8  # measured 0.94: no segment holds the success
    assert np.mean(dense.labels == 0.5) < 0.05  # measured 0.012: pairs of the same segment
    window = np.arange(lc.segment_length)
    s1, s2 = (ds.infos["dense_reward"][st[:, None] + window].sum(1) for st in (dense.starts_1, dense.starts_2))
    decided = dense.labels != 0.5
    np.testing.assert_array_equal(dense.labels[decided], (s1 < s2)[decided])
    # The preferred segment is the one further into its demo (closer to the success).
    starts, _ = ds.episode_bounds()
    offset = [st - starts[ds.episode_ids[st]] for st in (dense.starts_1, dense.starts_2)]
    later = (offset[1] > offset[0]).astype(np.float32)
    differ = decided & (offset[0] != offset[1])
    assert np.mean(dense.labels[differ] == later[differ]) > 0.9


def test_can_mh_operators_and_layout(can_mh):
    raw, card = can_mh
    ends = _check_demos(raw, card, 53, recipe.SIZES["tiny"]["mh"])
    names = [o.name for o in recipe.MH_OPERATORS]
    assert raw.metadata["episode_operator"] == names
    assert raw.metadata["episode_skill"] == ["better"] * 2 + ["okay"] * 2 + ["worse"] * 2
    assert card["episodes_per_operator"] == dict.fromkeys(names, 1)
    rates = card["success_rate_per_operator"]
    assert all(0.0 < rates[n] <= 1.0 for n in names)
    assert card["success_rate_per_skill"].keys() == {"better", "okay", "worse"}
    # Every demo ends with the can (Can_pos = obs[7:10]) in its quadrant of the target bin.
    can_end = raw.next_observations[ends, 7:10]
    assert np.all((can_end[:, 0] > 0.1) & (can_end[:, 1] > 0.28) & (can_end[:, 2] < 0.9))
    assert card["env"] == "PickPlaceCan"


def test_bad_name_and_size(tmp_path):
    with pytest.raises(SpotError, match="square-ph"):
        recipe.build("square-ph", "tiny", 0, tmp_path)
    with pytest.raises(SpotError, match="huge"):
        recipe.build("lift-ph", "huge", 0, tmp_path)
    assert registry.entry("can-mh").family == "robosuite"
