"""A smoke block's budget wins over the base's settings of the keys its preset sets."""

from spot import config
from spot.sweep import spec


def test_smoke_budget_drops_base_keys_of_its_preset():
    base = {"budget": "small", "iql.steps": 10000, "eval.every": 2000, "method": "pt", "labels.source": "script"}
    out = spec.smoke_base(base, {"budget": "tiny", "data.size": "tiny"})
    # iql.steps and eval.every are tiny-preset keys: dropped, so the preset's 200 / 100 apply
    assert out == {"budget": "tiny", "data.size": "tiny", "method": "pt", "labels.source": "script"}
    # a key the smoke block sets itself is kept
    assert spec.smoke_base(base, {"budget": "tiny", "iql.steps": 300})["iql.steps"] == 300
    # without a smoke budget the base is only updated
    assert spec.smoke_base(base, {"seed_like": 1}) == {**base, "seed_like": 1}


def test_quickstart_smoke_runs_the_tiny_budget():
    full, smoke = spec.load("sweeps/quickstart.yaml"), spec.load("sweeps/quickstart.yaml", smoke=True)
    assert all(t.overrides["iql.steps"] == 10000 and t.overrides["eval.every"] == 2000 for t in full.trials())
    for trial in smoke.trials():
        assert "iql.steps" not in trial.overrides and "eval.every" not in trial.overrides
        cfg = config.resolve(trial.overrides, {"seed": 0})
        tiny = config.BUDGET_PRESETS["tiny"]
        assert (cfg.iql.steps, cfg.eval.every, cfg.data.size) == (tiny["iql.steps"], tiny["eval.every"], "tiny")
        assert cfg.labels.source == "script"  # a base key outside the preset stays
