"""SAC's tanh-Gaussian log-probability, and tiny D4RL-style locomotion builds in real Hopper-v5."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from spot import SpotError
from spot.recipes import locomotion, locomotion_sac, sac, sac_train

RAW_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


# ------------------------------------------------------------------------------ tanh-Gaussian
def test_tanh_gaussian_log_prob_matches_scipy():
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(5, 3))
    log_std = rng.uniform(-2.0, 1.0, size=(5, 3))
    pre_tanh = rng.normal(scale=3.0, size=(5, 3))
    pre_tanh[0] = [8.0, -9.0, 0.0]  # saturated tanh: the naive log(1 - tanh^2) loses precision
    expected = (
        stats.norm.logpdf(pre_tanh, mean, np.exp(log_std)) - np.log(4.0) + 2.0 * np.logaddexp(pre_tanh, -pre_tanh)
    ).sum(-1)
    # ^ log(1 - tanh(u)^2) = log 4 - 2 log(e^u + e^-u), in float64
    naive = (
        stats.norm.logpdf(pre_tanh[1:], mean[1:], np.exp(log_std[1:])) - np.log(1.0 - np.tanh(pre_tanh[1:]) ** 2)
    ).sum(-1)
    np.testing.assert_allclose(expected[1:], naive, rtol=1e-10)
    got = sac.tanh_gaussian_log_prob(
        jnp.asarray(pre_tanh, jnp.float32), jnp.asarray(mean, jnp.float32), jnp.asarray(log_std, jnp.float32)
    )
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-5, atol=1e-4)


def test_tanh_gaussian_density_integrates_to_one():
    # p(a) = exp(log_prob(atanh(a))) is a density on (-1, 1).
    a = np.linspace(-1.0, 1.0, 400_001)[1:-1]
    u = jnp.asarray(np.arctanh(a)[:, None], jnp.float32)
    logp = sac.tanh_gaussian_log_prob(u, jnp.full_like(u, 0.4), jnp.full_like(u, -0.3))
    assert np.trapezoid(np.exp(np.asarray(logp, np.float64)), a) == pytest.approx(1.0, abs=1e-3)


def test_sample_tanh_gaussian_returns_its_log_prob():
    mean, log_std = jnp.array([[0.3, -1.0]]), jnp.array([[-0.5, 0.2]])
    action, logp = sac.sample_tanh_gaussian(jax.random.key(0), mean, log_std)
    assert np.all(np.abs(np.asarray(action)) < 1.0)
    np.testing.assert_allclose(logp, sac.tanh_gaussian_log_prob(jnp.arctanh(action), mean, log_std), rtol=1e-4)


# ---------------------------------------------------------------------------------- cheap checks
def test_bad_names_and_configs_raise():
    with pytest.raises(SpotError, match="unknown locomotion dataset"):
        locomotion.build("hopper-random", "tiny", 0, "unused")
    with pytest.raises(SpotError, match="unknown size"):
        locomotion.build("hopper-medium", "huge", 0, "unused")
    with pytest.raises(SpotError, match="eval_every"):
        sac.SACConfig(total_steps=10_000, update_every=1000, eval_every=1500)


def test_normalized_score_by_hand():
    # midpoints of D4RL's (random, expert) references score 50
    assert locomotion.normalized("hopper", (3234.3 - 20.272305) / 2) == pytest.approx(50.0)
    assert locomotion.normalized("walker2d", (4592.3 + 1.629008) / 2) == pytest.approx(50.0)
    np.testing.assert_allclose(locomotion.normalized("hopper", [-20.272305, 3234.3]), [0.0, 100.0])
    assert locomotion.normalized("walker2d", 3000.0) == pytest.approx(100 * 2998.370992 / 4590.670992)


def test_pick_medium_takes_first_snapshot_reaching_a_third():
    snaps = [
        sac_train.Snapshot(step, ret, 0.0, None)
        for step, ret in [(1, 50.0), (2, 400.0), (3, 200.0), (4, 1100.0), (5, 900.0)]
    ]
    assert locomotion.pick_medium(snaps, 1 / 3).step == 2  # 400 >= 900 / 3; later dips don't count


@pytest.mark.slow
def test_a_build_under_a_stochastic_stop_rule_records_the_rule_and_the_stochastic_returns(tmp_path, monkeypatch):
    # tiny Hopper with paper-fast's Hopper rule and an unreachable target: SAC runs to its cap of 3000 steps
    rule = locomotion_sac.StopRule(1e9, 3000, policy="stochastic", evals=2)
    monkeypatch.setitem(locomotion.SIZES, "tiny", dataclasses.replace(locomotion.SIZES["tiny"], stop={"hopper": rule}))
    raw, card = locomotion.build("hopper-medium-replay", "tiny", 0, tmp_path, progress=False)
    b = card["behaviour"]
    assert (b["stop_policy"], b["stop_evals"], b["target_reached"]) == ("stochastic", 2, False)
    assert [step for step, _ in b["stochastic_curve"]] == list(range(500, 3001, 500))  # every evaluation
    assert b["expert_stochastic_return"] == pytest.approx(b["stochastic_curve"][-1][1], abs=0.05)
    medium_step = b["medium_snapshot_step"]  # the medium snapshot is still picked by the deterministic returns
    assert b["medium_stochastic_return"] == pytest.approx(dict(b["stochastic_curve"])[medium_step], abs=0.05)
    assert card["recipe_version"] == f"{locomotion.RECIPE_VERSION}+stop-stochastic-2"
    # its SAC run is cached under its own name, never mistaken for the plain rule's run
    assert locomotion_sac.sac_cache_path(tmp_path, "hopper", "tiny", 0).exists()
    monkeypatch.undo()
    assert not locomotion_sac.sac_cache_path(tmp_path, "hopper", "tiny", 0).exists()


# ------------------------------------------------------------------------- tiny builds (Hopper)
@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    """medium-replay, then medium-expert (cache hit), then medium-expert in a fresh cache dir."""
    first = tmp_path_factory.mktemp("cache_a")
    second = tmp_path_factory.mktemp("cache_b")
    return {
        "medium-replay": locomotion.build("hopper-medium-replay", "tiny", 0, first, progress=False),
        "medium-expert": locomotion.build("hopper-medium-expert", "tiny", 0, first, progress=False),
        "medium-expert-rebuilt": locomotion.build("hopper-medium-expert", "tiny", 0, second, progress=False),
        "full-replay": locomotion.build("hopper-full-replay", "tiny", 0, first, progress=False),
        "cache_dir": first,
    }


def _check_layout(raw, card):
    n = len(raw)
    assert raw.observations.shape == (n, 11) and raw.next_observations.shape == (n, 11)
    assert raw.actions.shape == (n, 3) and raw.rewards.shape == (n,)
    assert raw.terminals.dtype == bool and raw.timeouts.dtype == bool
    assert np.all(np.abs(raw.actions) <= 1.0)
    # each episode ends in exactly one flag, and the data ends with an episode end
    assert not np.any(raw.terminals & raw.timeouts)
    ends = raw.terminals | raw.timeouts
    assert ends[-1]
    assert int(ends.sum()) == card["episodes"] == len(raw.metadata["episode_kind"])
    # rows are consecutive steps inside an episode
    inside = np.flatnonzero(~ends[:-1])
    np.testing.assert_array_equal(raw.next_observations[inside], raw.observations[inside + 1])
    # episodes last at most 1000 steps; a timeout is the 1000-step limit or the cut that ends a
    # block of rollouts (the last episode of its kind)
    lengths = np.diff(np.concatenate([[-1], np.flatnonzero(ends)]))
    assert lengths.max() <= 1000
    kinds = np.array(raw.metadata["episode_kind"])
    last_of_kind = np.append(kinds[1:] != kinds[:-1], True)
    timed_out = raw.timeouts[ends]
    assert np.all((lengths[timed_out] == 1000) | last_of_kind[timed_out])
    for key in (
        "recipe",
        "env",
        "name",
        "size",
        "seed",
        "transitions",
        "episodes",
        "return",
        "behaviour",
        "sac",
        "sac_cache_hit",
        "build_time_s",
        "versions",
    ):
        assert key in card, key
    assert card["env"] == "Hopper-v5" and card["size"] == "tiny" and card["transitions"] == n
    assert set(card["return"]) == {"mean", "std", "min", "max", "normalized_mean"}
    assert card["return"]["normalized_mean"] == pytest.approx(
        100 * (card["return"]["mean"] + 20.272305) / 3254.572305, abs=0.01
    )
    assert card["return"]["min"] <= card["return"]["mean"] <= card["return"]["max"]
    for key in ("medium_snapshot_step", "medium_eval_return", "expert_snapshot_step", "expert_eval_return"):
        assert key in card["behaviour"], key
    assert {"gymnasium", "mujoco"} <= set(card["versions"])
    b = card["behaviour"]
    for part in ("medium", "expert"):  # D4RL: 100 (R + 20.272305) / (3234.3 + 20.272305)
        assert b[f"{part}_normalized"] == pytest.approx(
            100 * (b[f"{part}_eval_return"] + 20.272305) / 3254.572305, abs=0.01
        )
    assert b["d4rl_reference"]["expert_return"] == 3234.3
    assert b["d4rl_reference"]["random_return"] == -20.272305
    assert b["target_return"] is None and b["target_reached"] is None  # tiny: fixed length
    assert card["sac"]["steps"] == card["sac"]["step_cap"] == 3000
    assert card["sac"]["train_time_s"] > 0 and card["sac"]["peak_rss_mb"] > 0
    assert card["peak_rss_mb"] >= card["sac"]["peak_rss_mb"] or card["sac_cache_hit"]
    assert card["build_time_s"] > 0


@pytest.mark.slow
def test_medium_replay_is_the_buffer_up_to_the_medium_snapshot(builds):
    raw, card = builds["medium-replay"]
    _check_layout(raw, card)
    assert card["name"] == "hopper-medium-replay" and card["sac_cache_hit"] is False
    assert 0 < len(raw) <= card["behaviour"]["medium_snapshot_step"]
    assert set(raw.metadata["episode_kind"]) == {"replay"}


@pytest.mark.slow
def test_full_replay_is_the_whole_buffer_and_medium_replay_its_first_part(builds):
    raw, card = builds["full-replay"]
    _check_layout(raw, card)
    assert card["name"] == "hopper-full-replay" and card["sac_cache_hit"] is True  # the same SAC run
    short, short_card = builds["medium-replay"]
    b = card["behaviour"]
    assert len(short) < len(raw) <= b["expert_snapshot_step"] == locomotion.SIZES["tiny"].sac.total_steps
    # SAC's buffer in order: every complete episode up to the expert step, medium-replay's rows first
    np.testing.assert_array_equal(raw.observations[: len(short)], short.observations)
    np.testing.assert_array_equal(raw.rewards[: len(short)], short.rewards)
    assert len(raw) > b["expert_snapshot_step"] - 1000  # at most the one unfinished 1000-step episode dropped
    assert set(raw.metadata["episode_kind"]) == {"replay"}


@pytest.mark.slow
def test_medium_expert_is_medium_then_expert_and_reuses_sac(builds):
    raw, card = builds["medium-expert"]
    _check_layout(raw, card)
    assert card["sac_cache_hit"] is True
    assert len(list((builds["cache_dir"] / "sac").glob("*.msgpack"))) == 1
    assert not list((builds["cache_dir"] / "sac").glob("*.ckpt"))  # checkpoints go once stored
    per_part = locomotion.SIZES["tiny"].transitions
    assert len(raw) == 2 * per_part
    kinds = np.array(raw.metadata["episode_kind"])
    assert set(kinds) == {"medium", "expert"} and np.all(np.diff((kinds == "expert").astype(int)) >= 0)
    replay_card = builds["medium-replay"][1]
    assert card["behaviour"] == replay_card["behaviour"]  # one SAC run serves every variant
    b = card["behaviour"]
    assert b["medium_snapshot_step"] <= b["expert_snapshot_step"] == locomotion.SIZES["tiny"].sac.total_steps
    assert b["medium_eval_return"] >= b["expert_eval_return"] / 3


@pytest.mark.slow
def test_same_seed_gives_identical_arrays(builds):
    # cache_b trained SAC from scratch: same snapshots, same rollouts, same arrays
    (raw_a, card_a), (raw_b, card_b) = builds["medium-expert"], builds["medium-expert-rebuilt"]
    assert card_b["sac_cache_hit"] is False
    assert card_a["behaviour"] == card_b["behaviour"]
    for key in RAW_KEYS:
        np.testing.assert_array_equal(getattr(raw_a, key), getattr(raw_b, key), err_msg=key)


@pytest.mark.slow
def test_medium_expert_is_joined_from_its_built_parts(builds, tmp_path, monkeypatch, capsys):
    """With medium and expert built, the registry joins them: the same rows and card as the
    rollout build, without rolling out again; a part that is damaged, or whose card records another
    SAC run, makes it build the dataset whole instead."""
    import json

    from spot.data import formats, registry

    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path))
    for part in ("hopper-medium", "hopper-expert"):
        registry.build(part, "tiny", 0, progress=False)
    path = registry.build("hopper-medium-expert", "tiny", 0, progress=True)
    assert "hopper-medium-expert (tiny, seed 0) joined from the built hopper-medium and hopper-expert" in (
        capsys.readouterr().err
    )
    joined, card = formats.read_d4rl_hdf5(path), registry.read_card(path)
    rolled, rolled_card = builds["medium-expert"]  # locomotion.build: both parts rolled out again
    for key in RAW_KEYS:
        np.testing.assert_array_equal(getattr(joined, key), getattr(rolled, key), err_msg=key)
    assert joined.metadata["episode_kind"] == rolled.metadata["episode_kind"]
    assert card["joined_from"] == ["hopper-medium", "hopper-expert"] and card["sac_cache_hit"] is True
    assert card["build_time_s"] > 0
    timing = {"build_time_s", "peak_rss_mb", "sac_cache_hit", "train_time_s"}  # this data dir trained its own SAC

    def same(c):
        return {k: same(v) if isinstance(v, dict) else v for k, v in c.items() if k not in timing}

    assert same({k: v for k, v in card.items() if k in rolled_card}) == same(rolled_card)

    # a part whose card records another SAC run: built whole (its rows are still the same)
    medium_card = registry.card_path(registry.dataset_path("hopper-medium", "tiny", 0))
    other = json.loads(medium_card.read_text())
    other["behaviour"]["eval_curve"][-1][1] += 1.0
    medium_card.write_text(json.dumps(other))
    path = registry.build("hopper-medium-expert", "tiny", 0, progress=False, force=True)
    assert "joined_from" not in registry.read_card(path)
    np.testing.assert_array_equal(formats.read_d4rl_hdf5(path).rewards, rolled.rewards)

    # a part rolled out under other package versions: built whole
    medium_card.write_text(json.dumps({**other, "behaviour": rolled_card["behaviour"], "versions": {"mujoco": "0"}}))
    path = registry.build("hopper-medium-expert", "tiny", 0, progress=False, force=True)
    assert "joined_from" not in registry.read_card(path)

    # a damaged part (its sha256 no longer the card's): built whole
    medium_card.write_text(json.dumps({**other, "behaviour": rolled_card["behaviour"]}))
    expert = registry.dataset_path("hopper-expert", "tiny", 0)
    damaged = bytearray(expert.read_bytes())
    damaged[-1] ^= 0xFF
    expert.write_bytes(bytes(damaged))
    path = registry.build("hopper-medium-expert", "tiny", 0, progress=False, force=True)
    assert "joined_from" not in registry.read_card(path)
    np.testing.assert_array_equal(formats.read_d4rl_hdf5(path).observations, rolled.observations)


@pytest.mark.slow
def test_medium_expert_joins_parts_from_the_shared_store(tmp_path, monkeypatch):
    """Node A builds medium and expert (uploaded to the store); node B, with an empty data dir,
    fetches them and joins medium-expert instead of rolling it out."""
    from spot.data import registry

    monkeypatch.setenv("SPOT_STORE", str(tmp_path / "store"))
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "A"))
    for part in ("hopper-medium", "hopper-expert"):
        registry.build(part, "tiny", 0, progress=False)
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "B"))
    path = registry.build("hopper-medium-expert", "tiny", 0, progress=False)
    assert registry.read_card(path)["joined_from"] == ["hopper-medium", "hopper-expert"]
    assert {p.name for p in (tmp_path / "B").glob("*.hdf5")} == {
        "hopper-medium__tiny__seed0.hdf5",
        "hopper-expert__tiny__seed0.hdf5",
        "hopper-medium-expert__tiny__seed0.hdf5",
    }
