"""Config system: presets, overrides, validation messages, flat round trip."""

import pytest

from spot import SpotError, config


def test_defaults_are_the_papers_values():
    cfg = config.resolve({"budget": "paper"})
    assert (cfg.pt.n_layer, cfg.pt.n_head, cfg.pt.embd_dim) == (1, 4, 256)
    assert (cfg.reward.batch_size, cfg.reward.steps, cfg.pt.lr, cfg.pt.warmup_steps) == (256, 10_000, 1e-4, 500)
    assert (cfg.iql.expectile, cfg.iql.temperature, cfg.iql.tau, cfg.iql.discount) == (0.7, 3.0, 0.005, 0.99)
    assert cfg.cvae.hidden == (32, 64, 32) and cfg.cvae.beta == 1.0 and cfg.cvae.steps == 100_000
    assert cfg.subgoal.top_k == 10.0 and cfg.labels.segment_length == 100


def test_method_presets_and_precedence(tmp_path):
    f = tmp_path / "run.yaml"
    f.write_text("method: pt\niql:\n  steps: 123\nshaping:\n  weight: 0.5\n")
    cfg = config.load(f, ["iql.steps=456"])
    assert cfg.method == "pt" and cfg.reward.kind == "pt" and cfg.shaping.kind == "none"
    assert cfg.iql.steps == 456  # override beats file
    assert cfg.shaping.weight == 0.5
    spot = config.load(None, ["method=spot"])
    assert spot.reward.kind == "pt" and spot.shaping.kind == "cosine" and spot.shaping.weight == 1.0
    assert config.load(None, ["method=oracle"]).reward.kind == "none"
    # budget preset applies, user value still wins
    tiny = config.load(None, ["budget=tiny", "iql.steps=7"])
    assert tiny.iql.steps == 7 and tiny.reward.steps == config.BUDGET_PRESETS["tiny"]["reward.steps"]


def test_flat_round_trip_including_strings():
    cfg = config.load(None, ["method=mr", "mr.hidden=[32, 16]", "labels.tie_threshold=0.5"])
    flat = config.to_flat(cfg)
    assert config.from_flat(flat) == cfg
    assert config.from_flat({k: str(v) for k, v in flat.items()}) == cfg  # as MLflow stores params
    assert hash(cfg) == hash(config.from_flat(flat))  # frozen -> hashable


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("iql.step=3", "unknown config key 'iql.step'; did you mean 'iql.steps'"),
        ("iql.steps=abc", "'iql.steps': value 'abc' is not int"),
        ("iql.expectile=1.5", "expected 0.0 <= value <= 1.0"),
        ("shaping.weight=-2", "'shaping.weight'"),
        ("method=dpo", "is not one of 'oracle', 'mr', 'pt', 'ipl', 'hpl', 'spot'"),
        ("subgoal.reward_filter=maybe", "is not bool"),
        ("noequals", "expected KEY=VALUE"),
    ],
)
def test_bad_values_name_key_and_expectation(override, fragment):
    with pytest.raises(SpotError, match=None) as err:
        config.load(None, [override])
    assert fragment in str(err.value)


def test_bad_yaml_file(tmp_path):
    with pytest.raises(SpotError, match="does not exist"):
        config.load(tmp_path / "missing.yaml")
    f = tmp_path / "bad.yaml"
    f.write_text("iql:\n  stepz: 3\n")
    with pytest.raises(SpotError, match=r"bad.yaml.*unknown config key 'iql.stepz'"):
        config.load(f)
    f.write_text("- a\n- b\n")
    with pytest.raises(SpotError, match="expected a mapping"):
        config.load(f)


def test_suite_presets_follow_the_reference_per_benchmark():
    mw = config.resolve({"method": "ipl", "data.name": "drawer-open"})
    assert (mw.labels.segment_length, mw.labels.teacher, mw.iql.expectile) == (25, "discounted", 0.75)
    assert (mw.ipl.chi2_coeff, mw.ipl.target_clipping, mw.ipl.use_replay, mw.ipl.subsample) == (3.0, False, False, 16)
    assert mw.iql.hidden == (256, 256, 256)
    robo = config.resolve({"method": "spot", "data.name": "can-mh", "budget": "paper"})
    assert (robo.labels.segment_length, robo.iql.temperature, robo.relabel.normalize) == (100, 0.5, "iql")
    assert config.resolve({"method": "ipl", "data.name": "lift-ph", "budget": "paper"}).ipl.subsample == 32
    loco = config.resolve({"method": "pt", "data.name": "hopper-medium-replay-v2", "budget": "paper"})
    assert (loco.labels.segment_length, loco.iql.expectile, loco.relabel.normalize) == (100, 0.7, "pt")
    # the YAML file and overrides still win over the suite preset
    assert config.resolve({"data.name": "drawer-open"}, {"labels.segment_length": 30}).labels.segment_length == 30
    assert config.suite_of("/data/some_file.hdf5") is None


def test_robosuite_preset_labels_with_the_dense_reward_and_ties():
    for method in config.METHODS:
        for budget in config.BUDGETS:
            robo = config.resolve({"method": method, "budget": budget, "data.name": "lift-ph"})
            assert (robo.labels.score, robo.labels.tie_threshold) == ("dense", 0.0)
    for name in ("hopper-medium-replay", "drawer-open", "/data/can/ph/low_dim.hdf5"):
        other = config.resolve({"data.name": name})
        assert (other.labels.score, other.labels.tie_threshold) == ("reward", -1.0)
    assert config.resolve({"data.name": "can-mh"}, {"labels.score": "reward"}).labels.score == "reward"
    with pytest.raises(SpotError, match="'labels.score': value 'shaped' is not one of 'reward', 'dense'"):
        config.load(None, ["labels.score=shaped"])


def test_small_locomotion_budgets_normalise_learned_rewards_to_non_negative():
    for method in ("mr", "pt", "spot"):
        assert config.resolve({"method": method, "budget": "small"}).relabel.normalize == "minmax"
        assert config.resolve({"method": method, "budget": "paper"}).relabel.normalize == "pt"
    assert config.resolve({"method": "oracle", "budget": "small"}).relabel.normalize == "iql"
