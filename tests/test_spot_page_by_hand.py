"""By-hand checks that docs/spot.md cites and no other test made: the default CVAE loss (eq. 7-9),
the generated subgoal (eq. 10) and IQL's target-critic update, each written out in numpy from the
networks' outputs and compared with spot's function."""

import spot  # noqa: F401, I001  (first: sets the XLA flags before jax)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot.config import CVAEConfig, IQLConfig
from spot.policy import iql
from spot.subgoal import cvae, extract

OBS, ACT = 4, 2


def _cvae_inputs(cfg: CVAEConfig, seed: int = 0):
    """A fresh CVAE with non-trivial observation statistics (so the z-scoring matters) and a batch."""
    rng = np.random.default_rng(seed)
    mean, std = rng.normal(size=OBS) * 3.0, rng.uniform(0.5, 4.0, OBS)
    s = (rng.normal(size=(6, OBS)) * std + mean).astype(np.float32)
    a = rng.uniform(-1, 1, (6, ACT)).astype(np.float32)
    g = (rng.normal(size=(6, OBS)) * std + mean).astype(np.float32)
    params = cvae.init(jax.random.key(seed), OBS, ACT, cfg, (mean, std)).params
    return params, s, a, g, mean.astype(np.float64), std.astype(np.float64)


def _net(params: cvae.CVAEParams, method, *args) -> tuple[np.ndarray, ...] | np.ndarray:
    out = params.module.apply({"params": params.net}, *(jnp.asarray(x, jnp.float32) for x in args), method=method)
    return tuple(np.asarray(x, np.float64) for x in out) if isinstance(out, tuple) else np.asarray(out, np.float64)


def _cosine(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return (x * y).sum(-1) / (np.linalg.norm(x, axis=-1) * np.linalg.norm(y, axis=-1))


@pytest.mark.parametrize("loss,cos_sign", [("mse_cos", "minus"), ("mse_cos", "plus"), ("mse", "minus")])
def test_cvae_loss_by_hand(loss, cos_sign):
    """L = ½ mean_b ||μ_θ(z, s_n, a) - g_n||² + β mean_b KL(q_φ || p_ψ) (eq. 7, in z-scored units)
    + mean_b ½ (1 ∓ cos(ĝ, g)) on raw states (eq. 8: the intended minus, or the printed plus),
    with z = μ_q + σ_q ε and KL in its log-variance form."""
    cfg = CVAEConfig(latent_dim=3, hidden=(8, 8), beta=0.5, loss=loss, cos_sign=cos_sign)
    params, s, a, g, mean, std = _cvae_inputs(cfg)
    key = jax.random.key(1)
    got, info = cvae.loss_fn(params, extract.Triplets(jnp.asarray(s), jnp.asarray(a), jnp.asarray(g)), key, cfg)

    s_n, g_n = (s - mean) / std, (g - mean) / std
    mu_q, log_std_q = _net(params, cvae.CVAE.posterior, g_n, s_n, a)
    mu_p, log_std_p = _net(params, cvae.CVAE.prior, s_n, a)
    eps = np.asarray(jax.random.normal(key, mu_q.shape), np.float64)  # the reparameterisation noise
    g_hat_n = _net(params, cvae.CVAE.decode, mu_q + np.exp(log_std_q) * eps, s_n, a)
    recon = 0.5 * np.mean(np.sum((g_hat_n - g_n) ** 2, axis=-1))
    lv_q, lv_p = 2 * log_std_q, 2 * log_std_p
    kl = np.mean(0.5 * np.sum(lv_p - lv_q + (np.exp(lv_q) + (mu_q - mu_p) ** 2) / np.exp(lv_p) - 1.0, axis=-1))
    cos = _cosine(g_hat_n * std + mean, g)
    expected = recon + 0.5 * kl
    if loss == "mse_cos":
        expected += np.mean(0.5 * (1.0 - cos)) if cos_sign == "minus" else np.mean(0.5 * (1.0 + cos))
    np.testing.assert_allclose(float(got), expected, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(info["cvae/recon"]), recon, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(info["cvae/kl"]), kl, rtol=1e-4, atol=1e-6)


def test_generated_subgoal_by_hand():
    """ĝ = μ_θ(z, s_n, a) mapped back to raw units, with z the prior's mean (eq. 10, ``mode=mean``)
    or μ_p + σ_p ε (``mode=sample``); ``generate`` gives the same in batches."""
    params, s, a, _, mean, std = _cvae_inputs(CVAEConfig(latent_dim=3, hidden=(8, 8)), seed=2)
    s_n = (s - mean) / std
    mu_p, log_std_p = _net(params, cvae.CVAE.prior, s_n, a)
    by_mean = _net(params, cvae.CVAE.decode, mu_p, s_n, a) * std + mean
    np.testing.assert_allclose(np.asarray(cvae.sample_subgoal(params, s, a)), by_mean, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(cvae.generate(params, s, a, batch_size=4), by_mean, rtol=1e-4, atol=1e-5)

    key = jax.random.key(3)
    z = mu_p + np.exp(log_std_p) * np.asarray(jax.random.normal(key, mu_p.shape), np.float64)
    by_sample = _net(params, cvae.CVAE.decode, z, s_n, a) * std + mean
    np.testing.assert_allclose(np.asarray(cvae.sample_subgoal(params, s, a, key)), by_sample, rtol=1e-4, atol=1e-5)
    assert not np.allclose(by_sample, by_mean)


def test_target_critics_by_hand():
    """After one IQL update the target critics are Q̄' = τ Q' + (1 - τ) Q̄, leaf by leaf, with Q' the
    critics after their step."""
    cfg = IQLConfig(hidden=(16, 16), batch_size=8, tau=0.05)
    state = iql.init_state(jax.random.key(0), 3, 2, cfg)
    state = state._replace(target_critic_params=jax.tree.map(lambda p: p * 0.5 - 0.1, state.target_critic_params))
    rng = np.random.default_rng(0)
    batch = iql.Transitions(
        obs=jnp.asarray(rng.normal(size=(8, 3)), jnp.float32),
        act=jnp.asarray(rng.uniform(-1, 1, (8, 2)), jnp.float32),
        rew=jnp.asarray(rng.normal(size=8), jnp.float32),
        next_obs=jnp.asarray(rng.normal(size=(8, 3)), jnp.float32),
        mask=jnp.ones(8, jnp.float32),
    )
    new, _ = iql.update(state, batch, cfg)
    old_leaves = jax.tree.leaves(state.target_critic_params)
    for q_new, q_bar, got in zip(
        jax.tree.leaves(new.critic.params), old_leaves, jax.tree.leaves(new.target_critic_params), strict=True
    ):
        want = cfg.tau * np.asarray(q_new, np.float64) + (1 - cfg.tau) * np.asarray(q_bar, np.float64)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-6)
    # the critics did move, so the check above is not the identity
    assert any(
        not np.allclose(a, b)
        for a, b in zip(jax.tree.leaves(new.critic.params), jax.tree.leaves(state.critic.params), strict=True)
    )
