"""The run as stages: the method table, the tracker interface, a method added from outside, and the
cross-field config rules checked at resolve time."""

import sys
import textwrap

import mlflow
import numpy as np
import pytest

from spot import SpotError, config, pipeline, stages, sweep, tracking
from spot.run import subgoal_stages
from tests.conftest import TINY_RUN, run_cli


@pytest.fixture()
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))


@pytest.fixture()
def method_registry():
    """Undo registrations made by a test."""
    saved = (dict(stages.REWARD_KINDS), dict(config.METHOD_PRESETS), list(config.REWARD_KINDS))
    yield
    stages.REWARD_KINDS.clear()
    stages.REWARD_KINDS.update(saved[0])
    config.METHOD_PRESETS.clear()
    config.METHOD_PRESETS.update(saved[1])
    config.REWARD_KINDS[:] = saved[2]


# --------------------------------------------------------------------------- the method table
def test_every_method_has_its_stages():
    for method in config.METHODS:
        kind = stages.stages_of(config.resolve({"method": method}))
        assert callable(kind.reward) and callable(kind.relabel) and callable(kind.policy)
    assert stages.stages_of(config.resolve({"method": "ipl"})).policy is stages.ipl_policy
    assert stages.stages_of(config.resolve({"method": "pt"})).policy is stages.iql_policy
    assert not stages.stages_of(config.resolve({"method": "oracle"})).uses_labels
    assert subgoal_stages.needs_subgoals(config.resolve({"method": "spot"}))
    assert not subgoal_stages.needs_subgoals(config.resolve({"method": "mr"}))


def test_in_segments_mask_marks_both_segments_and_clips_at_the_end():
    class P:
        starts_1, starts_2, segment_length = np.array([0, 7]), np.array([3, 9]), 2

    # segments [0,1], [7,8], [3,4], [9,10->clipped]
    assert np.flatnonzero(subgoal_stages.in_segments_mask(10, P())).tolist() == [0, 1, 3, 4, 7, 8, 9]


@pytest.mark.slow
def test_run_with_a_memory_tracker_writes_no_store(tmp_path, spot_dirs, tiny_drawer, fresh_cache, monkeypatch):
    monkeypatch.chdir(tmp_path)
    tr = tracking.MemoryTracker()
    out = pipeline.run(config.load(None, [*TINY_RUN, "method=oracle"]), progress=False, tracker=tr)
    assert [s for s, _ in tr.metrics["eval/score"]] == [0, 100, 200]
    assert {"models/policy.npz", "models/policy.json"} <= set(tr.artifacts)  # the Oracle saves only its policy
    assert not any(k.startswith(("models/reward_model", "models/cvae")) for k in tr.artifacts)
    assert out["eval/score_final"] == tr.metrics["eval/score"][-1][1] == tr.last("eval/score_final")
    assert "learning_curve.png" in tr.artifacts and out["run_id"] == "memory"
    assert "time/iql_s" in tr.metrics and "time/reward_s" not in tr.metrics  # the Oracle trains no reward model
    assert not (tmp_path / "mlruns").exists() and not (tmp_path / "spot_runs").exists()


def test_fig2_in_distribution_is_the_training_segments_only():
    class P:
        def __init__(self, s1, s2):
            self.starts_1, self.starts_2, self.segment_length = np.array(s1), np.array(s2), 2

    labelled = stages.Labelled(
        prefs=P([0, 10], [4, 14]), train_prefs=P([0], [4]), train_batch={}, eval_batch=None, deps={}
    )
    # training segments [0, 1] and [4, 5]; the held-out query's [10, 11], [14, 15] are out of distribution
    assert np.flatnonzero(subgoal_stages.in_distribution(16, labelled)).tolist() == [0, 1, 4, 5]


@pytest.mark.parametrize(("name", "scale"), [("lift-ph", 500), ("drawer-open", 500), ("hopper-medium-replay", 1000)])
def test_normalisation_scales_returns_to_the_envs_episode_length(name, scale):
    from tests.conftest import make_dataset

    ds = make_dataset([5, 7, 3], seed=1)
    ctx = stages.Context(
        config.resolve({"method": "oracle", "data.name": name}), ds, {}, name, tracking.MemoryTracker(), {}
    )
    r = stages.true_rewards(ctx, None).normalised  # oracle: relabel.normalize=iql, r * scale / spread
    returns = np.add.reduceat(r.astype(np.float64), [0, 5, 12])
    assert returns.max() - returns.min() == pytest.approx(scale, rel=1e-5)
    fixed = stages.Context(
        config.resolve({"method": "oracle", "data.name": name, "relabel.scale": 7}),
        ds,
        {},
        name,
        tracking.MemoryTracker(),
        {},
    )
    returns = np.add.reduceat(stages.true_rewards(fixed, None).normalised.astype(np.float64), [0, 5, 12])
    assert returns.max() - returns.min() == pytest.approx(7, rel=1e-5)


# --------------------------------------------------------------------------- adding a method
def constant_rewards(ctx, model):
    """The toy method's relabel stage: reward 1 for every transition."""
    ones = np.ones(len(ctx.ds), np.float32)
    ctx.log({"toy/reward_mean": float(ones.mean())})
    return stages.Rewards(ones, ones, None)


def register_toy():
    stages.register(
        "toy",
        stages.RewardKind(stages.true_reward, constant_rewards, uses_labels=False),
        preset={"relabel.normalize": "none"},
    )


@pytest.mark.slow
def test_a_registered_method_runs_end_to_end_through_spot_run(
    tmp_path, spot_dirs, tiny_drawer, fresh_cache, method_registry, capsys
):
    from spot import cli

    register_toy()
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert cli.main(["run", "--quiet", "method=toy", *TINY_RUN, f"tracking.uri={uri}", "tracking.experiment=toy"]) == 0
    mlflow.set_tracking_uri(uri)
    runs = mlflow.search_runs(experiment_names=["toy"])
    assert len(runs) == 1 and runs["status"].iloc[0] == "FINISHED" and runs["tags.method"].iloc[0] == "toy"
    assert runs["metrics.toy/reward_mean"].iloc[0] == 1.0 and runs["params.reward.kind"].iloc[0] == "toy"
    with pytest.raises(SpotError, match="already registered"):
        register_toy()


def test_an_unknown_method_is_refused_with_the_registered_ones():
    with pytest.raises(SpotError, match="'toy' is not one of 'oracle', 'mr', 'pt', 'ipl', 'hpl', 'spot'"):
        config.resolve({"method": "toy"})


def test_methods_from_other_packages_load_through_entry_points(tmp_path):
    """A package that declares a ``spot.methods`` entry point is picked up by the CLI."""
    (tmp_path / "toy_plugin.py").write_text(
        textwrap.dedent("""
        from spot import stages

        def register():
            stages.register("plug", stages.RewardKind(stages.true_reward, stages.true_rewards,
                                                      uses_labels=False))
    """)
    )
    dist = tmp_path / "toy_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[spot.methods]\nplug = toy_plugin:register\n")
    env = {"PYTHONPATH": f"{tmp_path}:{':'.join(p for p in sys.path if p)}"}
    out = run_cli("config", "show", "method=plug", env=env)
    assert out.returncode == 0, out.stderr
    assert "method: plug" in out.stdout and "kind: plug" in out.stdout
    assert run_cli("config", "show", "method=plug").returncode == 2  # not installed: unknown method


# --------------------------------------------------------------------------- cross-field rules
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"method": "mr", "shaping.kind": "cosine"}, "shaping.kind='cosine' needs reward.kind=pt"),
        ({"method": "pt", "labels.source": "human"}, "labels.source=human needs labels.path"),
        ({"method": "hpl", "labels.segment_length": 80, "hpl.seq_len": 64}, "exceeds hpl.seq_len=64"),
    ],
)
def test_cross_field_rules_are_checked_when_resolving(overrides, message):
    with pytest.raises(SpotError, match=message.replace("(", r"\(").replace(")", r"\)")):
        config.resolve(overrides)


def test_replace_checks_the_same_rules():
    with pytest.raises(SpotError, match="needs reward.kind=pt"):
        config.replace(config.resolve({"method": "mr"}), **{"shaping.kind": "cosine"})


def test_oracle_may_keep_human_label_settings_it_does_not_use():
    assert config.resolve({"method": "oracle", "labels.source": "human"}).reward.kind == "none"


def test_a_sweep_with_a_bad_trial_is_rejected_before_launch(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("name: s\nbase: {budget: tiny, shaping.kind: cosine}\ngrid:\n  method: [pt, mr]\nseeds: [0]\n")
    with pytest.raises(SpotError, match=r"s\.yaml.*shaping\.kind='cosine' needs reward\.kind=pt"):
        sweep.load(f)


def test_eval_every_need_not_be_a_multiple_of_the_chunk():
    # evaluations cut the chunks (iql.eval_steps), so any eval.every resolves
    cfg = config.resolve({"iql.chunk": 1000, "eval.every": 2500})
    assert (cfg.iql.chunk, cfg.eval.every) == (1000, 2500)
