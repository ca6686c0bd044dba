"""Tests of spot.subgoal: extraction (eq. 5-6), CVAE (eq. 7-9), shaping (eq. 11-13), diagnostics."""

import spot  # noqa: F401, I001  (first: sets the XLA flags before jax)

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot import NonFiniteError, SpotError, cache
from spot.config import CVAEConfig, ShapingConfig, SubgoalConfig
from spot.subgoal import cvae, cvae_loss, diagnostics, extract, shaping

# --------------------------------------------------------------------------- extraction
# One segment of T = 10 with distinct weights; sorted ascending the indices are
# 6 (.01), 2 (.02), 8 (.03), 0 (.05), 4 (.08), 3 (.10), 7 (.12), 5 (.15), 1 (.20), 9 (.24).
W = np.array([0.05, 0.20, 0.02, 0.10, 0.08, 0.15, 0.01, 0.12, 0.03, 0.24])
# Mean 1.5: r >= mean at indices 2, 3, 6, 9.
R = np.array([1.0, 0.0, 2.0, 3.0, 0.0, 1.0, 5.0, -1.0, 0.0, 4.0])

# Hand-computed with numpy's linear quantile q(p) at position p * (T - 1):
# K = 10: q(.9) = .204, q(.8) = .16, q(.1) = .019, q(.2) = .028.
# K = 20: q(.8) = .16, q(.6) = .108, q(.2) = .028, q(.4) = .068.
EXPECTED = {
    (10, "top"): ({9}, {9}),
    (10, "top_next"): ({1}, set()),
    (10, "bottom_next"): ({2}, {2}),
    (10, "bottom"): ({6}, {6}),
    (20, "top"): ({1, 9}, {9}),
    (20, "top_next"): ({5, 7}, set()),
    (20, "bottom_next"): ({0, 8}, set()),
    (20, "bottom"): ({2, 6}, {2, 6}),
}


@pytest.mark.parametrize("top_k,group", list(EXPECTED))
@pytest.mark.parametrize("reward_filter", [False, True])
def test_subgoal_mask_by_hand(top_k, group, reward_filter):
    # Row 1 is row 0 reversed in time, scaled: the quantile and the mean are per segment.
    w = np.stack([W, 3 * W[::-1]])
    r = np.stack([R, R[::-1] + 100.0])
    mask = extract.subgoal_mask(w, r, top_k, group, reward_filter, filter_groups="all")
    want = EXPECTED[(top_k, group)][int(reward_filter)]
    assert set(np.flatnonzero(mask[0])) == want
    assert set(np.flatnonzero(mask[1])) == {9 - i for i in want}
    # Default (the authors' rule behind Table 2): the reward filter only narrows the top group.
    mask = extract.subgoal_mask(w, r, top_k, group, reward_filter)
    want = EXPECTED[(top_k, group)][int(reward_filter and group == "top")]
    assert set(np.flatnonzero(mask[0])) == want


def test_reward_filter_group_rule_from_the_config():
    # K = 20, top_next: attention alone gives {5, 7}; both have r < mean (1.5), so the literal
    # eq. 5 (all) empties the group while the authors' rule (top) keeps it.
    seg = extract.Segments(np.arange(10.0)[None, :, None], np.zeros((1, 10, 1)), R[None], W[None])
    other = extract.Segments(np.zeros((1, 10, 1)), np.zeros((1, 10, 1)), np.zeros((1, 10)), W[None])
    cfg = SubgoalConfig(top_k=20.0, group="top_next", filter_groups="top")
    _, states, _ = extract.extract(seg, other, np.array([0.0]), cfg)  # y = 0: segment 1 preferred
    assert sorted(states[:, 0].astype(int).tolist()) == [5, 7]
    with pytest.raises(SpotError, match="no subgoal triplets"):
        extract.extract(seg, other, np.array([0.0]), dataclasses.replace(cfg, filter_groups="all"))


def test_subgoal_mask_groups_partition_t100():
    w = np.random.default_rng(0).dirichlet(np.ones(100), size=3)
    masks = [extract.subgoal_mask(w, np.zeros_like(w), 10, g, False) for g in extract.GROUPS]
    assert all((m.sum(axis=1) == 10).all() for m in masks)
    assert not np.any(np.sum(masks, axis=0) > 1)  # the four groups are disjoint


def test_preferred_segments():
    y = np.array([1.0, 0.0, 0.5, 1.0])
    q, side = extract.preferred_segments(y)
    np.testing.assert_array_equal(q, [0, 1, 3])
    np.testing.assert_array_equal(side, [1, 0, 1])
    q, side = extract.preferred_segments(y, ties="both")
    np.testing.assert_array_equal(q, [0, 1, 2, 2, 3])
    np.testing.assert_array_equal(side, [1, 0, 0, 1, 1])
    with pytest.raises(SpotError, match="expected 0, 0.5 or 1"):
        extract.preferred_segments(np.array([0.3]))


def test_take_preferred_picks_rows():
    q, t = 3, 4
    seg = [
        extract.Segments(
            obs=np.full((q, t, 2), v), act=np.full((q, t, 1), v), reward=np.full((q, t), v), weight=np.full((q, t), v)
        )
        for v in (1.0, 2.0)
    ]
    pref = extract.take_preferred(seg[0], seg[1], np.array([0.0, 0.5, 1.0]))
    assert pref.obs.shape == (2, t, 2)
    np.testing.assert_array_equal(pref.reward[:, 0], [1.0, 2.0])
    np.testing.assert_array_equal(pref.act[:, :, 0], [[1.0] * t, [2.0] * t])


def test_make_triplets_by_hand():
    obs = (10.0 * np.arange(3)[:, None] + np.arange(5)[None, :])[..., None]  # obs[i, t] = 10 i + t
    act = -obs
    mask = np.array([[0, 1, 0, 0, 1], [0, 0, 1, 0, 0], [0, 0, 0, 0, 0]], bool)
    (s, a, g), info = extract.make_triplets(obs, act, mask)
    np.testing.assert_array_equal(s[:, 0], [0, 1, 2, 3, 4, 10, 11, 12])
    np.testing.assert_array_equal(a[:, 0], -s[:, 0])
    np.testing.assert_array_equal(g[:, 0], [1, 1, 4, 4, 4, 12, 12, 12])
    assert info == {
        "subgoal/num_segments": 3.0,
        "subgoal/num_subgoals": 3.0,
        "subgoal/num_triplets": 8.0,
        "subgoal/segments_without_subgoal": 1.0,
    }


def test_triplet_segments_and_cvae_split_by_segment():
    """Issue 11, bug 6: the CVAE's held-out triplets are whole segments; no preferred segment has
    triplets on both sides of the split (the stage passes extract_with_segments' ids as groups)."""
    import jax

    from spot.subgoal import cvae

    obs = (10.0 * np.arange(3)[:, None] + np.arange(5)[None, :])[..., None]
    mask = np.array([[0, 1, 0, 0, 1], [0, 0, 1, 0, 0], [0, 0, 0, 0, 0]], bool)
    (s, _, _), seg, _ = extract.make_triplets_with_segments(obs, -obs, mask)
    np.testing.assert_array_equal(seg, [0, 0, 0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(s[:, 0] // 10, seg)  # obs[i, t] = 10 i + t
    (_, _, g), seg, _ = extract.make_triplets_with_segments(obs, -obs, mask, "interval", draws=4)
    np.testing.assert_array_equal(g[:, 0] // 10, seg)
    groups = np.repeat(np.arange(40), 7)  # 40 segments of 7 triplets
    for k in range(5):
        train_idx, held_idx = cvae._split(jax.random.key(k), groups.size, 0.1, groups)
        assert held_idx.size == 4 * 7 and train_idx.size + held_idx.size == groups.size
        assert not set(groups[train_idx]) & set(groups[held_idx])
    # extract() on real segments returns the preferred segment of each triplet
    seg_a = extract.Segments(np.arange(20.0).reshape(1, 10, 2), np.zeros((1, 10, 1)), R[None], W[None])
    two = extract.Segments(*(np.concatenate([x, x]) for x in seg_a))
    trip, seg, _, info = extract.extract_with_segments(two, two, np.array([0.0, 1.0]), SubgoalConfig(top_k=10.0))
    np.testing.assert_array_equal(seg, np.repeat([0, 1], 10))
    assert trip.s.shape[0] == seg.size == info["subgoal/num_triplets"]


def test_cvae_stage_passes_segments_as_groups(monkeypatch):
    from types import SimpleNamespace

    from spot import config
    from spot.run import subgoal_stages
    from spot.subgoal import cvae

    seen = {}

    def fake_train(key, s, a, g, cfg, stats, progress=True, **kw):
        seen.update(kw)
        return "params", []

    monkeypatch.setattr(cvae, "train_cvae", fake_train)
    tracker = SimpleNamespace(set_tags=lambda tags: None, run_id="r")
    ctx = SimpleNamespace(
        cfg=config.load(None, ["budget=tiny"]),
        keys={"cvae": None},
        ds=SimpleNamespace(observations=np.zeros((4, 1), np.float32)),
        progress=False,
        tracker=tracker,
        cached=lambda name, deps, compute: (compute(), "key"),
        log=lambda *a, **k: None,
    )
    monkeypatch.setattr(subgoal_stages, "save_model", lambda *a, **k: None)
    trip = extract.Triplets(np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)))
    rewards = SimpleNamespace(source=SimpleNamespace(cache_key="reward-key"))
    subgoal_stages.cvae_stage(ctx, (trip, np.zeros((1, 1)), np.array([4, 4, 9])), rewards)
    np.testing.assert_array_equal(seen["groups"], [4, 4, 9])


def test_extract_end_to_end():
    obs = np.arange(20.0).reshape(1, 10, 2)
    seg_good = extract.Segments(obs, np.zeros((1, 10, 1)), R[None], W[None])
    seg_bad = extract.Segments(-obs, np.zeros((1, 10, 1)), R[None], W[None])
    trip, subgoals, info = extract.extract(seg_bad, seg_good, np.array([1.0]), SubgoalConfig(top_k=10.0))
    np.testing.assert_array_equal(subgoals, obs[0, [9]])  # step 9: top weight and r >= mean
    assert trip.s.shape == (10, 2) and (trip.g == obs[0, 9]).all()
    assert info["subgoal/num_triplets"] == 10
    with pytest.raises(SpotError, match="no subgoal triplets"):
        extract.extract(seg_bad, seg_good, np.array([0.5]), SubgoalConfig())


# --------------------------------------------------------------------------- CVAE maths
def test_gaussian_kl_by_hand_and_monte_carlo():
    mq, lq = np.array([1.0, -0.5]), np.log(np.array([0.5, 2.0]))
    mp, lp = np.array([0.0, 0.5]), np.log(np.array([1.0, 1.5]))
    # KL per dim = log(sp/sq) + (sq² + (mq - mp)²) / (2 sp²) - 1/2
    by_hand = (math.log(2.0) + (0.25 + 1.0) / 2 - 0.5) + (math.log(0.75) + (4.0 + 1.0) / (2 * 2.25) - 0.5)
    kl = float(cvae_loss.gaussian_kl(jnp.array(mq), jnp.array(lq), jnp.array(mp), jnp.array(lp)))
    assert kl == pytest.approx(by_hand, rel=1e-5)

    z = mq + np.exp(lq) * np.random.default_rng(0).standard_normal((200_000, 2))

    def log_prob(x, m, ls):
        return (-0.5 * ((x - m) / np.exp(ls)) ** 2 - ls - 0.5 * np.log(2 * np.pi)).sum(-1)

    mc = np.mean(log_prob(z, mq, lq) - log_prob(z, mp, lp))
    assert kl == pytest.approx(mc, abs=0.02)


def test_cosine_loss_by_hand():
    g = jnp.array([[1.0, 2.0, -1.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(cvae_loss.cosine_loss(g, g), [0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(cvae_loss.cosine_loss(-g, g), [1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(cvae_loss.cosine_loss(jnp.array([[0.0, 0.0, 5.0]]), g[1:]), [0.5], atol=1e-6)
    assert float(cvae_loss.cosine_loss(jnp.zeros((1, 3)), g[:1])[0]) == pytest.approx(0.5)  # eps guard


def _toy_triplets(n, seed=0):
    rng = np.random.default_rng(seed)
    s = rng.standard_normal((n, 3)).astype(np.float32)
    a = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    g = s + np.array([1.0, -0.5, 0.5], np.float32)
    return s, a, g


SMALL = CVAEConfig(latent_dim=4, hidden=(16, 16), lr=3e-3, batch_size=32, steps=20, beta=1.0)


@pytest.fixture(scope="module")
def small_params():
    s, _, _ = _toy_triplets(64)
    return cvae.init(jax.random.key(0), 3, 2, SMALL, cvae.obs_stats(s)).params


def test_loss_jit_matches_no_jit_and_cos_term(small_params):
    s, a, g = _toy_triplets(64)
    batch = extract.Triplets(*(jnp.asarray(x) for x in (s, a, g)))
    key = jax.random.key(1)
    loss, info = cvae.loss_fn(small_params, batch, key, SMALL)
    loss_j, info_j = jax.jit(cvae.loss_fn, static_argnums=3)(small_params, batch, key, SMALL)
    assert float(loss) == pytest.approx(float(loss_j), rel=1e-5)
    for k in info:
        assert float(info[k]) == pytest.approx(float(info_j[k]), rel=1e-5, abs=1e-6)
    assert float(loss) == pytest.approx(float(info["cvae/recon"] + info["cvae/kl"] + info["cvae/cos"]), rel=1e-5)
    assert float(info["cvae/recon"]) == pytest.approx(0.5 * 3 * float(info["cvae/mse"]), rel=1e-5)
    mse_cfg = dataclasses.replace(SMALL, loss="mse", beta=0.5)
    loss_mse, _ = cvae.loss_fn(small_params, batch, key, mse_cfg)
    assert float(loss_mse) == pytest.approx(float(info["cvae/recon"] + 0.5 * info["cvae/kl"]), rel=1e-5)


def test_train_chunk_compiles_once():
    s, a, g = _toy_triplets(64)
    chunk = cvae.make_train_chunk(SMALL, 5)
    state = cvae.init(jax.random.key(0), 3, 2, SMALL, cvae.obs_stats(s))
    data = extract.Triplets(*(jnp.asarray(x) for x in (s, a, g)))
    before = chunk._cache_size()  # 1 if test_non_finite_loss_raises already compiled it
    for i in range(3):
        state, metrics = chunk(state, 5, data, jnp.int32(64), jax.random.key(i))
    assert chunk._cache_size() == max(before, 1)
    assert int(state.step) == 15 and set(metrics) >= {"cvae/loss", "cvae/recon", "cvae/kl", "cvae/cos"}


def test_padded_triplets_train_as_the_unpadded_ones():
    """The CVAE's training data are padded to a bucket (shared compiled programs); the padding rows
    must never be drawn: training on the padded set gives bit-identical parameters to training
    on the 50 real rows, here against an unpadded loop written out step by step."""
    s, a, g = _toy_triplets(50)
    assert cvae.bucket(50) == 64 and cvae.bucket(64) == 64 and cvae.bucket(65) == 128 and cvae.bucket(1) == 64
    state0 = cvae.init(jax.random.key(0), 3, 2, SMALL, cvae.obs_stats(s))
    real = extract.Triplets(*(jnp.asarray(x) for x in (s, a, g)))
    padded = extract.Triplets(*(jnp.asarray(cvae.pad_rows(x, 64)) for x in (s, a, g)))
    assert padded.s.shape == (64, 3) and float(jnp.abs(padded.s[50:]).sum()) == 0.0
    update = jax.jit(cvae.make_update(SMALL))
    static = jax.jit(cvae.make_update(SMALL), static_argnums=2)  # the bound a constant, as before padding
    key = jax.random.key(7)
    ref, pad = state0, state0
    for _ in range(6):
        ref, _ = static(ref, real, 50, key)  # draws among exactly the 50 rows
        pad, _ = update(pad, padded, jnp.int32(50), key)
    for x, y in zip(jax.tree.leaves(ref.params.net), jax.tree.leaves(pad.params.net), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # a padding row drawn would show: rows 50-63 set to NaN leave the padded run finite
    poisoned = extract.Triplets(*(x.at[50:].set(jnp.nan) for x in padded))
    bad, _ = update(state0, poisoned, jnp.int32(50), key)
    assert all(bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(bad.params.net))


def test_triplet_counts_in_one_bucket_share_the_compiled_chunk():
    cfg = dataclasses.replace(SMALL, steps=5, lr=2.9e-3)  # a config no other test compiles
    chunk = cvae.make_train_chunk(cfg, 5)  # the chunk train_cvae uses (kept per config and length)
    sizes = []
    for m in (40, 57):  # 32 and 46 training rows: both pad to 64
        s, a, g = _toy_triplets(m, seed=m)
        params, _ = cvae.train_cvae(
            jax.random.key(m), s, a, g, cfg, cvae.obs_stats(s), progress=False, log_every=5, holdout=0.2
        )
        sizes.append(chunk._cache_size())
    assert sizes == [1, 1] and all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(params.net))


def test_cvaes_of_seeds_vmapped_equal_one_training_per_seed():
    """spot.subgoal.vmapped.train_cvaes: two seeds with different triplet counts (buckets 64 and
    128) and segment groups give each seed the parameters and history train_cvae gives it alone."""
    from spot.subgoal import vmapped

    cfg = dataclasses.replace(SMALL, steps=12)
    seeds = [(jax.random.key(5), _toy_triplets(50, seed=1)), (jax.random.key(9), _toy_triplets(100, seed=2))]
    groups = [np.arange(50) // 5, np.arange(100) // 5]
    stats = cvae.obs_stats(seeds[1][1][0])
    together = vmapped.train_cvaes(
        [k for k, _ in seeds], [t for _, t in seeds], cfg, stats, progress=False, log_every=5, groups=groups
    )
    for (key, (s, a, g)), grp, (got_params, got_rows) in zip(seeds, groups, together, strict=True):
        params, rows = cvae.train_cvae(key, s, a, g, cfg, stats, progress=False, log_every=5, groups=grp)
        assert [r["step"] for r in got_rows] == [r["step"] for r in rows] == [5, 10, 12]
        assert set(got_rows[0]) == set(rows[0]) and "cvae/heldout_loss" in rows[0]
        for want, got in zip(rows, got_rows, strict=True):
            for k in want:
                assert got[k] == pytest.approx(want[k], rel=1e-4, abs=1e-5), k
        for x, y in zip(jax.tree.leaves(params), jax.tree.leaves(got_params), strict=True):
            np.testing.assert_allclose(y, x, rtol=1e-4, atol=1e-5)
    assert together[0][1][-1]["cvae/loss"] != together[1][1][-1]["cvae/loss"]
    with pytest.raises(SpotError, match="differ in their sizes, or only some seeds have held-out"):
        vmapped.train_cvaes(
            [seeds[0][0]] * 2,
            [seeds[0][1], seeds[0][1]],
            cfg,
            stats,
            progress=False,
            groups=[groups[0], None],
            holdout=0.04,  # seed 0: round(0.4) of 10 segments held out, none; seed 1: 2 of 50 triplets
        )


def test_non_finite_loss_raises():
    s, a, g = _toy_triplets(64)
    g[:] = np.nan
    with pytest.raises(NonFiniteError) as err:  # 4 chunks of 5 steps: the chunk of the test above
        cvae.train_cvae(jax.random.key(0), s, a, g, SMALL, cvae.obs_stats(s), progress=False, log_every=5, holdout=0.0)
    assert err.value.step == 5 and err.value.loss_name == "cvae/loss"


@pytest.mark.slow
def test_cvae_learns_deterministic_subgoal():
    s, a, g = _toy_triplets(2000)
    cfg = CVAEConfig(latent_dim=4, hidden=(64, 64), lr=3e-3, batch_size=128, steps=600)
    params, history = cvae.train_cvae(jax.random.key(0), s, a, g, cfg, cvae.obs_stats(s), progress=False, log_every=200)
    assert [h["step"] for h in history] == [200, 400, 600]
    assert history[-1]["cvae/heldout_loss"] < history[0]["cvae/heldout_loss"]
    s_test, a_test, g_test = _toy_triplets(500, seed=1)
    g_hat = cvae.generate(params, s_test, a_test, batch_size=256)
    cos = np.asarray(cvae_loss.cosine_similarity(g_hat, g_test))
    baseline = np.asarray(cvae_loss.cosine_similarity(np.broadcast_to(g.mean(0), g_test.shape), g_test))
    assert cos.mean() > 0.98 and baseline.mean() < 0.7, (cos.mean(), baseline.mean())
    g_sample = cvae.generate(params, s_test, a_test, key=jax.random.key(3), mode="sample", batch_size=256)
    assert np.asarray(cvae_loss.cosine_similarity(g_sample, g_test)).mean() > 0.95


def test_generate_batches_compile_once_and_sample_is_keyed(small_params):
    s, a, _ = _toy_triplets(37)
    params = small_params
    full = np.asarray(jax.jit(cvae.sample_subgoal)(params, jnp.asarray(s), jnp.asarray(a)))
    before = cvae._generate_mean._cache_size()
    out = cvae.generate(params, s, a, batch_size=16)  # 3 batches, the last padded
    cvae.generate(params, s[:5], a[:5], batch_size=16)
    assert cvae._generate_mean._cache_size() - before <= 1
    np.testing.assert_allclose(out, full, rtol=1e-5, atol=1e-5)
    restored = cache.decode(*cache.encode(params))  # how the stage cache stores it (data only)
    np.testing.assert_array_equal(cvae.generate(restored, s, a, batch_size=16), out)
    key = jax.random.key(7)
    s1 = cvae.generate(params, s, a, key=key, mode="sample", batch_size=16)
    s2 = cvae.generate(params, s, a, key=key, mode="sample", batch_size=16)
    s3 = cvae.generate(params, s, a, key=jax.random.key(8), mode="sample", batch_size=16)
    np.testing.assert_array_equal(s1, s2)
    assert not np.allclose(s1, s3)


# --------------------------------------------------------------------------- shaping
NEXT_OBS = np.array([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]])
G_HAT = np.array([[1.0, 0.0], [0.0, -1.0], [1.0, 1.0]])
OBS = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]])


def test_shape_reward_by_hand():
    np.testing.assert_allclose(shaping.shape_reward("cosine", NEXT_OBS, G_HAT), [1.0, 0.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(
        shaping.shape_reward("neg_distance", NEXT_OBS, G_HAT), [0.0, -3.0, -math.sqrt(2)], atol=1e-6
    )
    # Φ(s') = [0, -3, -√2], Φ(s) = [-1, -1, 0]; γ Φ(s') - Φ(s) with γ = 0.9
    np.testing.assert_allclose(
        shaping.shape_reward("potential", NEXT_OBS, G_HAT, OBS, gamma=0.9), [1.0, -1.7, -0.9 * math.sqrt(2)], atol=1e-6
    )
    np.testing.assert_allclose(
        shaping.shape_reward("potential", NEXT_OBS, G_HAT, OBS, 0.9, terminals=np.array([0, 1, 0], bool)),
        [1.0, 1.0, -0.9 * math.sqrt(2)],
        atol=1e-6,
    )
    # The authors' potential Φ(x) = +||x - ĝ||: Φ(s') = [0, 3, √2], Φ(s) = [1, 1, 0]
    np.testing.assert_allclose(
        shaping.shape_reward("potential", NEXT_OBS, G_HAT, OBS, 0.9, potential_sign="pos"),
        [-1.0, 1.7, 0.9 * math.sqrt(2)],
        atol=1e-6,
    )
    np.testing.assert_allclose(shaping.shape_reward("none", NEXT_OBS, G_HAT), [0.0, 0.0, 0.0])
    rand = np.random.default_rng(0).standard_normal((2, 100, 4))
    cos = np.asarray(shaping.shape_reward("cosine", rand[0], rand[1]))
    assert cos.min() >= 0.0 and cos.max() <= 1.0
    with pytest.raises(SpotError, match="needs obs"):
        shaping.shape_reward("potential", NEXT_OBS, G_HAT)
    np.testing.assert_allclose(shaping.final_reward(np.array([1.0, 2.0]), np.array([0.5, 0.25]), -0.5), [0.75, 1.875])


def test_shaped_rewards_whole_dataset(small_params):
    s, a, _ = _toy_triplets(37)
    s_next = s + 0.1
    params = small_params
    r_model = np.linspace(0.0, 1.0, 37).astype(np.float32)
    cfg = ShapingConfig(kind="cosine", weight=0.5, subgoal="mean")
    out, info = shaping.shaped_rewards(params, s, a, s_next, r_model, cfg, jax.random.key(1), batch_size=16)
    g_hat = cvae.generate(params, s, a, batch_size=16)
    want_shape = np.asarray(shaping.shape_reward("cosine", s_next, g_hat))
    np.testing.assert_allclose(out.shape, want_shape, atol=1e-5)
    np.testing.assert_allclose(out.reward, r_model + 0.5 * want_shape, atol=1e-5)
    np.testing.assert_allclose(out.cos_to_subgoal, np.asarray(cvae_loss.cosine_similarity(s, g_hat)), atol=1e-5)
    assert info["shaping/r_shape_min"] >= 0.0 and info["shaping/r_shape_max"] <= 1.0


# --------------------------------------------------------------------------- diagnostics
def test_extrapolation_bins_by_hand(tmp_path):
    # z(r_model) = [1, -1, 1, -1], z(r_true) = [1, 1, -1, -1]  ->  error [0, 2, 2, 0]
    r_model = 10.0 * np.array([1.0, -1.0, 1.0, -1.0]) + 5.0  # scale and shift do not matter
    r_true = np.array([1.0, 1.0, -1.0, -1.0])
    cos = np.array([0.1, 0.2, 0.8, 0.9])
    in_dist = np.array([True, False, True, False])
    table = diagnostics.extrapolation_error_bins(r_model, r_true, cos, in_dist, bins=np.array([0.0, 0.5, 1.0, 1.5]))
    np.testing.assert_allclose(table.mean_error[:, :2], [[0.0, 2.0], [2.0, 0.0]])
    assert np.isnan(table.mean_error[:, 2]).all()
    np.testing.assert_array_equal(table.count, [[1, 1, 0], [1, 1, 0]])
    np.testing.assert_allclose(table.overall, [1.0, 1.0])
    auto = diagnostics.extrapolation_error_bins(r_model, r_true, cos, in_dist, bins=2)
    np.testing.assert_allclose(auto.edges, [0.1, 0.5, 0.9])
    np.testing.assert_allclose(auto.mean_error, [[0.0, 2.0], [2.0, 0.0]])
    assert auto.metrics() == {"diag/extrapolation_error_in_distribution": 1.0, "diag/extrapolation_error_ood": 1.0}
    png = diagnostics.plot_extrapolation({"PT": table, "SPOT": auto}, tmp_path / "fig2.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_precision_recall():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200, 4))
    assert diagnostics.precision_recall(x, x.copy()) == {"subgoal/precision": 1.0, "subgoal/recall": 1.0}
    far = diagnostics.precision_recall(x, x + 100.0)
    assert far == {"subgoal/precision": 0.0, "subgoal/recall": 0.0}
    # 1-D by hand, k = 1: real radii are all 1, so 0.5 is inside and 10 is not (precision 1/2);
    # generated radii are 9.5 (their mutual distance), covering every real point (recall 1).
    real = np.array([[0.0], [1.0], [2.0], [3.0]])
    gen = np.array([[0.5], [10.0]])
    pr = diagnostics.precision_recall(real, gen, k=1, standardize=False)
    assert pr == {"subgoal/precision": 0.5, "subgoal/recall": 1.0}


def test_plot_projection(tmp_path):
    rng = np.random.default_rng(0)
    png = diagnostics.plot_projection(
        rng.standard_normal((300, 5)), rng.standard_normal((50, 5)), tmp_path / "proj" / "pca.png"
    )
    assert png.exists() and png.read_bytes()[:4] == b"\x89PNG"


# --------------------------------------------------------------------------- fidelity keys (docs/fidelity.md)
# One segment of T = 3, preference attention A (rows: queries t, columns: keys j) and r_hat:
A3 = np.array([[0.2, 0.7, 0.1], [0.1, 0.5, 0.4], [0.2, 0.2, 0.6]])
R3 = np.array([1.0, 2.0, 4.0])
# Hand-computed: column means w = (.5, 1.4, 1.1) / 3; diagonal w = (.2, .5, .6);
# z_t = sum_j A_tj r_j = (.2 + 1.4 + .4, .1 + 1. + 1.6, .2 + .4 + 2.4) = (2.0, 2.7, 3.0).
# With K = 34: q(.66) at position 1.32; column means sorted (.1667, .3667, .4667) -> q = .39867,
# so only step 1 passes; diagonal sorted (.2, .5, .6) -> q = .532, only step 2 passes.
# Reward filter: mean r_hat = 7/3 (step 1: 2 < 2.33 fails, step 2: 4 passes);
# mean z = 7.7/3 = 2.5667 (step 1: 2.7 passes).


def test_step_scores_by_hand():
    w, r = extract.step_scores(R3[None], A3[None], "column_mean", "r_hat")
    np.testing.assert_allclose(w[0], [0.5 / 3, 1.4 / 3, 1.1 / 3])
    np.testing.assert_allclose(r[0], R3)
    w, r = extract.step_scores(R3[None], A3[None], "diagonal", "z")
    np.testing.assert_allclose(w[0], [0.2, 0.5, 0.6])
    np.testing.assert_allclose(r[0], [2.0, 2.7, 3.0])
    with pytest.raises(SpotError, match="weight"):
        extract.step_scores(R3[None], A3[None], "row_mean")
    with pytest.raises(SpotError, match=r"\[Q, T, T\]"):
        extract.step_scores(R3[None], A3)


@pytest.mark.parametrize(
    "weight,filter_on,expected",
    [
        ("column_mean", "r_hat", [False, False, False]),  # step 1 has the top weight, r_hat below mean
        ("column_mean", "z", [False, True, False]),  # ... but z above mean
        ("diagonal", "r_hat", [False, False, True]),  # the diagonal ranks step 2 first
        ("diagonal", "z", [False, False, True]),
    ],
)
def test_weight_and_filter_on_select_different_subgoals(weight, filter_on, expected):
    w, r = extract.step_scores(R3[None], A3[None], weight, filter_on)
    mask = extract.subgoal_mask(w, r, 34.0)
    np.testing.assert_array_equal(mask[0], expected)
    # last_step adds step 2 whatever the filters say
    last = extract.subgoal_mask(w, r, 34.0, last_step=True)
    np.testing.assert_array_equal(last[0], np.array(expected) | [False, False, True])


def test_pt_attention_matches_forward():
    """pt.attention's column mean is PT's w, and mean_t z_t is its logit (unpadded segments)."""
    from spot.config import PTConfig
    from spot.reward import pt

    cfg = PTConfig(embd_dim=16, n_layer=1, n_head=2, pref_attn_dim=8, max_timestep=20)
    rng = np.random.default_rng(0)
    obs, act = rng.standard_normal((3, 6, 4)), rng.standard_normal((3, 6, 2))
    ts, mask = np.tile(np.arange(1, 7), (3, 1)), np.ones((3, 6))
    params = pt.init_params(jax.random.PRNGKey(0), cfg, 4, 2)
    r_hat, w, logit = pt.forward(params, cfg, obs, act, ts, mask)
    r_hat2, attn = pt.attention(params, cfg, obs, act, ts, mask)
    np.testing.assert_allclose(np.asarray(attn).sum(-1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(r_hat2, r_hat, rtol=1e-5)
    w_col, z = extract.step_scores(np.asarray(r_hat2), np.asarray(attn), "column_mean", "z")
    np.testing.assert_allclose(w_col, w, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(z.mean(axis=1), logit, rtol=1e-4, atol=1e-6)


def test_interval_triplets_by_hand():
    # T = 8, obs[t] = t; subgoals at 3 and 6 (+ 7 with the last step).
    t = 8
    obs = np.arange(t, dtype=float)[None, :, None]
    act = 10.0 + obs
    mask = np.zeros((1, t), bool)
    mask[0, [3, 6]] = True
    rng = np.random.default_rng(1)
    (s, a, g), info = extract.make_triplets(obs, act, mask, "interval", draws=40, rng=rng)
    s, a, g = s[:, 0], a[:, 0], g[:, 0]
    # intervals [0, 3) -> 3 and [3, 6) -> 6; steps 6, 7 come after the last subgoal: dropped.
    assert info["subgoal/num_triplets"] == 80 and len(s) == 80
    np.testing.assert_array_equal(g, [3.0] * 40 + [6.0] * 40)
    np.testing.assert_array_equal(a, s + 10.0)
    assert set(s[:40]) == {0.0, 1.0, 2.0} and set(s[40:]) == {3.0, 4.0, 5.0}  # subgoal 3 -> next subgoal 6
    mask[0, 7] = True  # last step
    (s, _, g), _ = extract.make_triplets(obs, act, mask, "interval", draws=5)
    np.testing.assert_array_equal(g[:, 0], [3.0] * 5 + [6.0] * 5 + [7.0] * 5)
    np.testing.assert_array_equal(s[10:, 0], [6.0] * 5)  # the interval [6, 7) holds step 6 only
    # a subgoal at step 0 opens no empty interval: [0, 2) -> 2 only
    m0 = np.zeros((1, 4), bool)
    m0[0, [0, 2]] = True
    (s, _, g), info = extract.make_triplets(obs[:, :4], act[:, :4], m0, "interval", draws=3)
    np.testing.assert_array_equal(g[:, 0], [2.0] * 3)
    assert set(s[:, 0]) <= {0.0, 1.0}
    # the default mode on the same mask: every step to the first subgoal at or after it
    (s, _, g), _ = extract.make_triplets(obs[:, :4], act[:, :4], m0)
    np.testing.assert_array_equal(s[:, 0], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(g[:, 0], [0.0, 2.0, 2.0])


def test_extract_with_authors_keys():
    # Preferred segment 2 of T = 3 (A3, R3): diagonal weight, z filter, K = 34 -> step 2; the last
    # step is step 2 as well; intervals [0, 2) -> step 2.
    seg = extract.segments(
        np.arange(3.0)[None, :, None],
        np.zeros((1, 3, 1)),
        R3[None],
        A3[None],
        SubgoalConfig(weight="diagonal", filter_on="z"),
    )
    other = extract.Segments(np.zeros((1, 3, 1)), np.zeros((1, 3, 1)), np.zeros((1, 3)), np.ones((1, 3)) / 3)
    cfg = SubgoalConfig(
        top_k=34.0, weight="diagonal", filter_on="z", last_step=True, triplets="interval", interval_draws=4
    )
    (s, _, g), states, info = extract.extract(other, seg, np.array([1.0]), cfg, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(states[:, 0], [2.0])
    np.testing.assert_array_equal(g[:, 0], [2.0] * 4)
    assert set(s[:, 0]) <= {0.0, 1.0} and info["subgoal/num_subgoals"] == 1.0


def test_pt_learning_rate_schedules_by_hand():
    """pt.schedule / pt.warmup_fraction / pt.peak_factor / pt.b2 (spot.reward.pt)."""
    from spot.config import PTConfig
    from spot.reward import pt

    const = pt.learning_rate(PTConfig(lr=1e-4, warmup_steps=500))
    np.testing.assert_allclose([const(0), const(250), const(1000)], [0.0, 5e-5, 1e-4], rtol=1e-6)
    # PT repo: lr 1e-4 -> 1e-3 over 10 % of 100 steps, then cosine back to 1e-4:
    # step 5: 1e-4 + 9e-4 * 5/10 = 5.5e-4; step 55: 1e-4 + 9e-4 * (1 + cos(pi/2)) / 2 = 5.5e-4.
    cos = pt.learning_rate(PTConfig(lr=1e-4, schedule="warmup_cosine", warmup_fraction=0.1), 100)
    np.testing.assert_allclose(
        [cos(0), cos(5), cos(10), cos(55), cos(100)], [1e-4, 5.5e-4, 1e-3, 5.5e-4, 1e-4], rtol=1e-5
    )
    with pytest.raises(ValueError, match="total number of steps"):
        pt.learning_rate(PTConfig(schedule="warmup_cosine"))
    # b2: two AdamW steps (lr 1, no decay) with gradients 1 then 0; the second update is
    # m_hat / sqrt(v_hat) = (0.09 / 0.19) / sqrt(b2 / (1 + b2)): 0.671580 (b2 .99), 0.670058 (b2 .999).
    for b2, expected in ((0.99, 0.671580), (0.999, 0.670058)):
        tx = pt.PT(PTConfig(lr=1.0, weight_decay=0.0, warmup_steps=0, b2=b2)).optimizer(10)
        params = jnp.zeros(())
        state = tx.init(params)
        _, state = tx.update(jnp.ones(()), state, params)
        update, _ = tx.update(jnp.zeros(()), state, params)
        np.testing.assert_allclose(-float(update), expected, rtol=1e-5)
    # the optimizer runs the schedule over the steps it is given: with a constant gradient 1,
    # m_hat = v_hat = 1, so each update is minus that step's learning rate (1e-4 ... 5.5e-4 at step 5)
    tx = pt.PT(PTConfig(lr=1e-4, weight_decay=0.0, schedule="warmup_cosine", warmup_fraction=0.1)).optimizer(100)
    state, updates = tx.init(jnp.zeros(())), []
    for _ in range(6):
        update, state = tx.update(jnp.ones(()), state, jnp.zeros(()))
        updates.append(-float(update))
    np.testing.assert_allclose(updates, [1e-4, 1.9e-4, 2.8e-4, 3.7e-4, 4.6e-4, 5.5e-4], rtol=1e-4)


def test_cvae_authors_loss_by_hand():
    """cvae.loss=authors: per-dimension MSE - [mean (cos+1)/2 + 0.1 var cos] + KL averaged over
    latent dimensions, written here in the authors' log-variance form from the networks' outputs."""
    cfg = CVAEConfig(latent_dim=3, hidden=(8,), loss="authors", inputs="raw")
    rng = np.random.default_rng(0)
    s, a, g = rng.standard_normal((5, 4)), rng.uniform(-1, 1, (5, 2)), rng.standard_normal((5, 4))
    state = cvae.init(jax.random.PRNGKey(0), 4, 2, cfg, (np.zeros(4), np.ones(4)))
    params, key = state.params, jax.random.PRNGKey(1)
    loss, _ = cvae.loss_fn(params, extract.Triplets(*(jnp.asarray(x, jnp.float32) for x in (s, a, g))), key, cfg)

    def net(method, *args):
        return np.asarray(
            params.module.apply({"params": params.net}, *(jnp.asarray(x, jnp.float32) for x in args), method=method),
            np.float64,
        )

    q_mean, q_log_std = (
        np.asarray(x, np.float64)
        for x in params.module.apply(
            {"params": params.net},
            jnp.asarray(g, jnp.float32),
            jnp.asarray(s, jnp.float32),
            jnp.asarray(a, jnp.float32),
            method=cvae.CVAE.posterior,
        )
    )
    p_mean, p_log_std = (
        np.asarray(x, np.float64)
        for x in params.module.apply(
            {"params": params.net}, jnp.asarray(s, jnp.float32), jnp.asarray(a, jnp.float32), method=cvae.CVAE.prior
        )
    )
    z = q_mean + np.exp(q_log_std) * np.asarray(jax.random.normal(key, q_mean.shape), np.float64)
    g_hat = net(cvae.CVAE.decode, z, s, a)
    sim = (g_hat * g).sum(-1) / (np.linalg.norm(g_hat, axis=-1) * np.linalg.norm(g, axis=-1))
    lv_q, lv_p = 2 * q_log_std, 2 * p_log_std
    kl = 0.5 * np.mean(np.exp(lv_q - lv_p) + (q_mean - p_mean) ** 2 / np.exp(lv_p) - 1 + lv_p - lv_q)
    expected = np.mean((g_hat - g) ** 2) - (np.mean((sim + 1) / 2) + 0.1 * np.var(sim)) + kl
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4, atol=1e-6)


def test_cvae_raw_inputs_use_identity_statistics():
    cfg = CVAEConfig(latent_dim=2, hidden=(8,), steps=2, batch_size=4, inputs="raw")
    rng = np.random.default_rng(0)
    s, a, g = rng.standard_normal((8, 3)) * 5 + 7, rng.uniform(-1, 1, (8, 2)), rng.standard_normal((8, 3))
    params, _ = cvae.train_cvae(
        jax.random.PRNGKey(0), s, a, g, cfg, (np.full(3, 7.0), np.full(3, 5.0)), progress=False, log_every=2
    )
    np.testing.assert_array_equal(params.obs_mean, np.zeros(3))
    np.testing.assert_array_equal(params.obs_std, np.ones(3))
    params, _ = cvae.train_cvae(
        jax.random.PRNGKey(0),
        s,
        a,
        g,
        dataclasses.replace(cfg, inputs="zscore"),
        (np.full(3, 7.0), np.full(3, 5.0)),
        progress=False,
        log_every=2,
    )
    np.testing.assert_array_equal(params.obs_mean, np.full(3, 7.0))
