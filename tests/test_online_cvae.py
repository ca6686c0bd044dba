"""Fidelity rows 28/29 (the online CVAE: one CVAE step per reward-model step on that step's
minibatch) and 33 (the state+action shaping term), each at its own level: the term by hand, the
in-jit extraction against the host extraction, the trainer's companion step by step, and tiny runs."""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot import SpotError, config
from spot.reward import models, train, update
from spot.subgoal import cvae, extract, online, shaping
from tests.conftest import TINY_RUN


# --------------------------------------------------------------------------- row 33: the term
def test_state_action_cosine_by_hand():
    s = np.array([[3.0, 4.0], [1.0, 0.0], [0.0, 0.0]], np.float32)
    g_s = np.array([[6.0, 8.0], [0.0, 1.0], [1.0, 1.0]], np.float32)  # cos 1, 0, 0 (zero state)
    a = np.array([[1.0, 0.0], [0.5, -0.5], [1.0, 1.0]], np.float32)
    g_a = np.array([[-2.0, 0.0], [1.0, -1.0], [-1.0, 1.0]], np.float32)  # cos -1, 1, 0
    # (cos_s + 1)/2 + (cos_a + 1)/2: 1 + 0, 0.5 + 1, 0.5 + 0.5
    got = np.asarray(shaping.state_action_cosine(s, a, g_s, g_a))
    np.testing.assert_allclose(got, [1.0, 1.5, 1.0], atol=1e-6)
    with pytest.raises(SpotError, match="must match"):
        shaping.state_action_cosine(s, a, g_s[:, :1], g_a)


def _cvae_params(obs_dim: int, act_dim: int, goal_actions: bool, seed: int = 0) -> cvae.CVAEParams:
    cfg = config.CVAEConfig(hidden=(8,), latent_dim=2)
    stats = (np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32))
    return cvae.init(jax.random.key(seed), obs_dim, act_dim, cfg, stats, goal_actions).params


def test_shaped_rewards_state_action_reads_current_state_and_action():
    """eq. 13 with the state+action term: the CVAE's (ĝ_s, ĝ_a) for (s, a), the term on s and a
    (not s'), r = r_model + λ·term; ``constant`` is its dataset mean; a state-only CVAE is refused."""
    rng = np.random.default_rng(0)
    n, o, k = 7, 3, 2
    obs, act = rng.normal(size=(n, o)).astype(np.float32), rng.uniform(-1, 1, (n, k)).astype(np.float32)
    next_obs = rng.normal(size=(n, o)).astype(np.float32)
    r_model = rng.normal(size=n).astype(np.float32)
    params = _cvae_params(o, k, True)
    goals = cvae.generate(params, obs, act, with_actions=True)
    assert cvae.generate(params, obs, act).shape == (n, o)  # the state part by default
    assert goals.shape == (n, o + k)
    g_s, g_a = goals[:, :o], goals[:, o:]
    cos = lambda x, y: (x * y).sum(-1) / (np.linalg.norm(x, axis=-1) * np.linalg.norm(y, axis=-1))  # noqa: E731
    term = (cos(obs, g_s) + 1) / 2 + (cos(act, g_a) + 1) / 2
    cfg = config.ShapingConfig(kind="cosine", weight=0.5, state_action=True)
    out, info = shaping.shaped_rewards(params, obs, act, next_obs, r_model, cfg, jax.random.key(0))
    np.testing.assert_allclose(out.shape, term, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.reward, r_model + 0.5 * term, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.cos_to_subgoal, cos(obs, g_s), rtol=1e-5, atol=1e-6)
    const = config.ShapingConfig(kind="constant", weight=1.0, state_action=True)
    out_c, _ = shaping.shaped_rewards(params, obs, act, next_obs, r_model, const, jax.random.key(0))
    np.testing.assert_allclose(out_c.shape, np.full(n, term.mean()), rtol=1e-5)
    with pytest.raises(SpotError, match="state_action"):
        shaping.shaped_rewards(_cvae_params(o, k, False), obs, act, next_obs, r_model, cfg, jax.random.key(0))


def test_state_action_config_rules():
    cfg = config.load(None, ["method=spot", "shaping.state_action=true"])
    assert cfg.shaping.state_action and cfg.shaping.kind == "cosine"
    with pytest.raises(SpotError, match="state_action"):
        config.load(None, ["method=spot", "shaping.state_action=true", "shaping.kind=potential"])
    with pytest.raises(SpotError, match="subgoal.source=random"):
        config.load(None, ["method=spot", "variant=authors", "subgoal.source=random"])


def test_state_action_goals_in_triplets_and_cvae_loss():
    """Triplets carry the subgoal step's state and action; the CVAE decodes both and its losses
    read both parts (mse_cos: one cosine term per part; authors: both MSEs, the state cosine)."""
    obs = np.arange(2 * 4 * 2, dtype=np.float32).reshape(2, 4, 2)
    act = -np.arange(2 * 4 * 1, dtype=np.float32).reshape(2, 4, 1) - 1
    mask = np.array([[False, False, True, False], [False, True, False, True]])
    trip, _ = extract.make_triplets(obs, act, mask, "next_subgoal", goal_actions=True)
    # row 0: steps 0-2 -> step 2; row 1: step 0-1 -> 1, steps 2-3 -> 3
    np.testing.assert_array_equal(trip.g[0], [*obs[0, 2], *act[0, 2]])
    np.testing.assert_array_equal(trip.g[5], [*obs[1, 3], *act[1, 3]])
    params = _cvae_params(2, 1, True)
    for loss in ("mse", "mse_cos", "authors"):
        value, info = cvae.loss_fn(params, trip, jax.random.key(0), config.CVAEConfig(loss=loss))
        assert np.isfinite(float(value)), loss
    with pytest.raises(SpotError, match="obs_dim \\+ act_dim"):
        cvae.train_cvae(jax.random.key(0), trip.s, trip.a, trip.g[:, :2], config.CVAEConfig(steps=1), (0, 1), False,
                        goal_actions=True)  # fmt: skip


@pytest.mark.parametrize("loss", ["mse", "mse_cos", "authors"])
@pytest.mark.parametrize("goal_actions", [False, True])
def test_weighted_cvae_loss_is_the_loss_of_the_weighted_rows(loss, goal_actions, monkeypatch):
    """The online CVAE's fixed batch with 0/1 weights has the loss (and gradient) of a batch of just
    the rows of weight 1: the authors' batch of exactly that minibatch's triplets."""
    rng = np.random.default_rng(4)
    m, o, k = 9, 3, 2
    s, a = rng.normal(size=(m, o)).astype(np.float32), rng.uniform(-1, 1, (m, k)).astype(np.float32)
    g = rng.normal(size=(m, o + (k if goal_actions else 0))).astype(np.float32)
    keep = np.array([1, 0, 1, 1, 0, 0, 1, 1, 0], np.float32)
    idx = np.flatnonzero(keep)
    params = _cvae_params(o, k, goal_actions)
    cfg = config.CVAEConfig(loss=loss)
    key = jax.random.key(0)
    noise = jax.random.normal(key, (m, params.latent_dim))  # the full batch's reparameterisation noise

    def full_loss(net):
        return cvae.loss_fn(params.replace(net=net), extract.Triplets(s, a, g), key, cfg, jnp.asarray(keep))[0]

    def subset_loss(net):  # the kept rows alone, with the noise their rows get in the full batch
        with monkeypatch.context() as mp:
            mp.setattr(cvae.jax.random, "normal", lambda _key, _shape: noise[idx])
            return cvae.loss_fn(params.replace(net=net), extract.Triplets(s[idx], a[idx], g[idx]), key, cfg)[0]

    (l_full, g_full), (l_sub, g_sub) = (jax.jit(jax.value_and_grad(f))(params.net) for f in (full_loss, subset_loss))
    np.testing.assert_allclose(float(l_full), float(l_sub), rtol=1e-5, atol=1e-6)
    for x, y in zip(jax.tree.leaves(g_full), jax.tree.leaves(g_sub), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-6)


# --------------------------------------------------------------------------- rows 28/29: extraction in jit
def _scores(seed: int, q: int = 6, t: int = 20):
    rng = np.random.default_rng(seed)
    w = rng.random((q, t)).astype(np.float32)
    r = rng.normal(size=(q, t)).astype(np.float32)
    return w, r


@pytest.mark.parametrize("group", ["top", "top_next", "bottom_next", "bottom"])
@pytest.mark.parametrize("last_step", [False, True])
def test_online_subgoal_mask_matches_the_host_filter(group, last_step):
    w, r = _scores(1)
    for filter_groups in ("top", "all"):
        cfg = config.SubgoalConfig(group=group, last_step=last_step, filter_groups=filter_groups, top_k=20.0)
        host = extract.subgoal_mask(w, r, cfg.top_k, group, True, filter_groups, last_step)
        np.testing.assert_array_equal(np.asarray(online.subgoal_mask(jnp.asarray(w), jnp.asarray(r), cfg)), host)


def test_online_step_scores_match_the_host_scores():
    rng = np.random.default_rng(2)
    attn = jax.nn.softmax(jnp.asarray(rng.normal(size=(3, 5, 5)), jnp.float32), axis=-1)
    r_hat = rng.normal(size=(3, 5)).astype(np.float32)
    for weight in ("column_mean", "diagonal"):
        for filter_on in ("r_hat", "z"):
            w, r = online.step_scores(jnp.asarray(r_hat), attn, weight, filter_on)
            hw, hr = extract.step_scores(r_hat, np.asarray(attn), weight, filter_on)
            np.testing.assert_allclose(w, hw, rtol=1e-6)
            np.testing.assert_allclose(r, hr, rtol=1e-5, atol=1e-6)


def test_online_triplet_steps_match_the_host_triplets():
    """next_subgoal: the same triplets as the host; interval: one triplet per non-empty interval,
    its goal the host's, its step drawn inside ``[previous subgoal or 0, goal)``."""
    mask = np.array(
        [
            [False, False, True, False, False, True, False],
            [True, False, False, False, True, True, False],
            [False] * 7,
            [False, False, False, False, False, False, True],
        ]
    )
    obs = np.arange(4 * 7, dtype=np.float32).reshape(4, 7, 1)  # the value names (row, step)
    act = obs.copy()
    step, goal, ok = (np.asarray(x) for x in online.triplet_steps(jnp.asarray(mask), "next_subgoal", jax.random.key(0)))
    host, _ = extract.make_triplets(obs, act, mask, "next_subgoal")
    got = np.stack([obs[np.nonzero(ok)[0], step[ok], 0], obs[np.nonzero(ok)[0], goal[ok], 0]])
    np.testing.assert_array_equal(got, np.stack([host.s[:, 0], host.g[:, 0]]))
    host_i, _ = extract.make_triplets(obs, act, mask, "interval", draws=1)
    for seed in range(5):
        step, goal, ok = (
            np.asarray(x) for x in online.triplet_steps(jnp.asarray(mask), "interval", jax.random.key(seed))
        )
        rows, cols = np.nonzero(ok)
        np.testing.assert_array_equal(obs[rows, goal[ok], 0], host_i.g[:, 0])  # same goals, same order
        prev = {(0, 2): 0, (0, 5): 2, (1, 4): 0, (1, 5): 4, (3, 6): 0}
        assert {(int(r), int(c)) for r, c in zip(rows, cols, strict=True)} == set(prev)
        for r, c, s in zip(rows, cols, step[ok], strict=True):
            assert prev[(int(r), int(c))] <= s < c


def _pairs(q: int, t: int, o: int, a: int, seed: int = 0) -> dict:
    """Preference pairs whose first observation feature names the query (side 2: + 1000)."""
    rng = np.random.default_rng(seed)
    b = {}
    for side, offset in (("1", 0), ("2", 1000)):
        obs = rng.normal(size=(q, t, o)).astype(np.float32)
        obs[:, :, 0] = np.arange(q)[:, None] + offset
        b[f"obs_{side}"] = obs
        b[f"act_{side}"] = rng.uniform(-1, 1, size=(q, t, a)).astype(np.float32)
        b[f"timesteps_{side}"] = np.tile(np.arange(t), (q, 1)).astype(np.int32)
    b["label"] = np.tile(np.array([0.0, 1.0, 0.5], np.float32), q)[:q]
    return b


def test_minibatch_triplets_come_from_the_preferred_segments():
    """Each triplet's state and goal are steps of the preferred segment of a non-tied query."""
    q, t = 9, 12
    b = _pairs(q, t, 3, 2)
    rng = np.random.default_rng(3)
    attn = jax.nn.softmax(jnp.asarray(rng.normal(size=(2, q, t, t)), jnp.float32), axis=-1)
    r_hat = jnp.asarray(rng.normal(size=(2, q, t)), jnp.float32)
    fp = update.ForwardPass(
        b["obs_1"], b["act_1"], r_hat[0], attn[0], b["obs_2"], b["act_2"], r_hat[1], attn[1], b["label"]
    )
    cfg = config.SubgoalConfig(weight="diagonal", filter_on="z", last_step=True, triplets="interval")
    trip, weight = online.minibatch_triplets(fp, cfg, jax.random.key(0), goal_actions=True)
    ok = np.asarray(weight) > 0
    ids_s, ids_g = np.asarray(trip.s)[ok, 0], np.asarray(trip.g)[ok, 0]
    np.testing.assert_array_equal(ids_s, ids_g)  # state and goal from the same segment
    expected = {i + (1000 if b["label"][i] == 1.0 else 0) for i in range(q) if b["label"][i] != 0.5}
    assert set(ids_s.astype(int)) == expected  # every preferred segment (last step is a subgoal), no tie
    assert trip.g.shape[1] == 3 + 2  # the goal's state and action


# --------------------------------------------------------------------------- rows 28/29: the trainer
@dataclass(frozen=True)
class Probe:
    """The online CVAE, recording per step the query ids of the minibatch it saw and, at the first
    step, the forward pass's per-step rewards."""

    inner: online.OnlineCVAE

    def __call__(self, state, fp, key):
        cs, seen, first_r, n = state
        cs, metrics = self.inner(cs, fp, key)
        seen = seen.at[n].set(fp.obs_1[:, 0, 0])
        first_r = jnp.where(n == 0, fp.r_hat_1, first_r)
        return (cs, seen, first_r, n + 1), metrics


def test_online_cvae_steps_once_per_reward_step_on_that_minibatch():
    cfg = config.load(
        None,
        ["budget=tiny", "variant=authors", "pt.n_layer=1", "reward.length=steps", "reward.steps=5",
         "reward.eval_every=2", "reward.eval_epochs=0", "reward.batch_size=4", "cvae.log_std_clip=true"],
    )  # fmt: skip  (chunks of eval_every steps; the ids ~1000 in obs would overflow an unclipped log-std)
    q, t, o, a = 10, 8, 3, 2
    tb, eb = _pairs(q, t, o, a), _pairs(4, t, o, a, seed=1)
    model = models.from_config(cfg)
    key = jax.random.key(0)
    inner = online.OnlineCVAE(cfg.subgoal, cfg.cvae, False)
    cs = online.init_state(jax.random.key(1), np.zeros((5, o), np.float32), a, cfg.cvae, False)
    state = (cs, jnp.full((5, 4), -1.0), jnp.zeros((4, t)), jnp.zeros((), jnp.int32))
    comp = train.Companion(Probe(inner), state, {"cvae/loss": "cvae/loss"})
    params, hist = train.train_reward_model(model, key, tb, eb, cfg.reward, progress=False, companion=comp)
    cs, seen, first_r, n = hist["companion_state"]
    assert int(n) == 5 and int(cs.step) == 5  # one CVAE step per reward-model step (every batch has triplets)
    assert [len(v) for v in hist["companion"].values()] == [3] * len(hist["companion"])  # chunk means
    # the minibatch of step i: the trainer's own draw (fold_in(train_key, i), then split)
    _, train_key = jax.random.split(key)
    for i in range(5):
        batch_key, dropout_key = jax.random.split(jax.random.fold_in(train_key, i))
        idx = np.asarray(update.batch_indices(batch_key, q, 4))
        np.testing.assert_array_equal(np.asarray(seen[i]), idx.astype(np.float32))
        if i == 0:  # the training pass: initial parameters, dropout on (one micro-batch)
            init_key, _ = jax.random.split(key)
            pairs = train.pref_pairs(tb)
            mb = jax.tree.map(lambda x, i=idx: x[i], pairs)
            cat = lambda x, y: jnp.concatenate([x, y])  # noqa: E731
            r_hat, _, _ = model.apply_attention(
                model.init(init_key, o, a),
                cat(mb.obs_1, mb.obs_2),
                cat(mb.act_1, mb.act_2),
                cat(mb.timesteps_1, mb.timesteps_2),
                cat(mb.mask_1, mb.mask_2),
                jax.random.fold_in(dropout_key, 0),
            )
            np.testing.assert_allclose(np.asarray(first_r), np.asarray(r_hat[:4]), rtol=1e-5, atol=1e-6)
    # the reward model trains exactly as without the companion
    plain, _ = train.train_reward_model(model, key, tb, eb, cfg.reward, progress=False)
    for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(plain), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_online_cvae_skips_a_minibatch_without_triplets_and_decodes_actions():
    """A minibatch of ties gives no triplet and no step; with goal actions the CVAE decodes both."""
    q, t, o, a = 3, 6, 2, 2
    b = _pairs(q, t, o, a)
    b["label"] = np.full(q, 0.5, np.float32)
    cvae_cfg = config.CVAEConfig(hidden=(8,), latent_dim=2)
    step = online.OnlineCVAE(config.SubgoalConfig(last_step=True, triplets="interval"), cvae_cfg, True)
    state = online.init_state(jax.random.key(0), b["obs_1"].reshape(-1, o), a, cvae_cfg, True)
    attn = jnp.full((q, t, t), 1.0 / t)
    r_hat = jnp.zeros((q, t))
    fp = update.ForwardPass(b["obs_1"], b["act_1"], r_hat, attn, b["obs_2"], b["act_2"], r_hat, attn, b["label"])
    after, metrics = jax.jit(step)(state, fp, jax.random.key(1))
    assert int(after.step) == 0 and float(metrics["cvae/triplets"]) == 0.0
    np.testing.assert_array_equal(jax.tree.leaves(after.params.net)[0], jax.tree.leaves(state.params.net)[0])
    fp = fp._replace(label=jnp.array([0.0, 1.0, 0.0]))
    after, metrics = jax.jit(step)(state, fp, jax.random.key(1))
    assert int(after.step) == 1 and float(metrics["cvae/triplets"]) >= 3 and np.isfinite(float(metrics["cvae/loss"]))
    assert after.params.goal_act_dim == a and cvae.generate(
        after.params, b["obs_1"][0], b["act_1"][0], with_actions=True
    ).shape == (
        t,
        o + a,
    )


def test_online_schedule_only_where_the_variant_or_key_says():
    """Offline stays today's default (spot, paper); authors trains online; runs without a CVAE
    (PT without diagnostics, MR) attach none."""
    from spot.run import subgoal_stages

    def cfg(*o):
        return config.load(None, ["method=spot", "budget=tiny", *o])

    assert not subgoal_stages.online_cvae(cfg()) and not subgoal_stages.online_cvae(cfg("variant=paper"))
    assert subgoal_stages.online_cvae(cfg("variant=authors"))
    assert subgoal_stages.online_cvae(cfg("cvae.schedule=online"))
    assert not subgoal_stages.online_cvae(cfg("variant=authors", "cvae.schedule=offline"))
    pt = config.load(None, ["method=pt", "variant=authors", "subgoal.diagnostics=false"])
    assert not subgoal_stages.online_cvae(pt)
    assert not subgoal_stages.online_cvae(config.load(None, ["method=mr", "variant=authors"]))


def test_online_cvae_code_is_in_the_reward_entry_only_when_online():
    """The online reward stage's cache key covers the CVAE's code; the offline one's does not (an
    edit of the CVAE retires no offline reward model)."""
    from spot import cache, stages
    from spot.run import reward_stages

    off, on = cache.code_parts(reward_stages.learned_reward), cache.code_parts(reward_stages.learned_reward_online)
    assert "spot.subgoal.online" not in off and "spot.subgoal.cvae" not in off and "spot.reward.train" in off
    assert {"spot.subgoal.online", "spot.subgoal.cvae", "spot.reward.train"} <= set(on)
    authors = config.load(None, ["method=spot", "variant=authors"])
    assert stages.stages_of(authors).reward is reward_stages.learned_reward_online
    assert stages.stages_of(config.load(None, ["method=spot"])).reward is stages.learned_reward


# --------------------------------------------------------------------------- tiny runs
TINY = [*TINY_RUN, "pt.n_layer=1"]


def test_state_action_shaping_runs_end_to_end(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """method=spot with shaping.state_action: the offline CVAE decodes (ĝ_s, ĝ_a), the term lies in
    [0, 2], and the saved CVAE says it decodes actions."""
    import mlflow

    from spot import pipeline, tracking

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = config.load(None, [*TINY, "method=spot", "shaping.state_action=true", f"tracking.uri={uri}"])
    out = pipeline.run(cfg, progress=False)
    mlflow.set_tracking_uri(uri)
    m = mlflow.get_run(out["run_id"]).data.metrics
    assert 0.0 <= m["shaping/r_shape_min"] <= m["shaping/r_shape_max"] <= 2.0
    assert m["shaping/r_shape_max"] > 1.0  # two cosine halves: above a state-only term's maximum
    params, _ = tracking.load_model(out["run_id"], "cvae", uri)
    assert params.goal_act_dim == 4  # drawer-open's action size
