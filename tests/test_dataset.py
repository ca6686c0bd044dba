"""The D4RL ``qlearning_dataset`` view and segment checks, against hand-built raw data."""

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
        observations=obs, actions=np.zeros((n, 1), np.float32), rewards=np.arange(n, dtype=np.float32),
        terminals=t, timeouts=to, next_observations=obs + 100 if next_obs else None, name="hand",
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
    base = dict(observations=np.zeros((4, 2), np.float32), actions=np.zeros((4, 1), np.float32),
                rewards=np.zeros(4, np.float32), terminals=np.zeros(4, bool), timeouts=np.zeros(4, bool))
    base.update(change)
    with pytest.raises(SpotError) as err:
        RawDataset(**base, name="bad")
    assert fragment in str(err.value) and "bad" in str(err.value)


def test_raw_from_episodes_layout():
    def ep(t, term):
        return dict(observations=np.zeros((t, 2)), actions=np.zeros((t, 1)), rewards=np.ones(t),
                    next_observations=np.ones((t, 2)), terminals=np.eye(t)[-1] * term,
                    timeouts=np.eye(t)[-1] * (1 - term))
    raw = raw_from_episodes([ep(3, 0), ep(2, 1)], "eps")
    assert len(raw) == 5 and raw.timeouts.tolist() == [0, 0, 1, 0, 0] and raw.terminals.tolist() == [0, 0, 0, 0, 1]
    ds = raw.qlearning()
    assert len(ds) == 3 and ds.episode_returns().tolist() == [2.0, 1.0]
