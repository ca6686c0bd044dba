"""Self-contained runs: the evaluation schedule, models saved as run artifacts, `spot eval`."""

import json
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from spot import NonFiniteError, SpotError, config, pipeline, tracking
from spot.policy import iql
from spot.run import policy_stages


# --------------------------------------------------------------------------- the evaluation schedule
def test_eval_steps_by_hand():
    assert iql.eval_steps(200, 100) == [0, 100, 200]
    assert iql.eval_steps(250, 100) == [0, 100, 200, 250]
    assert iql.eval_steps(10000, 2500) == [0, 2500, 5000, 7500, 10000]
    assert iql.eval_steps(50, 100) == [0, 50]
    with pytest.raises(SpotError):
        iql.eval_steps(100, 0)


def test_the_last_evaluation_uses_final_episodes():
    cfg = config.load(None, ["budget=tiny", "iql.steps=250", "eval.episodes=4", "eval.final_episodes=20"])
    assert [policy_stages.eval_episodes(cfg, step) for step in (0, 100, 249, 250)] == [4, 4, 4, 20]
    unset = config.load(None, ["budget=tiny", "iql.steps=250", "eval.episodes=4"])
    assert [policy_stages.eval_episodes(unset, step) for step in (0, 250)] == [4, 4]


class _Counter:
    """A fake train chunk: the state counts updates; records each call's (n, chunk index)."""

    def __init__(self, nan_at_call=None):
        self.calls, self.nan_at_call = [], nan_at_call

    def __call__(self, state, n, c):
        self.calls.append((int(n), c))
        loss = np.nan if len(self.calls) == self.nan_at_call else 1.0
        done = state.actor.params + int(n)
        return SimpleNamespace(actor=SimpleNamespace(params=done)), {"loss": jnp.float32(loss)}


def _train(chunk, steps=250, every=100, length=60):
    cfg = config.IQLConfig(steps=steps, chunk=length)
    seen, logged = [], []
    state = SimpleNamespace(actor=SimpleNamespace(params=0))
    curve = iql.train(
        chunk,
        state,
        lambda c: (c,),
        cfg,
        every,
        lambda params, step: (seen.append((params, step)), float(step))[1],
        log=lambda metrics, step: logged.append(step),
    )
    return curve, seen, logged


def test_train_evaluates_at_zero_and_exactly_at_multiples_of_every():
    chunk = _Counter()
    curve, seen, logged = _train(chunk)
    # evaluations see exactly the updates done so far: 0, 100, 200, 250
    assert seen == [(0, 0), (100, 100), (200, 200), (250, 250)]
    assert curve.steps == [0, 100, 200, 250] and curve.scores == [0.0, 100.0, 200.0, 250.0]
    # chunks of 60 cut at each evaluation, numbered through the run; 250 updates in all
    assert chunk.calls == [(60, 0), (40, 1), (60, 2), (40, 3), (50, 4)]
    assert logged == [60, 100, 160, 200, 250] and curve.state.actor.params == 250


def test_non_finite_loss_names_the_step_of_the_run():
    with pytest.raises(NonFiniteError, match="at step 160"):
        _train(_Counter(nan_at_call=3))  # the third chunk ends at update 160


# --------------------------------------------------------------------------- saved models
def _uri(tmp_path):
    return f"sqlite:///{tmp_path / 'mlflow.db'}"


def test_saved_model_round_trip_and_cvae_from_run(tmp_path):
    from spot import figures
    from spot.subgoal import cvae

    cfg = config.load(None, ["method=spot", "budget=tiny", f"tracking.uri={_uri(tmp_path)}", "tracking.experiment=m"])
    params = cvae.init(jax.random.key(0), 5, 2, cfg.cvae, (np.arange(5.0), np.ones(5))).params
    with tracking.start_run(cfg, {"name": "hopper-medium-replay"}, system_metrics=False) as tr:
        head = tracking.save_model(
            tr, tmp_path / "out", "cvae", "a CVAE", params, {"cvae": {"latent_dim": 4}}, score=float("nan")
        )
    assert head["shapes"][".obs_mean"] == [5] and head["score"] is None  # JSON-safe header
    got, cfg_back, head = figures.cvae_from_run(tr.run_id, _uri(tmp_path))
    assert isinstance(got, cvae.CVAEParams) and (got.hidden, got.latent_dim) == (params.hidden, params.latent_dim)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert cfg_back == cfg
    header = json.loads(next((tmp_path / "artifacts").rglob("models/cvae.json")).read_text())
    assert (
        header["name"] == "cvae"
        and header["config"] == {"cvae": {"latent_dim": 4}}
        and "spot.cache" in header["format"]
    )
    with pytest.raises(SpotError, match="has no saved model models/policy"):
        tracking.load_model(tr.run_id, "policy", _uri(tmp_path))


def test_a_tampered_model_is_refused(tmp_path):
    with tracking.start_run(
        config.load(None, [f"tracking.uri={_uri(tmp_path)}"]), {"name": "x"}, system_metrics=False
    ) as tr:
        tracking.save_model(tr, tmp_path / "out", "policy", "p", {"w": np.ones(3)}, {})
    npz = next((tmp_path / "artifacts").rglob("models/policy.npz"))
    data = bytearray(npz.read_bytes())
    data[-30] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(SpotError, match="not a readable saved model"):
        tracking.load_model(tr.run_id, "policy", _uri(tmp_path))


# --------------------------------------------------------------------------- spot eval
@pytest.mark.slow
def test_spot_eval_reproduces_the_logged_final_score(tmp_path, spot_dirs, tiny_drawer, monkeypatch, capsys):
    from spot import cli

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    uri = _uri(tmp_path)
    cfg = config.load(
        None,
        [
            "method=oracle",
            "budget=tiny",
            "data.name=drawer-open",
            "iql.steps=200",
            "eval.every=100",
            "eval.episodes=2",
            "eval.final_episodes=3",
            f"tracking.uri={uri}",
            "tracking.experiment=e",
        ],
    )
    out = pipeline.run(cfg, progress=False)
    run_id = out["run_id"]
    client = MlflowClient(uri)
    logged_return = [m for m in client.get_metric_history(run_id, "eval/return") if m.step == 200][0].value
    logged_length = [m for m in client.get_metric_history(run_id, "eval/length") if m.step == 200][0].value

    res = pipeline.evaluate_run(run_id, uri)
    # the last evaluation ran eval.final_episodes (3), and spot eval defaults to the same episodes
    assert (res["episodes"], res["steps"], res["env"]) == (3, 200, "drawer-open")
    # same policy, same env seeds: the same episodes, so the same score and return
    assert res["score_mean"] == pytest.approx(out["eval/score_final"], rel=1e-9, abs=1e-12)
    assert res["score_mean"] == pytest.approx(res["logged_score_final"], rel=1e-9, abs=1e-12)
    assert res["return_mean"] == pytest.approx(logged_return, rel=1e-6)
    assert res["length_mean"] == logged_length and 1 <= logged_length <= 500  # drawer-open's horizon

    assert cli.main(["eval", run_id, "--tracking-uri", uri]) == 0
    printed = capsys.readouterr().out
    assert f"run {run_id}" in printed and "reproduces the logged eval/score_final" in printed
    assert "length_mean" in printed
    assert cli.main(["eval", "0" * 32, "--tracking-uri", uri]) == 2


def test_fig3_uses_the_runs_cvae_on_the_runs_dataset(tmp_path):
    """`spot figures fig3 --run-id`: the run's saved CVAE, its dataset (a D4RL-layout file here) and
    its env (Hopper), rendered headless in a fresh process."""
    import subprocess
    import sys
    from pathlib import Path

    from spot.subgoal import cvae
    from tests.conftest import run_cli

    root = Path(__file__).resolve().parents[1]
    data = tmp_path / "hopper-medium-replay-v2.hdf5"
    made = subprocess.run(
        [
            sys.executable,
            str(root / "scripts" / "make_synthetic_d4rl.py"),
            str(data),
            "--transitions",
            "2000",
            "--episode-length",
            "100",
        ],
        capture_output=True,
        text=True,
    )
    assert made.returncode == 0, made.stderr
    cfg = config.load(
        None, ["method=spot", "budget=tiny", f"data.name={data}", "data.source=file", f"tracking.uri={_uri(tmp_path)}"]
    )
    params = cvae.init(jax.random.key(1), 11, 3, cfg.cvae, (np.zeros(11), np.ones(11))).params
    with tracking.start_run(cfg, {"name": "hopper-medium-replay"}, system_metrics=False) as tr:
        tracking.save_model(tr, tmp_path / "out", "cvae", "a CVAE", params, {}, dataset="hopper-medium-replay")
    out = tmp_path / "fig3.png"
    got = run_cli(
        "figures",
        "fig3",
        "--run-id",
        tr.run_id,
        "--index",
        "0",
        "7",
        "--width",
        "48",
        "--height",
        "48",
        "--tracking-uri",
        _uri(tmp_path),
        "--out",
        str(out),
        timeout=300,
    )
    assert got.returncode == 0, got.stderr[-2000:]
    assert out.read_bytes()[:4] == b"\x89PNG" and f"wrote {out}" in got.stdout


def test_spot_eval_plays_whole_episodes_for_runs_logged_before_eval_max_steps(monkeypatch):
    from spot import tracking
    from spot.run import pipeline

    monkeypatch.setattr(tracking, "load_artifact_text", lambda *a: "eval:\n  episodes: 1\n  every: 100\n")
    assert pipeline._logged_max_steps("r", None, 100) == 0  # resolved from the tiny preset, not logged
    monkeypatch.setattr(tracking, "load_artifact_text", lambda *a: "eval:\n  episodes: 1\n  max_steps: 100\n")
    assert pipeline._logged_max_steps("r", None, 100) == 100
