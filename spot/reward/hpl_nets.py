"""Hindsight Preference Learning's networks and pure loss terms (HPL; Gao et al. 2024,
arXiv:2407.04451); the objectives and training are in :mod:`spot.reward.hpl`.

Model (x_t = [s_t; a_t], k = ``HPLConfig.future_len``, z = G one-hot categoricals of C classes):

* hindsight encoder q(z_t | x_t .. x_{t+k}): a non-causal GPT-2 over one token per step (input
  Dense + learned positional embedding + dropout, ``n_layer`` pre-LN blocks, final LayerNorm),
  whose attention lets token t see keys j in [t, t+k] only; a Dense head gives logits ``[G, C]``.
* prior p(z | s, a): MLP on x_t to the same logits.
* decoder p(x_{t+D} | x_t, z_t, D): ReLU(concat(Dense(x_t), Dense(z_t), Embed(D))) -> MLP -> x_hat.
* reward r(s, a, z): MLP on [x; z], sigmoid output when ``reward_sigmoid``.
* relabelling reward r_hat(s, a) = (1/N) sum_i r(s, a, z_i), z_i ~ p(z | s, a), N = ``prior_samples``
  (:func:`prior_marginal_reward`).

Reference facts followed [typoverflow/WiseRL : wiserl/algorithm/hpl/hpl.py] (reference/algorithms.md
§4): discrete latent (``OneHotCategoricalStraightThrough``, 8 groups); attention mask = not below the
diagonal and not beyond t + future_len (applied in every layer); GPT-2 with GELU MLPs, dropout on
embeddings, attention and residuals [wiserl/module/net/attention/gpt2.py]; the encoder takes no dataset
timesteps (positions 0..T-1 of the segment); decoder input layers and Embedding(k + 1); reward MLP with
orthogonal init gain 1, zero bias [``ortho_init: true``, wiserl/module/net/basic.py ``weight_init``];
the other nets keep default init.

* **Receptive field.** Like WiseRL, the [t, t+k] mask is applied in every layer, so with n_layer
  blocks the output at t depends on x_t .. x_{t + n_layer * k} (never on the past). Exactly
  [t, t+k] holds for n_layer = 1 (tested both ways).
* **Decoder width** is ``decoder_embd`` (64, the tuned configs' ``decoder.embed_dim``); WiseRL's code
  passes ``z_dim`` (128) instead and ignores that key.
* **Random draws** (latent samples here, segment starts, D and minibatches in training) use
  :func:`random_bits`, a counter hash seeded by one draw from the explicit key (as
  :class:`spot.nets.Dropout`), not a threefry draw per element: same key discipline, less XLA
  compile time per call site on CPU (docs/benchmarks.md).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from spot.config import HPLConfig
from spot.nets import LN_EPS, MLP, Dropout, Params, TransformerBlock, hash_bits, orthogonal_init


# --------------------------------------------------------------------------- random draws
def random_bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """uint32 bits ``[shape]``: :func:`spot.nets.hash_bits` seeded by one 32-bit draw from ``key``.

    Every shaped random draw of this module goes through here (as :class:`spot.nets.Dropout` does):
    the randomness still comes from the explicit key, while a threefry draw per element costs more
    XLA compile time per call site and more run time on CPU (docs/benchmarks.md).
    """
    return hash_bits(shape, jax.random.bits(key, (), jnp.uint32))


def randint(key: jax.Array, shape: tuple[int, ...], n: jax.Array | int) -> jax.Array:
    """Integers in ``[0, n)`` (int32; ``bits mod n``, bias below ``n / 2^32``)."""
    return (random_bits(key, shape) % jnp.asarray(n, jnp.uint32)).astype(jnp.int32)


def sample_latent(key: jax.Array, logits: jax.Array) -> jax.Array:
    """One-hot samples ``[..., G, C]`` of each group, with straight-through gradients: the value is
    the one-hot sample, the gradient that of ``softmax(logits)`` (``OneHotCategoricalStraightThrough``).
    Sampling is Gumbel-max with uniforms ``(bits >> 8 + 1/2) / 2^24`` from :func:`random_bits`."""
    u = ((random_bits(key, logits.shape) >> 8).astype(jnp.float32) + 0.5) * 2.0**-24  # in (0, 1)
    hard = jax.nn.one_hot(jnp.argmax(logits - jnp.log(-jnp.log(u)), axis=-1), logits.shape[-1], dtype=logits.dtype)
    probs = jax.nn.softmax(logits, axis=-1)
    return hard + (probs - jax.lax.stop_gradient(probs))  # parenthesised: the value stays exactly one-hot


def window_mask(length: int, future_len: int) -> np.ndarray:
    """bool ``[T, T]``: query t may attend to key j iff ``t <= j <= t + future_len``."""
    diff = np.arange(length)[None, :] - np.arange(length)[:, None]
    return (diff >= 0) & (diff <= future_len)


# --------------------------------------------------------------------------- networks
def _gelu(x: jax.Array) -> jax.Array:
    return nn.gelu(x, approximate=False)  # torch nn.GELU (WiseRL's GPT-2 MLP)


class HindsightEncoder(nn.Module):
    """q(z_t | x_t..x_{t+k}): logits ``[B, T, G, C]`` of ``x [B, T, D]`` with ``valid [B, T]``."""

    cfg: HPLConfig

    @nn.compact
    def __call__(self, x: jax.Array, valid: jax.Array, deterministic: bool = True) -> jax.Array:
        cfg = self.cfg
        b, t, _ = x.shape
        if t > cfg.seq_len:
            raise ValueError(f"segment length {t} exceeds hpl.seq_len {cfg.seq_len} (positional embedding size)")
        pos = self.param("pos_embedding", nn.initializers.normal(0.02), (cfg.seq_len, cfg.embd_dim))
        h = nn.Dense(cfg.embd_dim, name="input_embed")(x) + pos[:t]
        h = Dropout(cfg.dropout)(h, deterministic=deterministic)
        mask = jnp.asarray(window_mask(t, cfg.future_len))[None] & (valid[:, None, :] > 0)  # [B, T, T]
        for i in range(cfg.n_layer):
            h = TransformerBlock(cfg.embd_dim, cfg.n_head, cfg.dropout, activation=_gelu, name=f"block_{i}")(
                h, mask, deterministic=deterministic
            )
        h = nn.LayerNorm(epsilon=LN_EPS, name="out_ln")(h)
        return nn.Dense(cfg.latent_groups * cfg.latent_classes, name="proj")(h).reshape(
            b, t, cfg.latent_groups, cfg.latent_classes
        )


class Decoder(nn.Module):
    """p(x_{t+D} | x_t, z_t, D): ``x [..., D_x]``, ``z [..., G*C]``, ``delta [...]`` int -> x_hat."""

    cfg: HPLConfig
    out_dim: int

    @nn.compact
    def __call__(self, x: jax.Array, z: jax.Array, delta: jax.Array) -> jax.Array:
        e = self.cfg.decoder_embd
        h = jnp.concatenate(
            [
                nn.Dense(e, name="x_embed")(x),
                nn.Dense(e, name="z_embed")(z),
                nn.Embed(self.cfg.future_len + 1, e, name="delta_embed")(delta),
            ],
            axis=-1,
        )
        return MLP(self.cfg.decoder_hidden, self.out_dim, name="unify")(nn.relu(h))


def _prior_net(cfg: HPLConfig) -> MLP:
    return MLP(cfg.prior_hidden, cfg.latent_groups * cfg.latent_classes)


def _reward_net(cfg: HPLConfig) -> MLP:
    return MLP(cfg.reward_hidden, 1, kernel_init=orthogonal_init(1.0))


# The HPLConfig fields that shape the parameters.
_ARCH_FIELDS = (
    "seq_len",
    "future_len",
    "latent_groups",
    "latent_classes",
    "embd_dim",
    "n_layer",
    "n_head",
    "decoder_hidden",
    "decoder_embd",
    "prior_hidden",
    "reward_hidden",
)


def init_params(key: jax.Array, cfg: HPLConfig, obs_dim: int, act_dim: int) -> Params:
    """``{"encoder", "prior", "decoder", "reward"}`` parameter dicts."""
    arch = HPLConfig(**{f: getattr(cfg, f) for f in _ARCH_FIELDS})  # configs that differ elsewhere share one
    return _init_program(arch, obs_dim, act_dim)(key)


@functools.lru_cache(maxsize=8)
def _init_program(cfg: HPLConfig, obs_dim: int, act_dim: int) -> Callable[[jax.Array], Params]:
    """All four nets' init as one program at optimisation level 0 (as :func:`spot.nets.jit_init`),
    kept per config and dims so that further seeds do not compile it again."""
    d, z = obs_dim + act_dim, cfg.latent_groups * cfg.latent_classes
    x = np.zeros((cfg.seq_len, d), np.float32)  # numpy: no program per size

    def init(key: jax.Array) -> Params:
        k = jax.random.split(key, 4)
        return {
            "encoder": HindsightEncoder(cfg).init(k[0], x[None], jnp.ones((1, cfg.seq_len))),
            "prior": _prior_net(cfg).init(k[1], x),
            "decoder": Decoder(cfg, d).init(k[2], x, jnp.zeros((cfg.seq_len, z)), jnp.zeros(cfg.seq_len, jnp.int32)),
            "reward": _reward_net(cfg).init(k[3], jnp.zeros((1, d + z), jnp.float32)),
        }

    return jax.jit(init, compiler_options={"xla_backend_optimization_level": 0})


def encode(
    params: Params, cfg: HPLConfig, x: jax.Array, valid: jax.Array, dropout_key: jax.Array | None = None
) -> jax.Array:
    """Posterior logits ``[B, T, G, C]``; dropout on iff ``dropout_key`` is given."""
    rngs = {} if dropout_key is None else {"dropout": dropout_key}
    return HindsightEncoder(cfg).apply(params["encoder"], x, valid, dropout_key is None, rngs=rngs)


def prior_logits(params: Params, cfg: HPLConfig, x: jax.Array) -> jax.Array:
    """Prior logits ``[..., G, C]`` of ``x [..., D]``."""
    return _prior_net(cfg).apply(params["prior"], x).reshape(*x.shape[:-1], cfg.latent_groups, cfg.latent_classes)


def reward(params: Params, cfg: HPLConfig, x: jax.Array, z: jax.Array) -> jax.Array:
    """``r(s, a, z)`` ``[...]`` of ``x [..., D]`` and one-hot ``z [..., G, C]``."""
    r = _reward_net(cfg).apply(params["reward"], jnp.concatenate([x, z.reshape(*z.shape[:-2], -1)], axis=-1))[..., 0]
    return jax.nn.sigmoid(r) if cfg.reward_sigmoid else r


def prior_marginal_reward(params: Params, cfg: HPLConfig, x: jax.Array, key: jax.Array) -> jax.Array:
    """``(1/N) sum_i r(x, z_i)``, ``z_i ~ p(z | x)``, N = ``cfg.prior_samples``: ``x [..., D] -> [...]``.

    The N latents are ``sample_latent(key, broadcast_to(prior_logits, (N, ...)))``.
    """
    logits = prior_logits(params, cfg, x)
    z = sample_latent(key, jnp.broadcast_to(logits, (cfg.prior_samples, *logits.shape)))
    return jnp.mean(reward(params, cfg, jnp.broadcast_to(x, (cfg.prior_samples, *x.shape)), z), axis=0)


# --------------------------------------------------------------------------- pure losses
def categorical_kl(logits_q: jax.Array, logits_p: jax.Array) -> jax.Array:
    """KL(q || p) of independent categoricals ``[..., G, C]``, summed over the G groups -> ``[...]``."""
    if logits_q.shape != logits_p.shape or logits_q.ndim < 2:
        raise ValueError(f"expected equal [..., G, C] logits, got {logits_q.shape} and {logits_p.shape}")
    log_q = jax.nn.log_softmax(logits_q, axis=-1)
    log_p = jax.nn.log_softmax(logits_p, axis=-1)
    return jnp.sum(jnp.exp(log_q) * (log_q - log_p), axis=(-2, -1))


def balanced_kl(logits_q: jax.Array, logits_p: jax.Array, alpha: float) -> jax.Array:
    """KL balancing: ``alpha KL(sg(q) || p) + (1 - alpha) KL(q || sg(p))`` (value = KL(q || p));
    the prior learns with weight alpha, the posterior with 1 - alpha."""
    sg = jax.lax.stop_gradient
    return alpha * categorical_kl(sg(logits_q), logits_p) + (1.0 - alpha) * categorical_kl(logits_q, sg(logits_p))


def vae_loss(
    pred: jax.Array,
    target: jax.Array,
    logits_q: jax.Array,
    logits_p: jax.Array,
    weight: jax.Array,
    *,
    kl_coef: float,
    kl_balance: float,
) -> tuple[jax.Array, dict]:
    """``mean_w sum_dims (pred - target)^2 + kl_coef * mean_w balanced_kl(q, p)``.

    Args:
      pred, target: ``[B, T, D]`` decoder output and x_{t+D}; logits_q, logits_p: ``[B, T, G, C]``
        posterior and prior logits at t; weight: ``[B, T]``, 1 for real steps, 0 for padding.

    Returns:
      ``(loss, {"recon", "kl"})``, the two terms as weighted means over steps.
    """
    if pred.shape != target.shape or weight.shape != pred.shape[:2] or logits_q.shape[:2] != weight.shape:
        raise ValueError(
            f"shapes pred {pred.shape}, target {target.shape}, logits {logits_q.shape}, "
            f"weight {weight.shape}; expected [B, T, D], [B, T, D], [B, T, G, C], [B, T]"
        )
    denom = jnp.maximum(weight.sum(), 1.0)
    recon = jnp.sum(weight * jnp.sum(jnp.square(pred - target), axis=-1)) / denom
    kl = jnp.sum(weight * balanced_kl(logits_q, logits_p, kl_balance)) / denom
    return recon + kl_coef * kl, {"recon": recon, "kl": kl}


def preference_bce(return_1: jax.Array, return_2: jax.Array, label: jax.Array) -> jax.Array:
    """Per-pair ``BCEWithLogits(return_2 - return_1, label)`` ``[B]``; label 0.5 is a tie."""
    return optax.sigmoid_binary_cross_entropy(return_2 - return_1, label)


def huber_to_zero(r: jax.Array) -> jax.Array:
    """Elementwise Huber(delta = 1) of r toward 0: ``r^2 / 2`` if ``|r| <= 1`` else ``|r| - 1/2``."""
    return optax.huber_loss(r, delta=1.0)


def decoder_targets(key: jax.Array, valid: jax.Array, future_len: int) -> tuple[jax.Array, jax.Array]:
    """For every position t of ``valid [B, T]`` (a real prefix): D ~ U{0..k}, the target index
    ``min(t + D, last real step)`` and the offset actually predicted ``target - t`` (>= 0)."""
    b, t = valid.shape
    pos = jnp.arange(t)
    last = jnp.sum(valid, axis=1).astype(jnp.int32) - 1  # [B]
    delta = randint(key, (b, t), future_len + 1)
    target = jnp.minimum(pos + delta, last[:, None])
    return target, jnp.maximum(target - pos, 0)
