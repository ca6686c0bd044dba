"""Hindsight Preference Learning (HPL; Gao et al. 2024, arXiv:2407.04451): a reward r(s, a, z)
conditioned on a latent summary z of the future, marginalised over a prior p(z | s, a).

Model (x_t = [s_t; a_t], k = ``HPLConfig.future_len``, z = G one-hot categoricals of C classes):

* hindsight encoder q(z_t | x_t .. x_{t+k}): a non-causal GPT-2 over one token per step (input
  Dense + learned positional embedding + dropout, ``n_layer`` pre-LN blocks, final LayerNorm),
  whose attention lets token t see keys j in [t, t+k] only; a Dense head gives logits ``[G, C]``.
* prior p(z | s, a): MLP on x_t to the same logits.
* decoder p(x_{t+D} | x_t, z_t, D): ReLU(concat(Dense(x_t), Dense(z_t), Embed(D))) -> MLP -> x_hat.
* reward r(s, a, z): MLP on [x; z], sigmoid output when ``reward_sigmoid``.

Phase 1, VAE on unlabelled segments of ``seq_len`` steps (WiseRL ``update_vae``):

    L_vae = E_{t, D ~ U{0..k}} ||x_hat_{t+D} - x_{t+D}||^2
            + beta * E_t [ a KL(sg(q_t) || p_t) + (1 - a) KL(q_t || sg(p_t)) ]

with KL of independent categoricals summed over the G groups, z_t ~ q sampled with straight-through
gradients (forward one-hot, backward d softmax), beta = ``kl_coef``, a = ``kl_balance``; the target
index t + D is clipped to the last real step of the segment and the decoder gets the clipped D.

Phase 2, reward on labelled pairs (y = 1: segment 2 preferred; WiseRL ``update_reward``):

    l = sum_t r(x2_t, z2_t) - sum_t r(x1_t, z1_t),  z_t ~ q(. | x_{t..t+k}) (sampled, no gradient)
    L_r = BCE(l, y) + reg_coef * mean_{i, j} Huber_1(r(x_j, z_ij)),  z_ij ~ p(. | x_j)

over ``extra_batch`` unlabelled transitions x_j, each with ``prior_samples`` prior draws.

Relabelling: r_hat(s, a) = (1/N) sum_i r(s, a, z_i), z_i ~ p(z | s, a), N = ``prior_samples``.

Reference facts followed [typoverflow/WiseRL : wiserl/algorithm/hpl/hpl.py] (reference/algorithms.md
§4): discrete latent (``OneHotCategoricalStraightThrough``, 8 groups); attention mask = not below the
diagonal and not beyond t + future_len (applied in every layer); GPT-2 with GELU MLPs, dropout on
embeddings, attention and residuals [wiserl/module/net/attention/gpt2.py]; the encoder takes no dataset
timesteps (positions 0..T-1 of the segment); decoder input layers and Embedding(k + 1), the clipped
D; reconstruction ``sum(-1).mean()``; KL balancing with detached logits; posterior z sampled for the
reward loss (``stoc_encoding`` default); logit = difference of *summed* rewards, ``BCEWithLogits``
with y in {0, 0.5, 1}; Huber(delta = 1) of the prior-latent reward toward 0 on the extra batch
repeated ``prior_sample`` times (skipped when reg_coef = 0); reward MLP with orthogonal init gain 1,
zero bias [``ortho_init: true``, wiserl/module/net/basic.py ``weight_init``]; the other nets keep
default init; Adam(lr) for every net; no gradient clipping.

Deviations and choices (the reference is silent or we differ on purpose):

* **Receptive field.** Like WiseRL, the [t, t+k] mask is applied in every layer, so with n_layer
  blocks the output at t depends on x_t .. x_{t + n_layer * k} (never on the past). Exactly
  [t, t+k] holds for n_layer = 1 (tested both ways).
* **Segment ends.** Windows are truncated at the end of the segment: at the last k positions of a
  labelled segment (and of an unlabelled one) the encoder sees only the steps up to the segment end,
  in training and in the reward phase alike (WiseRL does the same; no steps beyond the segment).
* **Unlabelled segments** start at any row (uniform over transitions) and are right-padded and
  masked at the end of their episode (WiseRL's tuned configs use ``padding_mode: none``, full
  windows only); so short episodes (medium-replay, tiny datasets) also train the prior that
  relabels them. Padded steps are masked as keys and excluded from every loss term.
* **Decoder pairs.** Every real position t of each segment gets one D ~ U{0..k} (B * T pairs);
  WiseRL evaluates all B segments at 4B shared random positions. Same expected loss.
* **Decoder width** is ``decoder_embd`` (64, the tuned configs' ``decoder.embed_dim``); WiseRL's code
  passes ``z_dim`` (128) instead and ignores that key.
* **Reward phase encoder** is frozen and run without dropout (WiseRL leaves its dropout on), so its
  posterior logits are computed once per labelled pair before the phase; each step only samples z.
* **Held-out evaluation** after every chunk of ``chunk`` steps: loss/accuracy with posterior z (a fixed
  eval key) select the kept reward parameters (best held-out loss, as :mod:`spot.reward.train`;
  WiseRL keeps the last); the prior-marginalised loss/accuracy (what relabelling uses) is logged too.
  Accuracy counts non-tie pairs only.
* **Random draws** inside the jitted programs (latent samples, segment starts, D, minibatches) use
  :func:`random_bits`, a counter hash seeded by one draw from the explicit key (as
  :class:`spot.nets.Dropout`), not a threefry draw per element: same key discipline, ~1 s less XLA
  compile per call site on CPU.
* **Timing**: ``vae_s`` / ``reward_s`` are whole-phase wall times (compile, posterior encoding and
  held-out evaluation included) for stage-time tables; ``*_steps_per_s`` exclude compilation.
"""

from __future__ import annotations

import collections
import functools
import math
import time
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from spot import NonFiniteError, SpotError
from spot.config import HPLConfig
from spot.data.dataset import Dataset
from spot.nets import (
    LN_EPS,
    MLP,
    Dropout,
    Params,
    TransformerBlock,
    compile_cached,
    hash_bits,
    orthogonal_init,
)
from spot.reward.train import PrefPairs, pref_pairs

# Times each phase's train chunk was traced (tests assert one trace per training run).
TRACE_COUNT: collections.Counter[str] = collections.Counter()
EVAL_PAIRS = 64  # pairs per minibatch when encoding / evaluating labelled pairs


class HPLState(NamedTuple):
    """Training state of one phase: the trained nets' params, Adam state and steps taken."""

    params: Params
    opt_state: optax.OptState
    step: jax.Array


class Unlabelled(NamedTuple):
    """Dataset transitions on device. ``x [N, obs_dim + act_dim]`` = [s; a]; ``episode_end [N]``
    int32, the (exclusive) end row of each row's episode."""

    x: jax.Array
    episode_end: jax.Array


class LabelledPairs(NamedTuple):
    """Preference pairs with their frozen posterior logits. ``x_* [Q, T, D]``, ``mask_* [Q, T]``,
    ``post_* [Q, T, G, C]``, ``label [Q]`` (1 = segment 2 preferred, 0.5 = tie)."""

    x_1: jax.Array
    mask_1: jax.Array
    post_1: jax.Array
    x_2: jax.Array
    mask_2: jax.Array
    post_2: jax.Array
    label: jax.Array


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


def random_bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """uint32 bits ``[shape]``: :func:`spot.nets.hash_bits` seeded by one 32-bit draw from ``key``.

    Every shaped random draw of this module goes through here (as :class:`spot.nets.Dropout` does):
    the randomness still comes from the explicit key, but a threefry draw per element costs ~1 s of
    XLA compile per call site on CPU and ~9x the run time.
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


def vae_loss(pred: jax.Array, target: jax.Array, logits_q: jax.Array, logits_p: jax.Array,
             weight: jax.Array, *, kl_coef: float, kl_balance: float) -> tuple[jax.Array, dict]:
    """``mean_w sum_dims (pred - target)^2 + kl_coef * mean_w balanced_kl(q, p)``.

    Args:
      pred, target: ``[B, T, D]`` decoder output and x_{t+D}; logits_q, logits_p: ``[B, T, G, C]``
        posterior and prior logits at t; weight: ``[B, T]``, 1 for real steps, 0 for padding.

    Returns:
      ``(loss, {"recon", "kl"})``, the two terms as weighted means over steps.
    """
    if pred.shape != target.shape or weight.shape != pred.shape[:2] or logits_q.shape[:2] != weight.shape:
        raise ValueError(f"shapes pred {pred.shape}, target {target.shape}, logits {logits_q.shape}, "
                         f"weight {weight.shape}; expected [B, T, D], [B, T, D], [B, T, G, C], [B, T]")
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
                h, mask, deterministic=deterministic)
        h = nn.LayerNorm(epsilon=LN_EPS, name="out_ln")(h)
        return nn.Dense(cfg.latent_groups * cfg.latent_classes, name="proj")(h).reshape(
            b, t, cfg.latent_groups, cfg.latent_classes)


class Decoder(nn.Module):
    """p(x_{t+D} | x_t, z_t, D): ``x [..., D_x]``, ``z [..., G*C]``, ``delta [...]`` int -> x_hat."""

    cfg: HPLConfig
    out_dim: int

    @nn.compact
    def __call__(self, x: jax.Array, z: jax.Array, delta: jax.Array) -> jax.Array:
        e = self.cfg.decoder_embd
        h = jnp.concatenate([nn.Dense(e, name="x_embed")(x), nn.Dense(e, name="z_embed")(z),
                             nn.Embed(self.cfg.future_len + 1, e, name="delta_embed")(delta)], axis=-1)
        return MLP(self.cfg.decoder_hidden, self.out_dim, name="unify")(nn.relu(h))


def _prior_net(cfg: HPLConfig) -> MLP:
    return MLP(cfg.prior_hidden, cfg.latent_groups * cfg.latent_classes)


def _reward_net(cfg: HPLConfig) -> MLP:
    return MLP(cfg.reward_hidden, 1, kernel_init=orthogonal_init(1.0))


# The HPLConfig fields that shape the parameters.
_ARCH_FIELDS = ("seq_len", "future_len", "latent_groups", "latent_classes", "embd_dim", "n_layer", "n_head",
                "decoder_hidden", "decoder_embd", "prior_hidden", "reward_hidden")


def init_params(key: jax.Array, cfg: HPLConfig, obs_dim: int, act_dim: int) -> Params:
    """``{"encoder", "prior", "decoder", "reward"}`` parameter dicts."""
    arch = HPLConfig(**{f: getattr(cfg, f) for f in _ARCH_FIELDS})  # configs that differ elsewhere share one
    return _init_program(arch, obs_dim, act_dim)(key)


@functools.lru_cache(maxsize=8)
def _init_program(cfg: HPLConfig, obs_dim: int, act_dim: int) -> Callable[[jax.Array], Params]:
    """All four nets' init as one program at optimisation level 0 (as :func:`spot.nets.jit_init`),
    kept per config and dims so that further seeds do not compile it again."""
    d, z = obs_dim + act_dim, cfg.latent_groups * cfg.latent_classes
    x = jnp.zeros((cfg.seq_len, d), jnp.float32)

    def init(key: jax.Array) -> Params:
        k = jax.random.split(key, 4)
        return {
            "encoder": HindsightEncoder(cfg).init(k[0], x[None], jnp.ones((1, cfg.seq_len))),
            "prior": _prior_net(cfg).init(k[1], x),
            "decoder": Decoder(cfg, d).init(k[2], x, jnp.zeros((cfg.seq_len, z)), jnp.zeros(cfg.seq_len, jnp.int32)),
            "reward": _reward_net(cfg).init(k[3], jnp.zeros((1, d + z), jnp.float32)),
        }

    return jax.jit(init, compiler_options={"xla_backend_optimization_level": 0})


def encode(params: Params, cfg: HPLConfig, x: jax.Array, valid: jax.Array,
           dropout_key: jax.Array | None = None) -> jax.Array:
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


# --------------------------------------------------------------------------- phase 1: VAE
def sample_segments(key: jax.Array, data: Unlabelled, batch: int, length: int) -> tuple[jax.Array, jax.Array]:
    """``batch`` segments of ``length`` steps from uniform start rows, right-padded (zeros) at their
    episode's end: ``x [B, L, D]``, ``valid [B, L]`` float32."""
    start = randint(key, (batch,), data.x.shape[0])
    idx = start[:, None] + jnp.arange(length)  # [B, L]
    valid = idx < data.episode_end[start][:, None]
    x = data.x[jnp.where(valid, idx, start[:, None])] * valid[..., None]
    return x, valid.astype(jnp.float32)


def vae_objective(params: Params, cfg: HPLConfig, x: jax.Array, valid: jax.Array,
                  key: jax.Array) -> tuple[jax.Array, dict]:
    """The VAE loss of segments ``x [B, T, D]`` (module docstring), with dropout and sampled z, D."""
    enc_key, z_key, delta_key = jax.random.split(key, 3)
    logits_q = encode(params, cfg, x, valid, enc_key)
    z = sample_latent(z_key, logits_q)
    target_idx, delta = decoder_targets(delta_key, valid, cfg.future_len)
    target = jnp.take_along_axis(x, target_idx[..., None], axis=1)
    pred = Decoder(cfg, x.shape[-1]).apply(params["decoder"], x, z.reshape(*z.shape[:-2], -1), delta)
    return vae_loss(pred, target, logits_q, prior_logits(params, cfg, x), valid,
                    kl_coef=cfg.kl_coef, kl_balance=cfg.kl_balance)


def _scan_chunk(name: str, update: Callable, chunk_len: int, total_steps: int, idle: dict) -> Callable:
    """``chunk(state, *args) -> (state, metrics [chunk_len])``: ``update`` scanned; steps at or past
    ``total_steps`` leave the state unchanged (``active`` False), so a last partial chunk reuses the
    compiled program. The state is donated."""

    def chunk(state: HPLState, *args: Any) -> tuple[HPLState, dict]:
        TRACE_COUNT[name] += 1

        def body(state: HPLState, _: None) -> tuple[HPLState, dict]:
            active = state.step < total_steps
            state, metrics = jax.lax.cond(active, lambda s: update(s, *args), lambda s: (s, idle), state)
            return state, {**metrics, "active": active}

        return jax.lax.scan(body, state, None, length=chunk_len)

    return jax.jit(chunk, donate_argnums=0)


def make_vae_chunk(cfg: HPLConfig, chunk_len: int, total_steps: int) -> Callable:
    """``chunk(state, data: Unlabelled, key) -> (state, {loss, recon, kl, active} [chunk_len])``;
    step i uses ``fold_in(key, i)``; ``state.params`` = encoder, prior and decoder."""
    tx = optax.adam(cfg.lr)

    def update(state: HPLState, data: Unlabelled, key: jax.Array) -> tuple[HPLState, dict]:
        seg_key, loss_key = jax.random.split(jax.random.fold_in(key, state.step))
        x, valid = sample_segments(seg_key, data, cfg.vae_batch, cfg.seq_len)
        (loss, info), grads = jax.value_and_grad(vae_objective, has_aux=True)(state.params, cfg, x, valid, loss_key)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        return HPLState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), {"loss": loss, **info}

    zero = jnp.zeros((), jnp.float32)
    return _scan_chunk("hpl/vae", update, chunk_len, total_steps, {"loss": zero, "recon": zero, "kl": zero})


# --------------------------------------------------------------------------- phase 2: reward
def _pair_returns(reward_params: Params, cfg: HPLConfig, pairs: LabelledPairs, key: jax.Array
                  ) -> tuple[jax.Array, jax.Array]:
    """Masked sums over t of ``r(x_t, z_t)``, ``z_t`` sampled from the stored posterior logits."""
    post = jnp.concatenate([pairs.post_1, pairs.post_2])
    z = jax.lax.stop_gradient(sample_latent(key, post))
    r = reward({"reward": reward_params}, cfg, jnp.concatenate([pairs.x_1, pairs.x_2]), z)  # [2B, T]
    ret = jnp.sum(r * jnp.concatenate([pairs.mask_1, pairs.mask_2]), axis=1)
    return jnp.split(ret, 2)


def _counts(ret_1: jax.Array, ret_2: jax.Array, label: jax.Array, weight: jax.Array) -> jax.Array:
    """``[sum w bce, sum w, sum w' correct, sum w']`` with w' = w on non-tie pairs."""
    non_tie = weight * (label != 0.5)
    correct = (ret_2 > ret_1) == (label > 0.5)
    return jnp.stack([jnp.sum(weight * preference_bce(ret_1, ret_2, label)), jnp.sum(weight),
                      jnp.sum(non_tie * correct), jnp.sum(non_tie)])


def reward_objective(reward_params: Params, prior_params: Params, cfg: HPLConfig, pairs: LabelledPairs,
                     extra_x: jax.Array, key: jax.Array) -> tuple[jax.Array, dict]:
    """``mean BCE + reg_coef * mean Huber(r(x_j, z_prior))`` (module docstring) and
    ``{bce, reg, acc}``."""
    z_key, prior_key = jax.random.split(key)
    ret_1, ret_2 = _pair_returns(reward_params, cfg, pairs, z_key)
    sums = _counts(ret_1, ret_2, pairs.label, jnp.ones_like(pairs.label))
    bce = sums[0] / sums[1]
    reg = jnp.zeros((), jnp.float32)
    if cfg.reg_coef > 0.0:  # static: WiseRL skips the term at 0
        params = {"prior": prior_params, "reward": reward_params}
        logits = jax.lax.stop_gradient(prior_logits(params, cfg, extra_x))
        z = sample_latent(prior_key, jnp.broadcast_to(logits, (cfg.prior_samples, *logits.shape)))
        r = reward(params, cfg, jnp.broadcast_to(extra_x, (cfg.prior_samples, *extra_x.shape)), z)
        reg = jnp.mean(huber_to_zero(r))
    return bce + cfg.reg_coef * reg, {"bce": bce, "reg": reg, "acc": sums[2] / jnp.maximum(sums[3], 1.0)}


def make_reward_chunk(cfg: HPLConfig, batch_size: int, chunk_len: int, total_steps: int) -> Callable:
    """``chunk(state, pairs, prior_params, x_all [N, D], key) -> (state, {loss, bce, reg, acc, active})``;
    ``state.params`` = the reward net's."""
    tx = optax.adam(cfg.lr)

    def update(state: HPLState, pairs: LabelledPairs, prior_params: Params, x_all: jax.Array,
               key: jax.Array) -> tuple[HPLState, dict]:
        batch_key, extra_key, loss_key = jax.random.split(jax.random.fold_in(key, state.step), 3)
        idx = jnp.argsort(random_bits(batch_key, pairs.label.shape))[:batch_size]  # distinct pairs
        mb = jax.tree.map(lambda a: a[idx], pairs)
        extra_x = x_all[randint(extra_key, (cfg.extra_batch,), x_all.shape[0])]
        (loss, info), grads = jax.value_and_grad(reward_objective, has_aux=True)(
            state.params, prior_params, cfg, mb, extra_x, loss_key)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        return HPLState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), {"loss": loss, **info}

    zero = jnp.zeros((), jnp.float32)
    return _scan_chunk("hpl/reward", update, chunk_len, total_steps,
                       {"loss": zero, "bce": zero, "reg": zero, "acc": zero})


def make_evaluate(cfg: HPLConfig) -> Callable:
    """``evaluate(reward_params, prior_params, pairs [M, b, ...], weight [M, b], key)`` ->
    ``(loss, acc, prior_loss, prior_acc)``: posterior-z and prior-marginalised BCE / non-tie accuracy."""

    def evaluate(reward_params: Params, prior_params: Params, pairs: LabelledPairs, weight: jax.Array,
                 key: jax.Array) -> tuple[jax.Array, ...]:
        params = {"prior": prior_params, "reward": reward_params}

        def one(args: tuple) -> jax.Array:
            i, mb, w = args
            post_key, prior_key = jax.random.split(jax.random.fold_in(key, i))
            post = _counts(*_pair_returns(reward_params, cfg, mb, post_key), mb.label, w)
            r = prior_marginal_reward(params, cfg, jnp.concatenate([mb.x_1, mb.x_2]), prior_key)
            ret_1, ret_2 = jnp.split(jnp.sum(r * jnp.concatenate([mb.mask_1, mb.mask_2]), axis=1), 2)
            return jnp.concatenate([post, _counts(ret_1, ret_2, mb.label, w)])

        s = jax.lax.map(one, (jnp.arange(weight.shape[0]), pairs, weight)).sum(axis=0)
        return s[0] / s[1], s[2] / jnp.maximum(s[3], 1.0), s[4] / s[5], s[6] / jnp.maximum(s[7], 1.0)

    return jax.jit(evaluate)


def _minibatches(tree: Any, q: int, size: int) -> tuple[Any, np.ndarray]:
    """Host arrays ``[Q, ...]`` padded (repeating row 0) to ``[M, size, ...]``; weight 0 on padding."""
    m = math.ceil(q / size)
    idx = np.concatenate([np.arange(q), np.zeros(m * size - q, np.int64)])
    weight = (np.arange(m * size) < q).astype(np.float32).reshape(m, size)
    return jax.tree.map(lambda a: np.asarray(a)[idx].reshape(m, size, *np.shape(a)[1:]), tree), weight


@functools.partial(jax.jit, static_argnums=1)
def _encode_minibatches(params: Params, cfg: HPLConfig, x: jax.Array, mask: jax.Array) -> jax.Array:
    """Deterministic posterior logits of minibatches ``x [M, b, T, D]`` -> ``[M, b, T, G, C]``."""
    return jax.lax.map(lambda a: encode(params, cfg, *a), (x, mask))


def _checked_pairs(batch: Mapping[str, np.ndarray], cfg: HPLConfig, ds: Dataset, where: str) -> PrefPairs:
    """:func:`spot.reward.train.pref_pairs` plus HPL's limits: ``T <= seq_len``, the dataset's dims."""
    pairs = pref_pairs(batch, where)
    t, o, a = pairs.obs_1.shape[1], pairs.obs_1.shape[2], pairs.act_1.shape[2]
    if t > cfg.seq_len:
        raise SpotError(f"{where}: segments of {t} steps exceed hpl.seq_len {cfg.seq_len}; the hindsight "
                        "encoder's positional embedding covers seq_len steps (set hpl.seq_len >= segment length)")
    if (o, a) != (ds.obs_dim, ds.act_dim):
        raise SpotError(f"{where}: obs/act dims {o}/{a}; dataset '{ds.name}' has {ds.obs_dim}/{ds.act_dim}")
    return pairs


def _labelled(params: Params, cfg: HPLConfig, pairs: PrefPairs) -> LabelledPairs:
    """Device pairs with the frozen encoder's deterministic posterior logits attached."""
    q = pairs.label.shape[0]
    size = min(EVAL_PAIRS, q)
    fields: dict[str, Any] = {"label": jnp.asarray(pairs.label)}
    for s in ("1", "2"):
        x = np.concatenate([getattr(pairs, f"obs_{s}"), getattr(pairs, f"act_{s}")], axis=-1)
        mask = getattr(pairs, f"mask_{s}")
        (x_mb, mask_mb), _ = _minibatches((x, mask), q, size)
        post = _encode_minibatches(params, cfg, jnp.asarray(x_mb), jnp.asarray(mask_mb))
        fields.update({f"x_{s}": jnp.asarray(x), f"mask_{s}": jnp.asarray(mask),
                       f"post_{s}": post.reshape(-1, *post.shape[2:])[:q]})
    return LabelledPairs(**fields)


def unlabelled(ds: Dataset) -> Unlabelled:
    """The dataset's transitions as device arrays for segment / transition sampling."""
    starts, ends = ds.episode_bounds()
    x = np.concatenate([ds.observations, ds.actions], axis=-1).astype(np.float32)
    return Unlabelled(jnp.asarray(x), jnp.asarray(np.repeat(ends, ends - starts).astype(np.int32)))


def _check_finite(values: np.ndarray, first_step: int, name: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise NonFiniteError(first_step + int(bad[0]), name, float(values[bad[0]]))


# --------------------------------------------------------------------------- driver
def train_hpl(key: jax.Array, ds: Dataset, train_batch: Mapping[str, np.ndarray],
              eval_batch: Mapping[str, np.ndarray] | None, cfg: HPLConfig,
              progress: bool = False) -> tuple[Params, dict[str, Any]]:
    """Train HPL: the VAE on unlabelled segments of ``ds``, then the reward on preference pairs.

    Args:
      key: PRNG key (split into init, VAE, reward and eval keys).
      ds: the ``qlearning`` view (unlabelled segments and the regulariser's transitions).
      train_batch, eval_batch: ``segment_batch`` dicts (:func:`spot.reward.train.pref_pairs`), segment
        length <= ``cfg.seq_len``; an empty or missing eval batch evaluates on the training pairs.
      cfg: :class:`HPLConfig`; both phases run in ``jit(lax.scan)`` chunks of ``cfg.chunk`` steps.
      progress: tqdm bars over chunks.

    Returns:
      ``(params, history)``: ``params = {"encoder", "prior", "decoder", "reward"}`` with the reward
      net of the best held-out (posterior-z) loss; ``history`` has per-chunk lists ``vae_step``,
      ``vae_loss``, ``vae_recon``, ``vae_kl``, ``reward_step``, ``train_loss``, ``train_bce``,
      ``train_reg``, ``train_acc`` (chunk means), ``eval_loss``, ``eval_acc``, ``eval_prior_loss``,
      ``eval_prior_acc``; and ``best_step``, ``best_eval_loss``, ``best_eval_acc``, ``eval_on``,
      ``batch_size``, ``vae_s`` / ``reward_s`` (wall seconds of each phase, compile included),
      ``vae_compile_s`` / ``reward_compile_s`` (0 when compiled before in this process),
      ``vae_steps_per_s``, ``reward_steps_per_s``, ``steps_per_s`` (both phases, compile excluded).

    Raises:
      NonFiniteError: a VAE, reward or held-out loss is NaN/inf (``hpl/vae_loss``,
        ``hpl/reward_loss``, ``hpl/eval_loss``).
      SpotError: malformed batches or segments longer than ``cfg.seq_len``.
    """
    train_pairs = _checked_pairs(train_batch, cfg, ds, "train preference batch")
    eval_on = "eval" if eval_batch is not None and np.size(eval_batch.get("label", 1)) > 0 else "train"
    eval_pairs = _checked_pairs(eval_batch, cfg, ds, "eval preference batch") if eval_on == "eval" else None
    init_key, vae_key, reward_key, eval_key = jax.random.split(key, 4)
    del key
    data = unlabelled(ds)
    params = init_params(init_key, cfg, ds.obs_dim, ds.act_dim)
    history: dict[str, Any] = collections.defaultdict(list)

    # ---- phase 1: VAE
    t0 = time.perf_counter()
    vae_params = {k: params[k] for k in ("encoder", "prior", "decoder")}
    state = HPLState(vae_params, optax.adam(cfg.lr).init(vae_params), jnp.zeros((), jnp.int32))
    chunk_len = min(cfg.chunk, cfg.vae_steps)
    vae_chunk, vae_compile_s = compile_cached(("hpl/vae_chunk", cfg, chunk_len),
                                              make_vae_chunk(cfg, chunk_len, cfg.vae_steps), state, data, vae_key)
    t_loop = time.perf_counter()
    for c in tqdm(range(math.ceil(cfg.vae_steps / chunk_len)), desc="hpl vae", disable=not progress, leave=False):
        state, metrics = vae_chunk(state, data, vae_key)
        metrics = jax.device_get(metrics)
        active = metrics["active"]
        _check_finite(metrics["loss"][active], c * chunk_len, "hpl/vae_loss")
        history["vae_step"].append(c * chunk_len + int(active.sum()))
        for name in ("loss", "recon", "kl"):
            history[f"vae_{name}"].append(float(metrics[name][active].mean()))
    params.update(state.params)
    vae_loop_s = time.perf_counter() - t_loop
    vae_s = time.perf_counter() - t0

    # ---- phase 2: reward
    t0 = time.perf_counter()
    train = _labelled(params, cfg, train_pairs)
    held_out = train if eval_pairs is None else _labelled(params, cfg, eval_pairs)
    q_train, q_eval = int(train.label.shape[0]), int(held_out.label.shape[0])
    eval_data, eval_weight = jax.device_put(_minibatches(held_out, q_eval, min(EVAL_PAIRS, q_eval)))
    batch_size = min(cfg.reward_batch, q_train)
    state = HPLState(params["reward"], optax.adam(cfg.lr).init(params["reward"]), jnp.zeros((), jnp.int32))
    chunk_len = min(cfg.chunk, cfg.reward_steps)
    reward_chunk, reward_compile_s = compile_cached(
        ("hpl/reward_chunk", cfg, batch_size, chunk_len),
        make_reward_chunk(cfg, batch_size, chunk_len, cfg.reward_steps), state, train, params["prior"], data.x,
        reward_key)
    evaluate, eval_compile_s = compile_cached(("hpl/evaluate", cfg), make_evaluate(cfg), state.params,
                                              params["prior"], eval_data, eval_weight, eval_key)
    reward_compile_s += eval_compile_s
    best_loss, best_step, best_acc, best_params = math.inf, 0, math.nan, None
    t_loop = time.perf_counter()
    for c in tqdm(range(math.ceil(cfg.reward_steps / chunk_len)), desc="hpl reward", disable=not progress,
                  leave=False):
        state, metrics = reward_chunk(state, train, params["prior"], data.x, reward_key)
        metrics = jax.device_get(metrics)
        active = metrics["active"]
        _check_finite(metrics["loss"][active], c * chunk_len, "hpl/reward_loss")
        steps_done = c * chunk_len + int(active.sum())
        ev = [float(v) for v in jax.device_get(evaluate(state.params, params["prior"], eval_data, eval_weight,
                                                        eval_key))]
        if not math.isfinite(ev[0]):
            raise NonFiniteError(steps_done, "hpl/eval_loss", ev[0])
        if ev[0] < best_loss:
            best_loss, best_step, best_acc = ev[0], steps_done, ev[1]
            best_params = jax.tree.map(lambda a: np.array(a, copy=True), state.params)  # host copy
        history["reward_step"].append(steps_done)
        for name in ("loss", "bce", "reg", "acc"):
            history[f"train_{name}"].append(float(metrics[name][active].mean()))
        for name, value in zip(("eval_loss", "eval_acc", "eval_prior_loss", "eval_prior_acc"), ev, strict=True):
            history[name].append(value)
    reward_loop_s = time.perf_counter() - t_loop
    params["reward"] = jax.device_put(best_params)
    reward_s = time.perf_counter() - t0

    history = dict(history)
    history.update(
        best_step=best_step, best_eval_loss=best_loss, best_eval_acc=best_acc, eval_on=eval_on,
        batch_size=batch_size, vae_s=vae_s, reward_s=reward_s, vae_compile_s=vae_compile_s,
        reward_compile_s=reward_compile_s, vae_steps_per_s=cfg.vae_steps / vae_loop_s,
        reward_steps_per_s=cfg.reward_steps / reward_loop_s,
        steps_per_s=(cfg.vae_steps + cfg.reward_steps) / (vae_loop_s + reward_loop_s),
    )
    return params, history


def relabel_hpl(params: Params, ds: Dataset, cfg: HPLConfig, key: jax.Array, batch_size: int = 4096,
                progress: bool = False) -> np.ndarray:
    """``r_hat(s, a)`` of every transition of ``ds``: :func:`prior_marginal_reward` in jitted batches
    of ``batch_size`` rows (the last padded); batch i uses ``fold_in(key, i)``.

    Returns:
      ``[N]`` float32 (not normalised; see ``relabel.normalize``, HPL's is ``wiserl``).
    """
    x_all = unlabelled(ds).x
    n = x_all.shape[0]
    n_batches = max(math.ceil(n / batch_size), 1)
    rows = np.minimum(np.arange(n_batches * batch_size), n - 1).astype(np.int32).reshape(n_batches, batch_size)
    sub = {"prior": params["prior"], "reward": params["reward"]}

    def program(p: Params, x_all: jax.Array, rows: jax.Array, key: jax.Array) -> jax.Array:
        return prior_marginal_reward(p, cfg, x_all[rows], key)

    compiled, _ = compile_cached(("hpl/relabel", cfg, batch_size), jax.jit(program), sub, x_all, rows[0], key)
    out = [jax.device_get(compiled(sub, x_all, rows[i], jax.random.fold_in(key, i)))
           for i in tqdm(range(n_batches), desc="relabel (hpl)", disable=not progress, leave=False)]
    return np.concatenate(out)[:n].astype(np.float32)
