"""IPL-IQL (spot.policy.ipl): hand-computed losses, target clipping, the update checked against
numpy, jit/no-jit, one trace per chunk, and a learning threshold on locally built Hopper data.

Unit tests share one small synthetic problem and config (the train chunk compiles once); the
learning test compiles its own chunk for the Hopper shapes.
"""

import spot  # noqa: F401, I001  (first: sets the XLA flags before jax)

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot import SpotError, loop
from spot.config import IPLConfig, IQLConfig
from spot.data import labels, registry
from spot.policy import ipl, iql

OBS, ACT, Q, T, N = 3, 2, 12, 6, 50
IQL_CFG = IQLConfig(hidden=(16,), batch_size=16, chunk=20, discount=0.9)
# chi2_coeff 20 with gamma 0.9 puts the V(s') clip at +-0.5, so some values of a fresh V clip.
IPL_CFG = IPLConfig(
    feedback_batch=4,
    subsample=4,
    chi2_coeff=20.0,
    value_replay_weight=0.3,
    chi2_replay_weight=0.25,
    policy_replay_weight=0.6,
)


def _bce(logit: float, y: float) -> float:
    """-y log sigmoid(x) - (1 - y) log(1 - sigmoid(x)), written out."""
    p = 1.0 / (1.0 + math.exp(-logit))
    return -y * math.log(p) - (1.0 - y) * math.log(1.0 - p)


@pytest.fixture(scope="module")
def problem() -> tuple[ipl.FeedbackPairs, iql.Transitions]:
    rng = np.random.default_rng(0)
    f32 = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
    batch = {
        "obs_1": f32(Q, T, OBS),
        "act_1": np.tanh(f32(Q, T, ACT)),
        "obs_2": f32(Q, T, OBS),
        "act_2": np.tanh(f32(Q, T, ACT)),
        "label": np.array([0, 1, 0.5] * (Q // 3), np.float32),
    }
    mask = np.ones(N, np.float32)
    mask[::7] = 0.0
    replay = iql.Transitions(
        jnp.asarray(f32(N, OBS)),
        jnp.asarray(np.tanh(f32(N, ACT))),
        jnp.zeros(N),
        jnp.asarray(f32(N, OBS)),
        jnp.asarray(mask),
    )
    return ipl.feedback_from(batch), replay


# --------------------------------------------------------------------------- numeric
def test_preference_loss_by_hand():
    r_1 = jnp.array([[0.5, 0.5], [1.0, 0.0], [0.0, 0.0]])
    r_2 = jnp.array([[1.0, 1.0], [0.0, 0.0], [0.3, 0.2]])
    label = jnp.array([1.0, 0.0, 0.5])
    # logits sum(r_2) - sum(r_1) = [1, -1, 0.5]; the tie pays 1/2 log(1 + e^-0.5) + 1/2 log(1 + e^0.5)
    expected = (
        math.log1p(math.exp(-1.0))
        + math.log1p(math.exp(-1.0))
        + 0.5 * math.log1p(math.exp(-0.5))
        + 0.5 * math.log1p(math.exp(0.5))
    ) / 3
    assert abs(expected - 0.4502) < 1e-4
    np.testing.assert_allclose(ipl.preference_loss(r_1, r_2, label), expected, rtol=1e-6)
    # An ensemble axis is averaged over: member 2 sees logits [0, 0, 0] -> log 2 each.
    r_1e, r_2e = jnp.stack([r_1, jnp.zeros_like(r_1)]), jnp.stack([r_2, jnp.zeros_like(r_2)])
    np.testing.assert_allclose(ipl.preference_loss(r_1e, r_2e, label), (expected + math.log(2)) / 2, rtol=1e-6)
    # The tie is minimised at logit 0, a strict label is not.
    grad = jax.grad(lambda x: ipl.preference_loss(jnp.zeros((1, 1)), x, jnp.array([0.5])))(jnp.zeros((1, 1)))
    assert float(grad[0, 0]) == 0.0
    with pytest.raises(ValueError):
        ipl.preference_loss(r_1, r_2, label[:2])


def test_chi2_loss_with_replay_mixing_by_hand():
    r_1 = jnp.array([[1.0, 2.0]])  # E r^2 = 2.5
    r_2 = jnp.array([[0.0, 2.0]])  # E r^2 = 2.0
    r_replay = jnp.array([3.0, 1.0, 0.0, 0.0])  # E r^2 = 2.5
    # c [(1 - w) 1/2 (2.5 + 2.0) + w 2.5] with c = 0.5, w = 0.25: 0.5 (0.75 * 2.25 + 0.625)
    np.testing.assert_allclose(ipl.chi2_loss(r_1, r_2, r_replay, 0.5, 0.25), 1.15625, rtol=1e-6)
    np.testing.assert_allclose(ipl.chi2_loss(r_1, r_2, r_replay, 0.5, 1.0), 1.25, rtol=1e-6)
    np.testing.assert_allclose(ipl.chi2_loss(r_1, r_2, None, 0.5, 0.25), 1.125, rtol=1e-6)  # c E r^2


def test_target_clipping_bound_and_use(problem):
    assert ipl.target_clip_bound(0.99, 0.5) == pytest.approx(200.0)  # the D4RL setting
    assert ipl.target_clip_bound(0.9, 20.0) == pytest.approx(0.5)
    # A value net that outputs exactly 1000: kernel of the last layer 0, bias 1000.
    state = ipl.init_state(jax.random.key(0), OBS, ACT, IQL_CFG)
    params = jax.tree.map(jnp.copy, state.value.params)
    last = params["params"]["MLP_0"]["Dense_1"]  # the output layer of a one-hidden-layer MLP
    last["kernel"], last["bias"] = jnp.zeros_like(last["kernel"]), jnp.full_like(last["bias"], 1000.0)
    state = state._replace(value=state.value.replace(params=params))
    fb, _ = problem
    obs, act, next_obs = fb.obs_1[0, :-1], fb.act_1[0, :-1], fb.obs_1[0, 1:]
    q = np.asarray(state.critic.apply_fn(state.critic.params, obs, act)).mean(axis=0)
    d4rl_iql = IQLConfig(hidden=IQL_CFG.hidden)
    clipped = ipl.implied_reward(state, obs, act, next_obs, d4rl_iql, IPLConfig())
    np.testing.assert_allclose(clipped, q - 0.99 * 200.0, rtol=1e-5)
    unclipped = ipl.implied_reward(state, obs, act, next_obs, d4rl_iql, IPLConfig(target_clipping=False))
    np.testing.assert_allclose(unclipped, q - 0.99 * 1000.0, rtol=1e-5)


# --------------------------------------------------------------------------- data
def test_feedback_from_checks_and_casts():
    q, t = 4, 3
    batch = {
        "obs_1": np.zeros((q, t, 2)),
        "act_1": np.zeros((q, t, 1)),
        "obs_2": np.ones((q, t, 2)),
        "act_2": np.ones((q, t, 1)),
        "label": np.array([0, 1, 0.5, 1]),
        "timesteps_1": np.ones((q, t)),
    }
    fb = ipl.feedback_from(batch)
    assert fb.obs_1.shape == (q, t, 2) and fb.act_2.shape == (q, t, 1) and fb.label.dtype == jnp.float32
    for bad, match in [
        ({"label": np.array([0, 1, 2, 1])}, "label"),
        ({"act_2": np.ones((q, 2, 1))}, "segment 2"),
        ({"mask_1": np.array([[1, 1, 0]] * q)}, "padded"),
        ({k: batch[k][:, :1] for k in ("obs_1", "act_1", "obs_2", "act_2")}, "at least 2"),
    ]:
        with pytest.raises(SpotError, match=match):
            ipl.feedback_from({**batch, **bad})
    with pytest.raises(SpotError, match="missing"):
        ipl.feedback_from({k: v for k, v in batch.items() if k != "act_1"})


def test_sample_feedback_window_and_pairs():
    q, t = 10, 6
    coords = np.stack(np.meshgrid(np.arange(q), np.arange(t), indexing="ij"), axis=-1).astype(np.float32)
    fb = ipl.FeedbackPairs(
        jnp.asarray(coords),
        jnp.asarray(coords[..., :1]),
        jnp.asarray(coords + 100),
        jnp.asarray(coords[..., :1] + 100),
        jnp.arange(q, dtype=jnp.float32),
    )
    cfg = IPLConfig(feedback_batch=4, subsample=4)
    sample = jax.jit(ipl.sample_feedback, static_argnums=2)
    starts = set()
    for k in range(40):
        mb = jax.device_get(sample(jax.random.key(k), fb, cfg))
        pair, step = mb.obs_1[..., 0], mb.obs_1[..., 1]  # [4, 4]
        assert mb.obs_1.shape == (4, 4, 2) and mb.act_2.shape == (4, 4, 1)
        assert len(set(pair[:, 0])) == 4 and (pair == pair[:, :1]).all()  # distinct pairs, whole rows
        np.testing.assert_array_equal(mb.label, pair[:, 0])  # labels follow their pairs
        np.testing.assert_array_equal(step, np.broadcast_to(step[0, 0] + np.arange(4), (4, 4)))  # one shared window
        np.testing.assert_array_equal(mb.obs_2, mb.obs_1 + 100)
        starts.add(int(step[0, 0]))
    assert starts == {0, 1, 2}  # every start 0..T-S, the last one included
    whole = sample(jax.random.key(0), fb, IPLConfig(feedback_batch=4, subsample=64))
    assert whole.obs_1.shape == (4, t, 2)  # subsample >= T: whole segments


# --------------------------------------------------------------------------- update
@pytest.fixture(scope="module")
def eager_update(problem):
    """One update, eagerly, on the first 4 pairs (a 4-step window) and 16 replay rows."""
    fb, replay = problem
    fb = jax.tree.map(lambda x: x[:4] if x.ndim == 1 else x[:4, 1:5], fb)
    replay = jax.tree.map(lambda x: x[:16], replay)
    state = ipl.init_state(jax.random.key(3), OBS, ACT, IQL_CFG)
    with jax.disable_jit():
        new_state, metrics = ipl.update(state, fb, replay, IQL_CFG, IPL_CFG)
    return state, fb, replay, new_state, metrics


def test_update_jit_matches_no_jit(eager_update):
    state, fb, replay, eager_state, eager_metrics = eager_update
    jit_state, jit_metrics = jax.jit(ipl.update, static_argnames=("iql_cfg", "ipl_cfg"))(
        state, fb, replay, IQL_CFG, IPL_CFG
    )
    assert set(jit_metrics) == set(eager_metrics)
    for name, value in eager_metrics.items():
        np.testing.assert_allclose(jit_metrics[name], value, rtol=1e-5, atol=1e-6, err_msg=name)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), jit_state, eager_state)
    assert int(jit_state.step) == 1


def test_actor_dropout_changes_only_the_actor_loss(eager_update):
    """iql.actor_dropout (fidelity row 39, IPL robomimic 0.1) drops out the actor's hidden units
    in its loss, keyed by the update's dropout key; the critic and value losses are unchanged."""
    import dataclasses

    _, fb, replay, _, metrics = eager_update
    cfg = dataclasses.replace(IQL_CFG, actor_dropout=0.5)
    state = ipl.init_state(jax.random.key(3), OBS, ACT, cfg)  # the same parameters as the fixture's
    fn = jax.jit(ipl.update, static_argnames=("iql_cfg", "ipl_cfg"))
    _, m1 = fn(state, fb, replay, cfg, IPL_CFG, jax.random.key(0))
    _, m2 = fn(state, fb, replay, cfg, IPL_CFG, jax.random.key(1))
    assert float(m1["ipl/actor_loss"]) != float(m2["ipl/actor_loss"])
    assert float(m1["ipl/actor_loss"]) != float(metrics["ipl/actor_loss"])
    for name in ("ipl/value_loss", "ipl/pref_loss"):
        np.testing.assert_allclose(m1[name], metrics[name], rtol=1e-5, atol=1e-6, err_msg=name)


def test_update_losses_match_numpy(eager_update):
    """Value, preference and chi^2 losses of one update recomputed in numpy from the networks
    (segment 1, segment 2 and replay rows, replay terminals, V(s') clipped at +-0.5)."""
    state, fb, replay, new_state, metrics = eager_update
    cfg = IPL_CFG
    gamma, b, s = IQL_CFG.discount, 4, 4
    seg = [
        (
            np.asarray(o[:, :-1]).reshape(-1, OBS),
            np.asarray(a[:, :-1]).reshape(-1, ACT),
            np.asarray(o[:, 1:]).reshape(-1, OBS),
            np.full(b * (s - 1), gamma),
        )
        for o, a in ((fb.obs_1, fb.act_1), (fb.obs_2, fb.act_2))
    ]
    seg.append(
        (np.asarray(replay.obs), np.asarray(replay.act), np.asarray(replay.next_obs), gamma * np.asarray(replay.mask))
    )

    def weighted(parts, w):  # parts: per-element losses of segment 1, segment 2, replay
        return (1 - w) * 0.5 * (parts[0].mean() + parts[1].mean()) + w * parts[2].mean()

    value_parts, rewards, clipped = [], [], 0
    for obs, act, next_obs, disc in seg:
        u = np.asarray(state.critic.apply_fn(state.target_critic_params, obs, act)).min(0) - np.asarray(
            state.value.apply_fn(state.value.params, obs)
        )
        value_parts.append(np.where(u > 0, IQL_CFG.expectile, 1 - IQL_CFG.expectile) * u**2)
        next_v = np.asarray(new_state.value.apply_fn(new_state.value.params, next_obs))  # V' after its step
        clipped += int((np.abs(next_v) > 0.5).sum())
        q = np.asarray(state.critic.apply_fn(state.critic.params, obs, act))  # [2, n]
        rewards.append(q - disc * np.clip(next_v, -0.5, 0.5))
    assert clipped > 0  # the clip is exercised
    np.testing.assert_allclose(metrics["ipl/value_loss"], weighted(value_parts, cfg.value_replay_weight), rtol=1e-5)
    logits = rewards[1].reshape(2, b, s - 1).sum(-1) - rewards[0].reshape(2, b, s - 1).sum(-1)
    y = np.asarray(fb.label)
    pref = np.mean([[_bce(float(x), float(t)) for x, t in zip(row, y, strict=True)] for row in logits])
    np.testing.assert_allclose(metrics["ipl/pref_loss"], pref, rtol=1e-5)
    chi2 = cfg.chi2_coeff * weighted([r**2 for r in rewards], cfg.chi2_replay_weight)
    np.testing.assert_allclose(metrics["ipl/chi2_loss"], chi2, rtol=1e-5)
    acc = np.mean((logits.mean(0) > 0)[y != 0.5] == (y[y != 0.5] > 0.5))
    np.testing.assert_allclose(metrics["ipl/pref_acc"], acc)
    assert all(np.isfinite(float(v)) for v in metrics.values())


# --------------------------------------------------------------------------- chunk
def test_chunk_compiles_once_and_is_deterministic(problem):
    """Without replay (the Meta-World setting; the learning test runs chunks with replay)."""
    fb, _ = problem
    cfg = dataclasses.replace(IPL_CFG, use_replay=False)
    chunk_fn = ipl.make_train_chunk(IQL_CFG, cfg)
    runs = []
    for _ in range(2):
        state = ipl.init_state(jax.random.key(5), OBS, ACT, IQL_CFG)
        state, m1 = chunk_fn(state, IQL_CFG.chunk, None, fb, jax.random.key(6))
        state, m2 = chunk_fn(state, IQL_CFG.chunk, None, fb, jax.random.key(6))
        runs.append((loop.check_finite(m2, 2 * IQL_CFG.chunk), jax.device_get(state.critic.params)))
    assert chunk_fn._cache_size() == 1
    assert int(state.step) == 2 * IQL_CFG.chunk
    assert runs[0][0] == runs[1][0]
    jax.tree.map(np.testing.assert_array_equal, runs[0][1], runs[1][1])
    assert set(runs[0][0]) >= {
        "ipl/pref_loss",
        "ipl/chi2_loss",
        "ipl/value_loss",
        "ipl/actor_loss",
        "ipl/pref_acc",
        "ipl/reward_mean",
    }
    assert "ipl/reward_replay_mean" not in runs[0][0]
    # The actor is IQL's: iql.act evaluates it.
    assert np.asarray(iql.act(state.actor.params, np.zeros((2, OBS)), IQL_CFG)).shape == (2, ACT)
    with pytest.raises(SpotError, match="replay"):
        ipl.make_train_chunk(IQL_CFG, IPL_CFG)(state, IQL_CFG.chunk, None, fb, jax.random.key(6))


# --------------------------------------------------------------------------- learning
@pytest.mark.slow
def test_implied_reward_ranks_held_out_segments_of_local_hopper(spot_dirs):
    """Scripted labels on the tiny locally built hopper-medium-expert data (300 queries of 25
    steps, 60 held out). Measured held-out accuracy of the summed implicit reward after 1000
    updates: 0.95 / 0.90 / 0.93 for seeds 0 / 1 / 2 (0.65 at initialisation; 0.38-0.55 when
    trained on shuffled labels). Threshold 0.8."""
    ds, _ = registry.load("hopper-medium-expert", "tiny", 0, progress=False)
    prefs = labels.scripted_teacher(ds, 300, 25, seed=0)
    train_q, held_q = labels.split_eval(prefs, 0.2, 0)
    feedback = ipl.feedback_from(labels.segment_batch(ds, train_q))
    held = ipl.feedback_from(labels.segment_batch(ds, held_q))
    iql_cfg = IQLConfig(hidden=(32, 32), batch_size=64, steps=1000, chunk=500)
    ipl_cfg = IPLConfig(subsample=16, feedback_batch=8)
    init = ipl.evaluate_preferences(
        ipl.init_state(jax.random.key(0), ds.obs_dim, ds.act_dim, iql_cfg), held, iql_cfg, ipl_cfg
    )
    state, history = ipl.train_ipl(jax.random.key(0), jax.device_put(ds.transitions()), feedback, iql_cfg, ipl_cfg)
    assert ipl.make_train_chunk(iql_cfg, ipl_cfg)._cache_size() == 1  # two chunks with replay, one program
    final = ipl.evaluate_preferences(state, held, iql_cfg, ipl_cfg)
    assert len(held_q) == 60 and len(history) == 2
    assert all(np.isfinite(v) for h in history for v in h.values())
    assert history[-1]["ipl/pref_loss"] < history[0]["ipl/pref_loss"]
    assert final["ipl/eval_pref_loss"] < init["ipl/eval_pref_loss"]
    assert final["ipl/eval_pref_acc"] >= 0.8, (final, init)
