"""`spot run` end to end at the tiny budget: MLflow contents, stage cache reuse, determinism, failures."""

from pathlib import Path

import mlflow
import numpy as np
import pytest

from spot import NonFiniteError, SpotError, config, pipeline, tracking
from tests.conftest import TINY_RUN


def _cfg(tmp_path: Path, *overrides: str):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    return config.load(None, [*TINY_RUN, f"tracking.uri={uri}", "tracking.experiment=test", *overrides])


def _run(cfg):
    mlflow.set_tracking_uri(cfg.tracking.uri)
    return mlflow.get_run(pipeline.run(cfg, progress=False)["run_id"])


@pytest.fixture()
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))


def test_spot_run_logs_everything_and_reuses_stages(tmp_path, spot_dirs, tiny_drawer, fresh_cache):
    cfg = _cfg(tmp_path, "method=spot")
    run = _run(cfg)
    d = run.data
    assert run.info.status == "FINISHED"
    # tags and the full resolved config as params
    for tag in (
        "method",
        "dataset",
        "spot.dataset_source",
        "spot.label_source",
        "seed",
        "spot.git_commit",
        "spot.version.jax",
    ):
        assert tag in d.tags, tag
    assert (
        d.tags["method"] == "spot" and d.tags["dataset"] == "drawer-open" and d.tags["spot.dataset_source"] == "recipe"
    )
    # the active config as params (no mr.*/hpl.*/ipl.* on a SPOT run); the whole config in config.yaml
    assert d.params == {k: str(list(v) if isinstance(v, tuple) else v) for k, v in tracking.active_params(cfg).items()}
    # metrics of every stage
    for key in (
        "reward/best_eval_acc",
        "subgoal/num_subgoals",
        "subgoal/precision",
        "subgoal/recall",
        "cvae/loss",
        "shaping/r_shape_mean",
        "iql/critic_loss",
        "eval/score",
        "eval/score_final",
        "eval/score_best",
        "diag/extrapolation_error_ood",
        "time/reward_s",
        "time/cvae_s",
        "time/iql_s",
    ):
        assert key in d.metrics, key
    # cache hits are tags, not metrics
    assert not any(k.startswith("cache/") for k in d.metrics)
    assert (d.tags["spot.cache.reward"], d.tags["spot.cache.relabel"], d.tags["spot.cache.cvae"]) == ("miss",) * 3
    client = mlflow.tracking.MlflowClient()
    # evaluated before the first update and at every multiple of eval.every
    assert [m.step for m in client.get_metric_history(run.info.run_id, "eval/score")] == [0, 100, 200]
    names = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {
        "config.yaml",
        "dataset_card.json",
        "learning_curve.png",
        "subgoal_projection.png",
        "extrapolation_error.png",
        "extrapolation_error.json",
        "environment.json",
        "requirements.txt",
        "models",
    } <= names
    assert {a.path for a in client.list_artifacts(run.info.run_id, "models")} == {
        f"models/{m}.{ext}" for m in ("reward_model", "cvae", "policy") for ext in ("npz", "json")
    }

    # Only lambda changes: the reward model, relabelling and CVAE come from the cache.
    again = _run(config.replace(cfg, **{"shaping.weight": 0.5}))
    m, t = again.data.metrics, again.data.tags
    assert (t["spot.cache.reward"], t["spot.cache.relabel"], t["spot.cache.cvae"]) == ("hit", "hit", "hit")
    assert m["shaping/r_final_mean"] != d.metrics["shaping/r_final_mean"]


def test_same_config_and_seed_give_identical_metrics(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    results = []
    for i in range(2):  # separate caches: everything is recomputed
        monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / f"cache{i}"))
        results.append(_run(_cfg(tmp_path, "method=pt", "subgoal.diagnostics=false")).data.metrics)
    # wall times and MLflow's system metrics (CPU, memory samples) measure the machine, not the run
    skip = {k for k in results[0] if k.startswith(("time/", "system/")) or k.endswith("steps_per_s")}
    assert len(results[0]) - len(skip) > 20  # the scores, losses and diagnostics are compared
    assert {k: v for k, v in results[0].items() if k not in skip} == {
        k: v for k, v in results[1].items() if k not in skip
    }


def test_oracle_uses_true_reward_without_labels(tmp_path, spot_dirs, tiny_drawer, fresh_cache):
    run = _run(_cfg(tmp_path, "method=oracle"))
    assert run.data.tags["spot.label_source"] == "none"
    assert "reward/best_eval_acc" not in run.data.metrics and "eval/score_final" in run.data.metrics


def test_nan_loss_marks_run_failed_with_step_and_loss(tmp_path, spot_dirs, tiny_drawer, fresh_cache, monkeypatch):
    from spot.policy import iql

    real = iql.make_train_chunk

    def poisoned(cfg):
        chunk = real(cfg)

        def run_chunk(state, *args):
            state, metrics = chunk(state, *args)
            return state, {**metrics, "iql/critic_loss": metrics["iql/critic_loss"] * np.nan}

        return run_chunk

    monkeypatch.setattr(iql, "make_train_chunk", poisoned)
    cfg = _cfg(tmp_path, "method=oracle")
    with pytest.raises(NonFiniteError) as err:
        pipeline.run(cfg, progress=False)
    assert err.value.step == 100 and err.value.loss_name == "iql/critic_loss"
    mlflow.set_tracking_uri(cfg.tracking.uri)
    failed = mlflow.search_runs(experiment_names=["test"], filter_string="attributes.status = 'FAILED'")
    assert len(failed) == 1
    assert (
        "iql/critic_loss" in failed["tags.failure_reason"].iloc[0]
        and "step 100" in failed["tags.failure_reason"].iloc[0]
    )


def test_config_that_does_not_fit_the_dataset(tmp_path, spot_dirs, tiny_drawer, fresh_cache):
    # segments longer than any episode of the dataset
    with pytest.raises(SpotError, match="segment"):
        pipeline.run(_cfg(tmp_path, "method=pt", "labels.segment_length=5000"), progress=False)
    with pytest.raises(SpotError, match="needs reward.kind=pt"):
        pipeline.run(_cfg(tmp_path, "method=mr", "shaping.kind=cosine"), progress=False)


@pytest.mark.parametrize("method", ["ipl", "hpl"])
def test_baselines_run_end_to_end(method, tmp_path, spot_dirs, tiny_drawer, fresh_cache):
    run = _run(_cfg(tmp_path, f"method={method}"))
    m = run.data.metrics
    assert run.info.status == "FINISHED" and run.data.tags["method"] == method
    assert {"eval/score_final", "eval/score_best", "reward/eval_acc", "reward/train_acc", "time/iql_s"} <= set(m)
    if method == "ipl":
        # IPL trains no reward model and sees no reward: its critic's implied reward is ranked instead
        assert "ipl/pref_loss" in m and "ipl/chi2_loss" in m and "time/reward_s" not in m
        assert "iql/critic_loss" not in m
    else:
        # HPL's two pretraining phases are timed (Table 8) and the relabelled reward is cached
        assert {"time/hpl_vae_s", "time/hpl_reward_s", "time/reward_s"} <= set(m)
        assert run.data.tags["spot.cache.reward"] == "miss"
        again = _run(_cfg(tmp_path, f"method={method}", "iql.steps=100"))
        assert again.data.tags["spot.cache.reward"] == "hit" and again.data.tags["spot.cache.relabel"] == "hit"


@pytest.mark.parametrize("method", ["spot", "pt"])
def test_policy_reward_is_normalised_model_reward_plus_lambda_shape(
    method, tmp_path, spot_dirs, tiny_drawer, monkeypatch
):
    """Eq. 13 in the pipeline: SPOT's policy trains on normalise(r_hat) + lambda (1 + cos(s', g_hat)) / 2
    with g_hat = G(s, a) (prior mean); PT trains on normalise(r_hat) alone, although its run also
    extracts subgoals and trains the CVAE for the Fig. 2 diagnostics."""
    import dataclasses

    from spot import stages
    from spot.reward import relabel
    from spot.run import reward_stages, subgoal_stages
    from spot.subgoal import cvae

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    seen = {}
    shaping_stage = subgoal_stages.shaping_stage

    def capture_shaping(ctx, rewards, subgoals):
        seen.update(ctx=ctx, rewards=rewards, subgoals=subgoals)
        return shaping_stage(ctx, rewards, subgoals)

    kind = stages.REWARD_KINDS["pt"]

    def capture_policy(ctx, shaped, labelled):
        seen["policy_reward"] = np.asarray(shaped.reward)
        return kind.policy(ctx, shaped, labelled)

    monkeypatch.setattr(subgoal_stages, "shaping_stage", capture_shaping)
    monkeypatch.setitem(stages.REWARD_KINDS, "pt", dataclasses.replace(kind, policy=capture_policy))
    cfg = _cfg(tmp_path, f"method={method}", "shaping.weight=0.5", "iql.steps=100")
    assert cfg.subgoal.diagnostics and cfg.relabel.normalize == "iql"
    pipeline.run(cfg, progress=False)

    ctx, rewards, subgoals = seen["ctx"], seen["rewards"], seen["subgoals"]
    ds = ctx.ds
    assert subgoals is not None  # both methods trained the CVAE
    scale = reward_stages.normalisation_scale(cfg, ctx.env_name)
    normalised = relabel.normalize_rewards(rewards.model, ds, "iql", scale)
    np.testing.assert_allclose(rewards.normalised, normalised, rtol=1e-6)
    if method == "pt":
        np.testing.assert_array_equal(seen["policy_reward"], rewards.normalised)
        return
    g_hat = np.asarray(cvae.generate(subgoals.cvae_params, ds.observations, ds.actions), np.float64)
    s_next = ds.next_observations.astype(np.float64)
    cos = np.sum(s_next * g_hat, 1) / (np.linalg.norm(s_next, axis=1) * np.linalg.norm(g_hat, axis=1))
    expected = normalised + 0.5 * (1.0 + cos) / 2.0
    np.testing.assert_allclose(seen["policy_reward"], expected, rtol=1e-4, atol=1e-5)
    assert not np.allclose(seen["policy_reward"], normalised)
