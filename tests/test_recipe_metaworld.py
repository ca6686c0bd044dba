"""The IPL Meta-World recipe, built at the tiny size in the real simulator (drawer-open-v3)."""

import numpy as np
import pytest

from spot import SpotError
from spot.recipes import metaworld


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return metaworld.build("drawer-open", "tiny", seed=0, cache_dir=tmp_path_factory.mktemp("c"), progress=False)


def test_shapes_and_layout(tiny):
    raw, card = tiny
    n = len(raw)
    assert raw.observations.shape == (n, 39) and raw.next_observations.shape == (n, 39)
    assert raw.actions.shape == (n, 4)
    assert np.abs(raw.actions).max() <= 1 - 1e-5 + 1e-7
    assert raw.metadata["episode_kind"] == [k for k in metaworld.KINDS for _ in range(2)]
    assert len(raw.metadata["episode_first_success"]) == card["episodes"]
    assert card["transitions"] == n and (card["obs_dim"], card["act_dim"]) == (39, 4)


def test_each_episode_ends_in_exactly_one_timeout(tiny):
    raw, card = tiny
    assert not raw.terminals.any()
    assert raw.timeouts[-1]
    assert raw.timeouts.sum() == card["episodes"] == 4 * metaworld.SIZES["tiny"]
    ends = np.flatnonzero(raw.timeouts)
    lengths = np.diff(np.concatenate([[-1], ends]))
    assert lengths.max() <= 500
    # Within an episode, next_observations[t] == observations[t + 1].
    inner = np.setdiff1d(np.arange(len(raw) - 1), ends)
    np.testing.assert_array_equal(raw.next_observations[inner], raw.observations[inner + 1])
    # An episode shorter than 500 steps stopped at (at least) 25 steps after its first success.
    for length, first in zip(lengths, raw.metadata["episode_first_success"], strict=True):
        assert length == 500 or (first >= 0 and length >= first + metaworld.SUCCESS_STEPS)


def test_success_rates_per_kind(tiny):
    raw, card = tiny
    rates = card["success_rate_per_kind"]
    ever = np.array(raw.metadata["episode_first_success"]) >= 0
    assert rates == {k: float(ever[2 * i : 2 * i + 2].mean()) for i, k in enumerate(metaworld.KINDS)}
    assert rates["expert"] >= 0.5
    assert rates["random"] == 0.0
    assert card["return_per_kind"]["expert"]["mean"] > card["return_per_kind"]["random"]["mean"]


def test_card_fields(tiny):
    _, card = tiny
    for key in (
        "recipe",
        "env",
        "episodes_per_kind",
        "transitions",
        "return",
        "success_rate_per_kind",
        "build_time_s",
        "versions",
        "seed",
        "epsilon",
    ):
        assert key in card
    assert card["env"] == "drawer-open-v3"
    assert card["episodes_per_kind"] == {k: 2 for k in metaworld.KINDS}
    assert len(card["cross_tasks"]) == 2 and "drawer-open-v3" not in card["cross_tasks"]
    assert card["versions"]["metaworld"] == "3.1.1"


def test_deterministic_for_a_seed(tiny, tmp_path):
    raw, card = tiny
    again, card2 = metaworld.build("drawer-open", "tiny", seed=0, cache_dir=tmp_path, progress=False)
    for key in ("observations", "actions", "rewards", "timeouts", "next_observations"):
        np.testing.assert_array_equal(getattr(raw, key), getattr(again, key))
    assert card["cross_tasks"] == card2["cross_tasks"]


def test_bad_name_and_size(tmp_path):
    with pytest.raises(SpotError, match="door-open"):
        metaworld.build("door-open", "tiny", 0, tmp_path)
    with pytest.raises(SpotError, match="huge"):
        metaworld.build("drawer-open", "huge", 0, tmp_path)
