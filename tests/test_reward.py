"""Tests of the reward models (MR, PT), their training loop and dataset relabelling.

Levels (STYLE.md rule 15): numeric loss values by hand, PT attention maths on a tiny model, jit vs
no-jit, one trace per training run, learning tests with thresholds, relabelling against direct
forward passes, and the non-finite-loss error.
"""

from __future__ import annotations

import dataclasses
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import spot  # noqa: F401  (sets the XLA flag before jax is imported)
from spot import SpotError
from spot.config import MRConfig, PTConfig, RelabelConfig, RewardConfig
from spot.nets import MLP, Dropout, param_count
from spot.reward import mr, pt, relabel, train, update, vmapped
from spot.reward.mr import MR
from spot.reward.pt import PT
from tests.conftest import make_dataset

PT_TINY = PTConfig(embd_dim=16, n_layer=2, n_head=2, dropout=0.1, pref_attn_dim=8, max_timestep=50)
MR_TINY = MRConfig(hidden=(32, 32), lr=3e-3)
OBS, ACT = 4, 2


def synthetic_pairs(num_pairs: int, length: int, seed: int) -> dict[str, np.ndarray]:
    """Segments whose true return is sum_t (s_t . v + a_t . u); label 1 iff segment 2's is higher."""
    rng = np.random.default_rng(seed)
    v, u = np.linspace(-1.0, 1.0, OBS), np.array([1.0, -0.5])
    batch: dict[str, np.ndarray] = {}
    for s in ("1", "2"):
        offset = rng.normal(size=(num_pairs, 1, OBS))  # per-segment shift: returns differ clearly
        batch[f"obs_{s}"] = (rng.normal(size=(num_pairs, length, OBS)) + offset).astype(np.float32)
        batch[f"act_{s}"] = rng.uniform(-1, 1, size=(num_pairs, length, ACT)).astype(np.float32)
        batch[f"timesteps_{s}"] = np.tile(np.arange(1, length + 1, dtype=np.int32), (num_pairs, 1))
    ret = {s: (batch[f"obs_{s}"] @ v + batch[f"act_{s}"] @ u).sum(axis=1) for s in ("1", "2")}
    batch["label"] = (ret["2"] > ret["1"]).astype(np.float32)
    return batch


@pytest.fixture(scope="module")
def pt_params() -> dict:
    return pt.init_params(jax.random.key(0), PT_TINY, OBS, ACT)


pt_forward = jax.jit(pt.forward, static_argnums=1)


def segments(batch: int, length: int, seed: int) -> tuple[jax.Array, ...]:
    k1, k2 = jax.random.split(jax.random.key(seed))
    obs = jax.random.normal(k1, (batch, length, OBS))
    act = jax.random.uniform(k2, (batch, length, ACT), minval=-1, maxval=1)
    ts = jnp.tile(jnp.arange(1, length + 1), (batch, 1))
    return obs, act, ts, jnp.ones((batch, length))


# --------------------------------------------------------------------------- (a) loss by hand
def test_pref_loss_by_hand():
    logit_1 = jnp.array([0.0, 1.0, 2.0, 0.5])
    logit_2 = jnp.array([1.0, 1.0, 0.0, -0.5])
    label = jnp.array([1.0, 0.5, 1.0, 0.0])
    loss, acc = update.pref_loss(logit_1, logit_2, label)
    expected = [
        math.log(1 + math.exp(-1.0)),  # -log sigmoid(1): segment 2 preferred and ahead by 1
        math.log(2.0),  # tie with equal logits: -(0.5 log 0.5 + 0.5 log 0.5)
        math.log(1 + math.exp(2.0)),  # -log sigmoid(-2): segment 2 preferred but behind by 2
        math.log(1 + math.exp(-1.0)),  # label 0: -log sigmoid(l1 - l2) = -log sigmoid(1)
    ]
    assert float(loss) == pytest.approx(np.mean(expected), rel=1e-6)
    assert float(acc) == pytest.approx(2 / 3)  # non-tie pairs 0, 2, 3; pair 2 is wrong

    tie_only, tie_acc = update.pref_loss(jnp.array([3.0]), jnp.array([1.0]), jnp.array([0.5]))
    assert float(tie_only) == pytest.approx(0.5 * math.log(1 + math.exp(2.0)) + 0.5 * math.log(1 + math.exp(-2.0)))
    assert float(tie_acc) == 0.0


# --------------------------------------------------------------------------- nets
def test_mlp_layers_and_dropout():
    mlp = MLP(hidden=(8, 8), out_dim=3, output_kernel_init=nn.initializers.zeros)
    params = jax.jit(mlp.init)(jax.random.key(0), jnp.ones((1, 5)))
    assert param_count(params) == (5 * 8 + 8) + (8 * 8 + 8) + (8 * 3 + 3)
    assert np.all(jax.jit(mlp.apply)(params, jnp.ones((2, 5))) == 0.0)  # zero-initialised output layer
    trunk = MLP(hidden=(4,), activate_final=True, activation=lambda x: -jnp.abs(x))
    trunk_params = jax.jit(trunk.init)(jax.random.key(1), jnp.ones((1, 3)))
    assert np.all(jax.jit(trunk.apply)(trunk_params, jnp.ones((6, 3))) <= 0.0)

    x = jnp.ones((200, 500))
    drop = jax.jit(lambda key: Dropout(0.1).apply({}, x, deterministic=False, rngs={"dropout": key}))
    y = drop(jax.random.key(2))
    assert float((y == 0).mean()) == pytest.approx(0.1, abs=0.005)
    assert np.allclose(y[y != 0], 1 / 0.9)
    assert not np.array_equal(y, drop(jax.random.key(3)))
    assert Dropout(0.1).apply({}, x, deterministic=True) is x


# --------------------------------------------------------------------------- (b) PT attention
def test_pt_attention_by_hand(pt_params):
    obs, act, ts, mask = segments(2, 8, seed=1)
    r_hat, w, logit = pt_forward(pt_params, PT_TINY, obs, act, ts, mask)
    assert r_hat.shape == w.shape == (2, 8) and logit.shape == (2,)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(logit, (w * r_hat).sum(axis=1), rtol=1e-5, atol=1e-6)

    # Recompute the preference-attention layer by hand from the transformer output.
    hidden = jax.jit(
        lambda *a: pt.make_model(PT_TINY).apply(
            pt_params, *a, True, False, method=pt.PreferenceTransformer._state_hidden
        )
    )(obs, act, ts, mask)
    kernel = pt_params["params"]["pref_head"]["kernel"]
    bias = pt_params["params"]["pref_head"]["bias"]
    head = np.asarray(hidden) @ np.asarray(kernel) + np.asarray(bias)
    p = PT_TINY.pref_attn_dim
    q, k, r = head[..., :p], head[..., p : 2 * p], head[..., 2 * p]
    scores = np.einsum("btp,bjp->btj", q, k)  # no 1/sqrt(P)
    attn = np.exp(scores - scores.max(-1, keepdims=True))
    attn /= attn.sum(-1, keepdims=True)
    z = np.einsum("btj,bj->bt", attn, r)
    np.testing.assert_allclose(r_hat, r, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(w, attn.mean(axis=1), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(logit, z.mean(axis=1), rtol=1e-5, atol=1e-6)


def test_pt_causal_and_last_step(pt_params):
    obs, act, ts, mask = segments(2, 8, seed=2)
    r_hat, w, _ = pt_forward(pt_params, PT_TINY, obs, act, ts, mask)
    t = 4
    obs2 = obs.at[:, t + 1].add(3.0)
    act2 = act.at[:, t + 1].add(1.0)
    r_hat2, w2, _ = pt_forward(pt_params, PT_TINY, obs2, act2, ts, mask)
    np.testing.assert_allclose(r_hat2[:, : t + 1], r_hat[:, : t + 1], rtol=1e-5, atol=1e-6)
    assert np.all(np.abs(r_hat2[:, t + 1] - r_hat[:, t + 1]) > 1e-4)
    assert not np.allclose(w2[:, :t], w[:, :t])  # the preference attention is bidirectional
    last = jax.jit(pt.last_step_reward, static_argnums=1)(pt_params, PT_TINY, obs, act, ts, mask)
    np.testing.assert_allclose(last, r_hat[:, -1], rtol=1e-5, atol=1e-6)


def test_pt_reward_at_t_reads_the_action_at_t(pt_params):
    """Changing only a_t changes r_hat_t (PT reads r_hat_t at the action token of step t, after
    s_t) and leaves r_hat_<t alone; a model reading r_hat_t at the state token would not see a_t."""
    obs, act, ts, mask = segments(2, 8, seed=5)
    r_hat, _, _ = pt_forward(pt_params, PT_TINY, obs, act, ts, mask)
    for t in (0, 3, 7):
        act2 = act.at[:, t].add(1.0)
        r_hat2, _, _ = pt_forward(pt_params, PT_TINY, obs, act2, ts, mask)
        np.testing.assert_allclose(r_hat2[:, :t], r_hat[:, :t], rtol=1e-5, atol=1e-6)
        assert np.all(np.abs(r_hat2[:, t] - r_hat[:, t]) > 1e-4), t


def test_pt_padding_mask(pt_params):
    obs, act, ts, mask = segments(2, 8, seed=3)
    real = 5
    obs_pad = obs.at[:, real:].set(100.0)  # garbage in the padded steps
    mask_pad = mask.at[:, real:].set(0.0)
    ts_pad = ts.at[:, real:].set(0)
    r_pad, w_pad, logit_pad = pt_forward(pt_params, PT_TINY, obs_pad, act, ts_pad, mask_pad)
    r, w, logit = pt_forward(pt_params, PT_TINY, obs[:, :real], act[:, :real], ts[:, :real], mask[:, :real])
    np.testing.assert_allclose(r_pad[:, :real], r, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(w_pad[:, :real], w, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(w_pad[:, real:], 0.0)
    np.testing.assert_allclose(logit_pad, logit, rtol=1e-5, atol=1e-6)


def test_pt_dropout_and_bfloat16(pt_params):
    obs, act, ts, mask = segments(2, 8, seed=4)
    r_det, _, _ = pt_forward(pt_params, PT_TINY, obs, act, ts, mask)
    key = jax.random.key(5)
    r_a, _, _ = pt_forward(pt_params, PT_TINY, obs, act, ts, mask, key)
    r_b, _, _ = pt_forward(pt_params, PT_TINY, obs, act, ts, mask, key)
    np.testing.assert_array_equal(r_a, r_b)
    assert not np.allclose(r_a, r_det)
    bf16 = dataclasses.replace(PT_TINY, dtype="bfloat16")
    r16, w16, logit16 = pt_forward(pt_params, bf16, obs, act, ts, mask)
    assert r16.dtype == w16.dtype == logit16.dtype == jnp.float32
    np.testing.assert_allclose(r16, r_det, atol=0.1)


# --------------------------------------------------------------------------- (c) jit vs no-jit
def test_jit_matches_nojit(pt_params):
    obs, act, ts, mask = segments(2, 4, seed=6)
    jitted = pt_forward(pt_params, PT_TINY, obs, act, ts, mask)
    with jax.disable_jit():
        eager = pt.forward(pt_params, PT_TINY, obs, act, ts, mask)
        eager_loss = update.pref_loss(eager[2][:1], eager[2][1:], jnp.array([1.0]))
    for a, b in zip(jitted, eager, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    jit_loss = jax.jit(update.pref_loss)(jitted[2][:1], jitted[2][1:], jnp.array([1.0]))
    np.testing.assert_allclose(jit_loss, eager_loss, rtol=1e-6)


# --------------------------------------------------------------------------- (d) one trace
def test_train_chunk_compiles_once_with_partial_last_chunk():
    cfg = RewardConfig(steps=25, batch_size=8, eval_every=10)
    args = (MR(MR_TINY), jax.random.key(0), synthetic_pairs(32, 5, 0), synthetic_pairs(8, 5, 1), cfg)
    _, history = train.train_reward_model(*args, progress=False)
    chunk = update.make_train_chunk(MR(MR_TINY), 8, 10, 25)  # the run's chunk (kept per model and sizes)
    assert chunk._cache_size() == 1
    assert history["step"] == [10, 20, 25]
    assert len(history["eval_loss"]) == 3 and history["best_step"] in history["step"]
    # Same config and shapes again (another seed): the compiled programs are reused. (The
    # evaluation program is kept per model, so earlier tests in this process may have compiled it
    # for other shapes: count what this second training adds.)
    evaluate = update.make_evaluate(MR(MR_TINY))
    compiled = evaluate._cache_size()
    _, again = train.train_reward_model(*args[:1], jax.random.key(1), *args[2:], progress=False)
    assert chunk._cache_size() == 1 and evaluate._cache_size() == compiled >= 1


@pytest.mark.parametrize("kind", ["mr", "pt"])
def test_seeds_vmapped_equal_one_training_per_seed(kind):
    """train_reward_models: each seed (its own key and its own pairs) gets the parameters and the
    history that train_reward_model gives it alone, to float tolerance; the seeds differ."""
    model = MR(MR_TINY) if kind == "mr" else PT(PT_TINY)
    cfg = RewardConfig(steps=25, batch_size=8, eval_every=10)
    keys = [jax.random.key(3), jax.random.key(11)]
    trains = [synthetic_pairs(32, 5, 0), synthetic_pairs(32, 5, 7)]
    evals = [synthetic_pairs(12, 5, 1), synthetic_pairs(12, 5, 8)]
    together = vmapped.train_reward_models(model, keys, trains, evals, cfg, progress=False)
    assert len(together) == 2
    for s in range(2):
        params, history = train.train_reward_model(model, keys[s], trains[s], evals[s], cfg, progress=False)
        got_params, got = together[s]
        assert got["step"] == history["step"] == [10, 20, 25]
        assert got["best_step"] == history["best_step"] and got["steps"] == history["steps"] == 25
        for name in ("train_loss", "train_acc", "eval_loss", "eval_acc"):
            np.testing.assert_allclose(got[name], history[name], rtol=1e-4, atol=1e-5, err_msg=name)
        # The preference loss cannot see a constant added to every r_hat (the output bias, a dead
        # unit's bias): Adam turns their rounding-level gradients into full-size steps, so compare
        # what the loss sees, the rewards minus one constant (their mean), not the raw parameters.
        seg = (evals[s]["obs_1"], evals[s]["act_1"], evals[s]["timesteps_1"], np.ones((12, 5), np.float32))
        want = np.asarray(train.model_fn(model, params)(*seg)[0])
        have = np.asarray(train.model_fn(model, got_params)(*seg)[0])
        centred = [r - r.mean() for r in (want, have)]
        np.testing.assert_allclose(centred[1], centred[0], rtol=1e-3, atol=1e-4)
        assert np.ptp(centred[0]) > 0.01  # the rewards are not flat
    assert together[0][1]["eval_loss"] != together[1][1]["eval_loss"]


def test_seeds_vmapped_need_pairs_of_one_shape():
    cfg = RewardConfig(steps=5, batch_size=8, eval_every=5)
    with pytest.raises(SpotError, match="seed 1's preference pairs differ in shape from seed 0's"):
        vmapped.train_reward_models(
            MR(MR_TINY),
            [jax.random.key(0), jax.random.key(1)],
            [synthetic_pairs(32, 5, 0), synthetic_pairs(24, 5, 1)],
            [None, None],
            cfg,
            progress=False,
        )


def test_bad_batches_raise_spot_error():
    batch = synthetic_pairs(8, 5, 0)
    with pytest.raises(SpotError, match="missing key"):
        train.pref_pairs({k: v for k, v in batch.items() if k != "act_2"})
    with pytest.raises(SpotError, match="labels must be"):
        train.pref_pairs({**batch, "label": np.full(8, 2.0, np.float32)})
    with pytest.raises(SpotError, match="max_timestep"):
        train.train_reward_model(
            PT(PT_TINY),
            jax.random.key(0),
            {**batch, "timesteps_1": batch["timesteps_1"] + 60},
            None,
            RewardConfig(steps=1),
            progress=False,
        )


# --------------------------------------------------------------------------- (e) learning
@pytest.mark.slow
def test_mr_learns_synthetic_preferences():
    train_b, eval_b = synthetic_pairs(256, 10, 0), synthetic_pairs(128, 10, 1)
    cfg = RewardConfig(steps=200, batch_size=32, eval_every=50)
    params, history = train.train_reward_model(MR(MR_TINY), jax.random.key(0), train_b, eval_b, cfg, progress=False)
    assert history["best_eval_acc"] >= 0.9
    assert history["eval_loss"][-1] < history["eval_loss"][0] < math.log(2)
    # The returned parameters are the best-on-eval ones.
    f = train.model_fn(MR(MR_TINY), params)
    mask = np.ones(eval_b["timesteps_1"].shape, np.float32)
    logits = [
        f(eval_b[f"obs_{s}"], eval_b[f"act_{s}"], eval_b[f"timesteps_{s}"], mask)[0].mean(axis=1) for s in ("1", "2")
    ]
    loss, _ = update.pref_loss(*logits, jnp.asarray(eval_b["label"]))
    assert float(loss) == pytest.approx(history["best_eval_loss"], rel=1e-4)


@pytest.mark.slow
def test_pt_learns_synthetic_preferences():
    train_b, eval_b = synthetic_pairs(512, 10, 0), synthetic_pairs(128, 10, 1)
    cfg = RewardConfig(steps=300, batch_size=32, eval_every=100)
    pt_cfg = PTConfig(embd_dim=16, n_layer=1, n_head=2, pref_attn_dim=16, warmup_steps=10, lr=1e-3, max_timestep=50)
    _, history = train.train_reward_model(PT(pt_cfg), jax.random.key(0), train_b, eval_b, cfg, progress=False)
    assert history["best_eval_acc"] >= 0.8
    assert history["best_eval_loss"] < 0.45


# --------------------------------------------------------------------------- (f) relabelling
def test_relabel_mr_matches_per_step_reward():
    ds = make_dataset([7, 12, 3])
    params = mr.init_params(jax.random.key(0), MR_TINY, OBS, ACT)
    direct = mr.per_step_reward(params, jnp.asarray(ds.observations), jnp.asarray(ds.actions), MR_TINY)
    for mode in ("chunked", "sliding"):
        out = relabel.relabel_rewards(
            MR(MR_TINY), params, ds, RelabelConfig(mode=mode, window=4, batch_size=2), progress=False
        )
        assert out.weights is None and out.rewards.dtype == np.float32
        np.testing.assert_allclose(out.rewards, direct, rtol=1e-6, atol=1e-7)


def test_relabel_pt_chunked_and_sliding(pt_params):
    lengths = [7, 2, 5]  # chunks of 3: (3, 3, 1), (2,), (3, 2); sliding windows of 1..3 steps
    ds = make_dataset(lengths, seed=1)
    window = 3
    chunked = relabel.relabel_rewards(
        PT(PT_TINY), pt_params, ds, RelabelConfig(window=window, batch_size=3), progress=False
    )
    sliding = relabel.relabel_rewards(
        PT(PT_TINY), pt_params, ds, RelabelConfig(mode="sliding", window=window, batch_size=5), progress=False
    )
    f = train.model_fn(PT(PT_TINY), pt_params)

    def direct(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ts = np.arange(1, rows.size + 1)[None]
        r, w = f(ds.observations[rows][None], ds.actions[rows][None], ts, np.ones((1, rows.size)))
        return np.asarray(r[0]), np.asarray(w[0])

    start = 0
    for length in lengths:
        for c in range(start, start + length, window):  # chunked: one forward pass per chunk
            rows = np.arange(c, min(c + window, start + length))
            r, w = direct(rows)
            np.testing.assert_allclose(chunked.rewards[rows], r, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(chunked.weights[rows], w, rtol=1e-5, atol=1e-6)
            assert chunked.weights[rows].sum() == pytest.approx(1.0, rel=1e-5)
        for t in range(start, start + length):  # sliding: causal window ending at t
            r, _ = direct(np.arange(max(start, t - window + 1), t + 1))
            assert sliding.rewards[t] == pytest.approx(r[-1], rel=1e-5, abs=1e-6)
        start += length
    assert sliding.weights is None
    with pytest.raises(SpotError, match="max_timestep"):
        relabel.relabel_rewards(PT(PT_TINY), pt_params, ds, RelabelConfig(window=51), progress=False)


def test_normalize_rewards_by_hand():
    ds = make_dataset([3, 2])
    rewards = np.array([1.0, 2.0, 3.0, 4.0, 5.0], np.float32)  # episode returns 6 and 9
    np.testing.assert_allclose(relabel.normalize_rewards(rewards, ds, "iql"), rewards * 1000 / 3, rtol=1e-6)
    np.testing.assert_allclose(relabel.normalize_rewards(rewards, ds, "pt"), rewards * 1000 / 3 + 0.5, rtol=1e-6)
    np.testing.assert_array_equal(relabel.normalize_rewards(rewards, ds, "none"), rewards)
    # wiserl: 1000 / max(|R_min|, |R_max|, R_max - R_min, 1) = 1000 / max(6, 9, 3, 1) = 1000 / 9
    np.testing.assert_allclose(relabel.normalize_rewards(rewards, ds, "wiserl"), rewards * 1000 / 9, rtol=1e-6)
    # minmax: steps to [0, 1] ((r - 1) / 4 -> returns 0.75 and 1.75, spread 1), then * 1000 / 1
    np.testing.assert_allclose(relabel.normalize_rewards(rewards, ds, "minmax"), (rewards - 1) / 4 * 1000, rtol=1e-6)
    assert relabel.normalize_rewards(-rewards, ds, "minmax").min() == 0.0
    small = np.array([0.1, 0.1, 0.1, 0.2, 0.1], np.float32)  # returns 0.3 and 0.3: all below 1 -> scale 1
    np.testing.assert_allclose(relabel.normalize_rewards(small, ds, "wiserl"), small * 1000, rtol=1e-6)
    with pytest.raises(SpotError, match="episode returns are equal"):
        relabel.normalize_rewards(np.array([1, 1, 1, 1.5, 1.5], np.float32), ds, "pt")


# --------------------------------------------------------------------------- (g) non-finite
def test_nan_loss_names_the_step():
    num_pairs, batch_size, bad = 16, 4, 11
    data = synthetic_pairs(num_pairs, 5, 0)
    data["obs_2"][bad, 2, 0] = np.nan
    key = jax.random.key(3)
    # First step whose minibatch draws pair `bad` (same key schedule as train_reward_model).
    train_key = jax.random.split(key)[1]
    drawn = jax.jit(
        jax.vmap(
            lambda s: update.batch_indices(jax.random.split(jax.random.fold_in(train_key, s))[0], num_pairs, batch_size)
        )
    )(jnp.arange(100))
    first = int(np.flatnonzero((np.asarray(drawn) == bad).any(axis=1))[0])
    cfg = RewardConfig(steps=100, batch_size=batch_size, eval_every=100)
    with pytest.raises(train.NonFiniteError) as err:
        train.train_reward_model(MR(MR_TINY), key, data, synthetic_pairs(4, 5, 1), cfg, progress=False)
    assert (err.value.step, err.value.loss_name) == (first, "reward/train_loss")
    assert f"at step {first}" in str(err.value)

    eval_b = synthetic_pairs(4, 5, 1)
    eval_b["act_1"][0, 0, 0] = np.inf
    with pytest.raises(train.NonFiniteError) as err:
        train.train_reward_model(MR(MR_TINY), key, synthetic_pairs(num_pairs, 5, 0), eval_b, cfg, progress=False)
    assert (err.value.step, err.value.loss_name) == (100, "reward/eval_loss")


def test_training_length_in_pt_epochs_is_the_steps_taken():
    """reward.length=epochs: the run takes epochs * (N // batch + 1) steps (PT repo)."""
    batch = synthetic_pairs(10, 5, 0)
    cfg = RewardConfig(length="epochs", epochs=3, batch_size=4, eval_every=5, steps=1000)
    _, history = train.train_reward_model(MR(MR_TINY), jax.random.key(0), batch, None, cfg, progress=False)
    assert history["steps"] == 9 == history["step"][-1]  # 3 epochs x (10 // 4 + 1)
    _, history = train.train_reward_model(
        MR(MR_TINY), jax.random.key(0), batch, None, dataclasses.replace(cfg, length="steps", steps=7), progress=False
    )
    assert history["steps"] == 7 == history["step"][-1]
