"""The loss of the subgoal CVAE (SPOT paper, §4.1.3, eq. 7-9, Table 7); the networks and training
are :mod:`spot.subgoal.cvae`'s.

Loss per triplet (batch mean), ``z ~ q`` by reparameterisation, one sample:

* ``recon = ½ ||μ_θ(z, s, a) - g||²`` in normalised units: the decoder's negative
  log-likelihood (eq. 7, first term) up to the constant ``(obs_dim / 2) log 2π``, i.e.
  ``obs_dim / 2`` times the per-dimension MSE;
* ``kl = KL(q_φ || p_ψ)``, analytic for diagonal Gaussians (eq. 7, second term), weighted by β;
* ``cos = ½ (1 - cos(ĝ, g))`` on raw states, where ĝ is the decoder mean (the posterior
  reconstruction), mapped back to raw units. Eq. 8 prints ``½ (1 + cos)``, which would be
  *minimised* by pointing ĝ away from g; we implement the intended ``½ (1 - cos)`` (0 when ĝ
  points along g, 1 when opposite). The cosine is taken on raw states, as the shaping reward of
  eq. 11 is. ``cfg.loss = "mse"`` drops this term (Table 7's "MSE only").

``loss = recon + β · kl (+ cos)`` (eq. 9). ``cfg.cos_sign = "plus"`` adds ``½ (1 + cos)`` instead,
eq. 8 as printed.

``cfg.loss = "authors"`` is the loss of the authors' code (SGPbrl ``PrefTransformer.vae_train_step``):
``mean_{b,d} (ĝ - g)² - [mean_b (cos_b + 1)/2 + 0.1 var_b(cos_b)] + β · KL / latent_dim`` (their
KL is averaged over latent dimensions; the variance term is subtracted, as written there). It is
meant with ``cfg.inputs = "raw"`` (their inputs are not standardised). That is the cleaned commit
(a5b03df); the commit their experiments ran (b6d94e2) adds the bracket instead, ``MSE + [...]``
(``cfg.cos_sign = "plus"``, the printed sign of eq. 8).

State and action subgoals (``shaping.state_action``): ``g = [g_s, g_a]``. ``recon`` and ``mse`` run
over both parts, ``cos`` is the state part's; ``mse_cos`` adds ``½ (1 - cos(ĝ_a, g_a))`` for the
action part; ``authors`` is their state-action branch as intended: ``mean (ĝ_s - g_s)² + mean
(ĝ_a - g_a)²`` minus the state part's cosine terms (as stored it cannot run: docs/fidelity.md row 33).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from spot.config import CVAEConfig

COS_EPS = 1e-8


# --------------------------------------------------------------------------- maths
def gaussian_kl(mean_q: jax.Array, log_std_q: jax.Array, mean_p: jax.Array, log_std_p: jax.Array) -> jax.Array:
    """``KL(N(mean_q, diag σ_q²) || N(mean_p, diag σ_p²))`` summed over the last axis.

    ``Σ_d log σ_p - log σ_q + (σ_q² + (μ_q - μ_p)²) / (2 σ_p²) - ½``.
    """
    var_q, var_p = jnp.exp(2 * log_std_q), jnp.exp(2 * log_std_p)
    kl = log_std_p - log_std_q + (var_q + (mean_q - mean_p) ** 2) / (2 * var_p) - 0.5
    return kl.sum(axis=-1)


def cosine_similarity(x: jax.Array, y: jax.Array, eps: float = COS_EPS) -> jax.Array:
    """``x·y / max(||x|| ||y||, eps)`` over the last axis."""
    norms = jnp.linalg.norm(x, axis=-1) * jnp.linalg.norm(y, axis=-1)
    return (x * y).sum(axis=-1) / jnp.maximum(norms, eps)


def cosine_loss(g_hat: jax.Array, g: jax.Array) -> jax.Array:
    """``½ (1 - cos(ĝ, g))`` per row: the intended form of eq. 8 (see module docstring)."""
    return 0.5 * (1.0 - cosine_similarity(g_hat, g))


# --------------------------------------------------------------------------- loss
def _avg(x: jax.Array, weight: jax.Array | None) -> jax.Array:
    """Mean of ``x`` over the batch (every axis without ``weight``; with ``weight [B]`` the weighted
    mean over rows of the per-row means: the online CVAE's masked triplets)."""
    if weight is None:
        return x.mean()
    rows = jnp.where(weight > 0, x.reshape(x.shape[0], -1).mean(axis=-1), 0.0)
    return (weight * rows).sum() / jnp.maximum(weight.sum(), 1.0)


def _var(x: jax.Array, weight: jax.Array | None) -> jax.Array:
    """Variance of ``x [B]`` over the batch (weighted by ``weight [B]`` when given)."""
    if weight is None:
        return x.var()
    return _avg((x - _avg(x, weight)) ** 2, weight)


def _authors_loss(
    g_hat_n: jax.Array, g_n: jax.Array, sim: jax.Array, kl: jax.Array, o: int, cfg: CVAEConfig, weight
) -> jax.Array:
    """SGPbrl ``vae_train_step``: per-dimension MSE (state part, plus the action part's when the goal
    has one) -/+ [mean((cos_s + 1)/2) + 0.1 var(cos_s)] + beta * KL / latent_dim: ``-`` at a5b03df
    (``cvae.cos_sign=minus``), ``+`` at b6d94e2 (``plus``) (module docstring)."""
    if g_hat_n.shape[-1] == o:
        mse = _avg((g_hat_n - g_n) ** 2, weight)
    else:
        mse = _avg((g_hat_n[:, :o] - g_n[:, :o]) ** 2, weight) + _avg((g_hat_n[:, o:] - g_n[:, o:]) ** 2, weight)
    bracket = _avg(0.5 * (sim + 1.0), weight) + 0.1 * _var(sim, weight)
    return mse + _cos_sign(cfg) * bracket + cfg.beta * kl


def _cos_sign(cfg: CVAEConfig) -> float:
    """+1 for ``cvae.cos_sign=plus`` (eq. 8 as printed), -1 for ``minus``."""
    return 1.0 if cfg.cos_sign == "plus" else -1.0


def loss_terms(
    g_n: jax.Array,
    g_hat_n: jax.Array,
    g: jax.Array,
    g_hat: jax.Array,
    posterior: tuple[jax.Array, jax.Array],
    prior: tuple[jax.Array, jax.Array],
    o: int,
    goal_act_dim: int,
    cfg: CVAEConfig,
    weight: jax.Array | None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 9 from the CVAE's outputs on a batch (:func:`spot.subgoal.cvae.loss_fn` runs the
    networks): the goals ``g_n`` and reconstructions ``g_hat_n`` normalised, ``g`` and ``g_hat`` raw
    (``[B, o]``, or ``[B, o + goal_act_dim]``: a state and an action), the posterior's and the prior's
    ``(mean, log_std)``, and the optional row ``weight [B]``. Returns ``(loss, info)`` as ``loss_fn``."""
    q_mean, q_log_std = posterior
    p_mean, p_log_std = prior
    sq_err = ((g_hat_n - g_n) ** 2).sum(axis=-1)  # [B]
    recon = 0.5 * _avg(sq_err, weight)
    kl_rows = gaussian_kl(q_mean, q_log_std, p_mean, p_log_std)
    kl = _avg(kl_rows, weight)
    sim = cosine_similarity(g_hat[:, :o], g[:, :o])
    cos = _avg(0.5 * (1.0 - sim), weight)
    loss = recon + cfg.beta * kl
    if cfg.loss == "mse_cos" and cfg.cos_sign == "minus":  # ½ (1 - cos) per part: the intended eq. 8
        loss = loss + cos
        if goal_act_dim:
            loss = loss + _avg(cosine_loss(g_hat[:, o:], g[:, o:]), weight)
    elif cfg.loss == "mse_cos":  # ½ (1 + cos) per part: eq. 8 as printed
        loss = loss + _avg(0.5 * (1.0 + sim), weight)
        if goal_act_dim:
            loss = loss + _avg(0.5 * (1.0 + cosine_similarity(g_hat[:, o:], g[:, o:])), weight)
    elif cfg.loss == "authors":  # SGPbrl PrefTransformer.vae_train_step (see the module docstring)
        loss = _authors_loss(g_hat_n, g_n, sim, kl / q_mean.shape[-1], o, cfg, weight)
    info = {
        "cvae/loss": loss,
        "cvae/recon": recon,
        "cvae/kl": kl,
        "cvae/cos": cos,
        "cvae/mse": _avg(sq_err, weight) / g.shape[-1],
    }
    return loss, info
