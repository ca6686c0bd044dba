"""Issue 40, fewer compiles: rows padded to a bucket (spot/padding.py) leave every number unchanged
and let the datasets of an environment share their programs; compiles are counted (spot/compiles.py).

Levels: the bucket sizes by hand; the draws of a traced bound against a static one; each learner's
chunk (IQL, IPL, HPL's two phases) and relabelling on padded against unpadded data, state and
metrics equal bit for bit; then whole tiny runs: padded against unpadded (scores and losses to the
last digit), and two datasets of one environment (Hopper, 1,498 and 4,000 rows) that compile the
IQL chunk once in a process.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import mlflow
import numpy as np
import pytest

from spot import compiles, config, padding, pipeline
from spot.config import IPLConfig, IQLConfig, MRConfig, RelabelConfig
from spot.data import registry
from spot.policy import ipl, iql
from spot.reward import hpl, hpl_nets, mr, relabel
from tests.conftest import make_dataset
from tests.test_hpl import TINY as HPL_TINY
from tests.test_hpl import random_pairs


def _equal_trees(a, b) -> None:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _unpadded(monkeypatch) -> None:
    """spot's code as it was before padding: no bucket, plain arrays (static row counts)."""
    monkeypatch.setattr(padding, "bucket", lambda n, min_rows=0: n)
    monkeypatch.setattr(padding, "padded", lambda tree: tree)


# --------------------------------------------------------------------------- sizes and draws
def test_bucket_sizes():
    assert padding.MIN_ROWS == 16384
    assert [padding.bucket(n) for n in (0, 1, 118, 1498, 4000, 16384)] == [16384] * 6
    assert padding.bucket(16385) == 32768 and padding.bucket(402_000) == 524_288
    assert padding.bucket(2_000_000) == 2_097_152 and padding.bucket(5, min_rows=1) == 8
    x = np.arange(6, dtype=np.float32).reshape(3, 2)
    rows = padding.padded({"x": x, "m": np.ones(3, bool)})
    assert int(rows.count) == 3 and rows.data["x"].shape == (16384, 2) and rows.data["m"].dtype == bool
    np.testing.assert_array_equal(rows.data["x"][:3], x)
    assert not rows.data["x"][3:].any() and not rows.data["m"][3:].any()
    with pytest.raises(ValueError, match="different numbers of rows"):
        padding.pad_rows((np.zeros(3), np.zeros(4)))


@pytest.mark.parametrize("n", [1, 7, 1498, 4000, 100_003, 2**31 - 1])
def test_a_traced_bound_draws_what_a_static_one_draws(n):
    """jax.random.randint and HPL's randint: a bound passed as a traced int32 gives the same
    integers as the same bound known when tracing (the padded runs' draws)."""
    key = jax.random.key(n % 97)
    for draw in (
        lambda k, m: jax.random.randint(k, (4096,), 0, m),
        lambda k, m: hpl_nets.randint(k, (4096,), m),
    ):
        static = np.asarray(jax.jit(lambda k, d=draw: d(k, n))(key))
        traced = np.asarray(jax.jit(draw)(key, np.int32(n)))
        np.testing.assert_array_equal(static, traced)
        assert static.min() >= 0 and static.max() < n


# --------------------------------------------------------------------------- each learner's chunk
def _transitions(n: int, seed: int = 0) -> iql.Transitions:
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
    return iql.Transitions(f(n, 3), np.tanh(f(n, 2)), f(n), f(n, 3), (rng.random(n) > 0.1).astype(np.float32))


def test_iql_chunk_padded_equals_unpadded_and_compiles_once_per_bucket():
    cfg = IQLConfig(hidden=(16, 16), batch_size=8, steps=30, chunk=10)
    data = _transitions(37)
    chunk = iql.make_train_chunk(cfg)
    out = {}
    for name, arg in (("plain", data), ("padded", padding.padded(data))):
        state = iql.init_state(jax.random.key(1), 3, 2, cfg)
        for c in range(3):  # a short last chunk included
            state, metrics = chunk(
                state, 10 if c < 2 else 7, jax.device_put(arg), jax.random.fold_in(jax.random.key(2), c)
            )
        out[name] = (state, metrics)
    _equal_trees(out["plain"], out["padded"])
    # Another dataset of the same dims and a different size: the same program.
    before = chunk._cache_size()
    with compiles.counting() as count:
        state = iql.init_state(jax.random.key(1), 3, 2, cfg)
        chunk(state, 10, jax.device_put(padding.padded(_transitions(1000, 1))), jax.random.key(3))
    assert chunk._cache_size() == before and count.named("chunk") == 0


def test_vmapped_iql_chunk_takes_padded_rows_with_per_seed_rewards():
    cfg = IQLConfig(hidden=(16,), batch_size=8, steps=10, chunk=10)
    data = _transitions(29)
    rew = np.stack([data.rew, 2 * data.rew])
    keys = jax.random.split(jax.random.key(0), 2)
    plain = data._replace(rew=rew)
    padded = padding.Rows(padding.pad_rows(plain._replace(rew=rew.T)), np.int32(29))
    padded = padded._replace(data=padded.data._replace(rew=padded.data.rew.T))  # rew [S, bucket]
    out = []
    for arg, flag in ((plain, False), (padded, True)):
        states = iql.init_state(keys, 3, 2, cfg)
        out.append(iql.make_vmapped_train_chunk(cfg, True, flag)(states, 10, jax.device_put(arg), keys))
    _equal_trees(out[0], out[1])


def test_ipl_chunk_padded_equals_unpadded():
    iql_cfg = IQLConfig(hidden=(16,), batch_size=16, chunk=20, discount=0.9)
    ipl_cfg = IPLConfig(feedback_batch=4, subsample=4, chi2_coeff=20.0)
    rng = np.random.default_rng(0)
    f = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
    batch = {"obs_1": f(12, 6, 3), "act_1": np.tanh(f(12, 6, 2)), "obs_2": f(12, 6, 3), "act_2": np.tanh(f(12, 6, 2))}
    feedback = ipl.feedback_from({**batch, "label": np.array([0, 1, 0.5] * 4, np.float32)})
    data = _transitions(50)
    out = []
    for arg in (data, padding.padded(data)):
        state = ipl.init_state(jax.random.key(0), 3, 2, iql_cfg)
        out.append(ipl.make_train_chunk(iql_cfg, ipl_cfg)(state, 20, jax.device_put(arg), feedback, jax.random.key(5)))
    _equal_trees(out[0], out[1])


def test_hpl_phases_padded_equal_unpadded(monkeypatch):
    ds = make_dataset([30, 5, 40, 3, 22])
    tb, eb = random_pairs(12, 6, 0), random_pairs(5, 6, 1)
    params, history = hpl.train_hpl(jax.random.key(0), ds, tb, eb, HPL_TINY)
    assert isinstance(hpl.unlabelled(ds, padded=True), padding.Rows)
    _unpadded(monkeypatch)
    assert isinstance(hpl.unlabelled(ds, padded=True), hpl.Unlabelled)
    params_0, history_0 = hpl.train_hpl(jax.random.key(0), ds, tb, eb, HPL_TINY)
    _equal_trees(params, params_0)
    for name in ("vae_loss", "vae_kl", "train_loss", "train_reg", "eval_loss", "eval_prior_loss"):
        assert history[name] == history_0[name], name
    a = relabel.relabel_hpl(params, ds, HPL_TINY, jax.random.key(1), batch_size=32)
    monkeypatch.undo()
    np.testing.assert_array_equal(a, relabel.relabel_hpl(params, ds, HPL_TINY, jax.random.key(1), batch_size=32))


def test_relabelling_padded_equals_unpadded(monkeypatch):
    ds = make_dataset([30, 5, 40, 3, 22], obs_dim=3, act_dim=2)
    cfg = MRConfig(hidden=(16,))
    model = mr.MR(cfg)
    params = mr.init_params(jax.random.key(0), cfg, 3, 2)
    relabel_cfg = RelabelConfig(window=4, batch_size=8)
    padded = relabel.relabel_rewards(model, params, ds, relabel_cfg, progress=False)
    _unpadded(monkeypatch)
    plain = relabel.relabel_rewards(model, params, ds, relabel_cfg, progress=False)
    np.testing.assert_array_equal(padded.rewards, plain.rewards)
    assert padded.rewards.shape == (len(ds),)


# --------------------------------------------------------------------------- whole runs
TINY_HOPPER = ["budget=tiny", "data.size=tiny", "iql.steps=200", "eval.every=100", "eval.episodes=2"]


def _run(tmp_path: Path, name: str, *overrides: str) -> dict[str, list[float]]:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = config.load(
        None, [*TINY_HOPPER, f"data.name={name}", f"tracking.uri={uri}", "tracking.experiment=t", *overrides]
    )
    run_id = pipeline.run(cfg, progress=False)["run_id"]
    client = mlflow.tracking.MlflowClient(uri)
    metrics = client.get_run(run_id).data.metrics
    keys = [k for k in metrics if k.startswith(("iql/", "reward/", "eval/score")) and not k.endswith("_s")]
    return {k: [m.value for m in client.get_metric_history(run_id, k)] for k in sorted(keys)}


@pytest.fixture(scope="module")
def hopper_tiny():
    """The tiny Hopper datasets of the Table 1 smoke launch (SPOT_DATA_DIR=/work/cache/data has them)."""
    return [
        registry.build(name, "tiny", 0, progress=False) for name in ("hopper-medium-replay", "hopper-medium-expert")
    ]


def test_a_padded_run_equals_an_unpadded_one(tmp_path, monkeypatch, spot_dirs, hopper_tiny):
    """A seed-0 tiny PT run (reward model, relabelling, IQL, evaluations): every score and loss
    equal to the last digit with and without padding (fresh stage caches, so both relabel)."""
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "cache-a"))
    padded = _run(tmp_path, "hopper-medium-replay", "method=pt")
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "cache-b"))
    _unpadded(monkeypatch)
    plain = _run(tmp_path, "hopper-medium-replay", "method=pt")
    assert {"eval/score", "iql/critic_loss", "iql/actor_loss", "reward/best_eval_acc"} <= set(padded)
    assert padded == plain


def test_two_datasets_of_an_env_compile_the_iql_chunk_once(tmp_path, monkeypatch, spot_dirs, hopper_tiny):
    """In one process, warm: an Oracle run on hopper-medium-replay (1,498 rows) then one on
    hopper-medium-expert (4,000 rows) of the same config: the second compiles nothing (before
    padding it compiled the IQL chunk again)."""
    assert [registry.read_card(p)["transitions"] for p in hopper_tiny] == [1498, 4000]
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "cache"))
    _run(tmp_path, "hopper-medium-replay", "method=oracle")
    with compiles.counting() as count:
        _run(tmp_path, "hopper-medium-expert", "method=oracle")
    assert count.named("chunk") == 0, count.programs
    assert count.total == 0, count.programs
    # Unpadded, the second dataset's chunk is a new program.
    _unpadded(monkeypatch)
    with compiles.counting() as count:
        _run(tmp_path, "hopper-medium-expert", "method=oracle", "seed=1")
    assert count.named("chunk") == 1, count.programs


def test_counting_compiles_and_cache_hits():
    f = jax.jit(lambda x: x * 3 + 1)
    five, six = jnp.ones(5), jnp.ones(6)
    with compiles.counting() as outer:
        with compiles.counting() as inner:
            f(five)
            f(five)  # jit's own cache: nothing handed to XLA
        f(six)
    assert inner.named("<lambda>") == 1 and inner.total == 1
    assert outer.total == 2 and outer.compiled + outer.cache_hits == 2 and outer.seconds > 0
    assert outer.metrics() == {"trial/compiles": 2.0, "trial/compile_cache_hits": float(outer.cache_hits)}
    assert dataclasses.is_dataclass(outer)


def test_a_trial_clock_counts_programs_and_the_breakdown_prints_them():
    """spot.phases' clock (a sweep trial's) counts the programs handed to XLA; the sweep's
    breakdown prints their total (trial/compiles, trial/compile_cache_hits)."""
    from spot import phases
    from spot.sweep.summary import Row, format_breakdown

    phases.listen_to_compiles()
    g = jax.jit(lambda x: jnp.sin(x) * 2)
    seven = jnp.ones(7)
    with phases.measure() as clock:
        g(seven)
        g(seven)
    assert clock.compiles == 1 and 0 <= clock.cache_hits <= 1 and clock.totals["compile"] > 0
    timing = {"time/trial_wall_s": 10.0, "time/trial_compile_s": 4.0, "trial/compiles": 30.0}
    rows = [
        Row(
            {"method": "oracle"},
            s,
            f"k{s}",
            "FINISHED",
            1.0,
            "",
            f"r{s}",
            1,
            f"t{s}",
            {**timing, "trial/compile_cache_hits": float(s)},
        )
        for s in (0, 5)
    ]
    assert "programs: 60 compiled or loaded, 5 of them from the persistent compilation cache" in format_breakdown(
        rows, ("method",)
    )


def test_reward_model_inits_compile_once_per_config_and_sizes():
    """MR's and PT's init programs are kept per (config, obs_dim, act_dim): a second run's init in
    the process (another dataset of the env, a reused sweep trial) compiles nothing, same params."""
    from spot.config import PTConfig
    from spot.reward import pt

    key = jax.random.key(0)
    for module, cfg in ((mr, MRConfig(hidden=(8,))), (pt, PTConfig(embd_dim=16, n_layer=1, n_head=2))):
        first = module.init_params(key, cfg, 3, 2)
        with compiles.counting() as count:
            again = module.init_params(key, cfg, 3, 2)
        assert count.total == 0, count.programs
        _equal_trees(first, again)


_CHUNK_ON_ROWS = """
import json, sys
from spot import runtime
runtime.configure()
import jax, numpy as np
from spot import compiles, padding
from spot.config import IQLConfig
from spot.policy import iql
n = int(sys.argv[1])
rng = np.random.default_rng(n)
cols = [rng.normal(size=(n, *s)).astype(np.float32) for s in ((3,), (2,), (), (3,))]
data = iql.Transitions(*cols, np.ones(n, np.float32))
cfg = IQLConfig(hidden=(16, 16), batch_size=8, steps=20, chunk=10)
state = iql.init_state(jax.random.key(1), 3, 2, cfg)
rows, key = jax.device_put(padding.padded(data)), jax.random.key(2)
with compiles.counting() as count:
    iql.make_train_chunk(cfg)(state, 10, rows, key)
print(json.dumps({"chunk": count.named("chunk"), "hits": count.cache_hits}))
"""


def test_a_second_process_on_another_dataset_size_loads_the_chunk_from_the_persistent_cache(tmp_path):
    """Across processes (a sweep's trials): the IQL chunk one process compiled for padded rows of
    37 transitions is the program another process needs for 1,000 (spot.runtime's persistent
    compilation cache, in a fresh folder here)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_FLAGS", "SPOT_JAX_CACHE"))}
    env["SPOT_CACHE_DIR"] = str(tmp_path / "cache")
    out = []
    for n in (37, 1000):
        proc = subprocess.run(
            [sys.executable, "-c", _CHUNK_ON_ROWS, str(n)], capture_output=True, text=True, env=env, timeout=300
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    assert out[0] == {"chunk": 1, "hits": 0}
    assert out[1] == {"chunk": 1, "hits": 1}  # handed to XLA once: found in the cache
