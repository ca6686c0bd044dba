"""Hindsight Preference Learning (HPL; Gao et al. 2024, arXiv:2407.04451): a reward r(s, a, z)
conditioned on a latent summary z of the future, marginalised over a prior p(z | s, a).

The networks (hindsight encoder, prior, decoder, reward) and the pure loss terms are in
:mod:`spot.reward.hpl_nets`; this module holds the objectives and the two training phases.

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

Relabelling: r_hat(s, a) = (1/N) sum_i r(s, a, z_i), z_i ~ p(z | s, a), N = ``prior_samples``
(:func:`spot.reward.hpl_nets.prior_marginal_reward`, run over a dataset by
:func:`spot.reward.relabel.relabel_hpl`).

Reference facts followed [typoverflow/WiseRL : wiserl/algorithm/hpl/hpl.py] (reference/algorithms.md
§4; the networks' are listed in :mod:`spot.reward.hpl_nets`): the decoder gets the clipped D;
reconstruction ``sum(-1).mean()``; KL balancing with detached logits; posterior z sampled for the reward loss
(``stoc_encoding`` default); logit = difference of *summed* rewards, ``BCEWithLogits``
with y in {0, 0.5, 1}; Huber(delta = 1) of the prior-latent reward toward 0 on the extra batch
repeated ``prior_sample`` times (skipped when reg_coef = 0); Adam(lr) for every net; no gradient clipping.

Deviations and choices (the reference is silent or we differ on purpose):

* **Segment ends.** Windows are truncated at the end of the segment: at the last k positions of a
  labelled segment (and of an unlabelled one) the encoder sees only the steps up to the segment end,
  in training and in the reward phase alike (WiseRL does the same; no steps beyond the segment).
* **Unlabelled segments** start at any row (uniform over transitions) and are right-padded and
  masked at the end of their episode (WiseRL's tuned configs use ``padding_mode: none``, full
  windows only); so short episodes (medium-replay, tiny datasets) also train the prior that
  relabels them. Padded steps are masked as keys and excluded from every loss term.
* **Decoder pairs.** Every real position t of each segment gets one D ~ U{0..k} (B * T pairs);
  WiseRL evaluates all B segments at 4B shared random positions. Same expected loss.
* **Reward phase encoder** is frozen and run without dropout (WiseRL leaves its dropout on), so its
  posterior logits are computed once per labelled pair before the phase; each step only samples z.
* **Steps.** Each phase runs exactly its ``*_steps`` in :mod:`spot.loop` chunks of ``chunk`` steps
  (the last one shorter, same compiled program).
* **Held-out evaluation** after every chunk of ``chunk`` steps: loss/accuracy with posterior z (a fixed
  eval key) select the kept reward parameters (best held-out loss, as :mod:`spot.reward.train`;
  WiseRL keeps the last); the prior-marginalised loss/accuracy (what relabelling uses) is logged too.
  Accuracy counts non-tie pairs only.
* **Random draws** inside the jitted programs use :func:`spot.reward.hpl_nets.random_bits` (a counter
  hash seeded by one draw from the explicit key).
* **Timing**: ``vae_s`` / ``reward_s`` are whole-phase wall times (compile, posterior encoding and
  held-out evaluation included) for stage-time tables; ``*_steps_per_s`` exclude compilation.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from spot import SpotError, loop, padding
from spot.config import HPLConfig
from spot.nets import Params
from spot.reward.hpl_nets import (
    Decoder,
    decoder_targets,
    encode,
    huber_to_zero,
    init_params,
    preference_bce,
    prior_logits,
    prior_marginal_reward,
    randint,
    random_bits,
    reward,
    sample_latent,
    vae_loss,
)
from spot.reward.train import pref_pairs
from spot.reward.update import PrefPairs

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


# --------------------------------------------------------------------------- phase 1: VAE
def sample_segments(key: jax.Array, data: Any, batch: int, length: int) -> tuple[jax.Array, jax.Array]:
    """``batch`` segments of ``length`` steps from uniform start rows, right-padded (zeros) at their
    episode's end: ``x [B, L, D]``, ``valid [B, L]`` float32. ``data``: :class:`Unlabelled`, or
    :class:`spot.padding.Rows` of it (starts drawn from the real rows: the same draws)."""
    start = randint(key, (batch,), padding.count(data))
    data = padding.rows_of(data)
    idx = start[:, None] + jnp.arange(length)  # [B, L]
    valid = idx < data.episode_end[start][:, None]
    x = data.x[jnp.where(valid, idx, start[:, None])] * valid[..., None]
    return x, valid.astype(jnp.float32)


def vae_objective(
    params: Params, cfg: HPLConfig, x: jax.Array, valid: jax.Array, key: jax.Array
) -> tuple[jax.Array, dict]:
    """The VAE loss of segments ``x [B, T, D]`` (module docstring), with dropout and sampled z, D."""
    enc_key, z_key, delta_key = jax.random.split(key, 3)
    logits_q = encode(params, cfg, x, valid, enc_key)
    z = sample_latent(z_key, logits_q)
    target_idx, delta = decoder_targets(delta_key, valid, cfg.future_len)
    target = jnp.take_along_axis(x, target_idx[..., None], axis=1)
    pred = Decoder(cfg, x.shape[-1]).apply(params["decoder"], x, z.reshape(*z.shape[:-2], -1), delta)
    return vae_loss(
        pred, target, logits_q, prior_logits(params, cfg, x), valid, kl_coef=cfg.kl_coef, kl_balance=cfg.kl_balance
    )


def make_vae_update(cfg: HPLConfig) -> Callable[[HPLState, Any, jax.Array], tuple[HPLState, dict]]:
    """``update(state, data, key) -> (state, {loss, recon, kl})``: one VAE step on ``vae_batch``
    segments drawn with ``fold_in(key, state.step)``; ``state.params`` = encoder, prior and decoder."""
    tx = optax.adam(cfg.lr)

    def update(state: HPLState, data: Any, key: jax.Array) -> tuple[HPLState, dict]:
        seg_key, loss_key = jax.random.split(jax.random.fold_in(key, state.step))
        x, valid = sample_segments(seg_key, data, cfg.vae_batch, cfg.seq_len)
        (loss, info), grads = jax.value_and_grad(vae_objective, has_aux=True)(state.params, cfg, x, valid, loss_key)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        return HPLState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), {"loss": loss, **info}

    return update


@functools.lru_cache(maxsize=8)
def make_vae_chunk(cfg: HPLConfig, length: int) -> Callable:
    """Jitted ``chunk(state, n, data: Unlabelled, key) -> (state, {loss, recon, kl, active} [length])``
    (:func:`spot.loop.make_chunk`), kept per config and length."""
    return loop.make_chunk(make_vae_update(cfg), length, "stack")


# --------------------------------------------------------------------------- phase 2: reward
def _pair_returns(
    reward_params: Params, cfg: HPLConfig, pairs: LabelledPairs, key: jax.Array
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
    return jnp.stack(
        [
            jnp.sum(weight * preference_bce(ret_1, ret_2, label)),
            jnp.sum(weight),
            jnp.sum(non_tie * correct),
            jnp.sum(non_tie),
        ]
    )


def reward_objective(
    reward_params: Params,
    prior_params: Params,
    cfg: HPLConfig,
    pairs: LabelledPairs,
    extra_x: jax.Array,
    key: jax.Array,
) -> tuple[jax.Array, dict]:
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


def make_reward_update(cfg: HPLConfig, batch_size: int) -> Callable:
    """``update(state, pairs, prior_params, x_all [N, D], key) -> (state, {loss, bce, reg, acc})``:
    one reward step on ``batch_size`` distinct pairs; ``state.params`` = the reward net's. ``x_all``
    may be :class:`spot.padding.Rows` (the regulariser's rows drawn from the real ones)."""
    tx = optax.adam(cfg.lr)

    def update(
        state: HPLState, pairs: LabelledPairs, prior_params: Params, x_all: Any, key: jax.Array
    ) -> tuple[HPLState, dict]:
        batch_key, extra_key, loss_key = jax.random.split(jax.random.fold_in(key, state.step), 3)
        idx = jnp.argsort(random_bits(batch_key, pairs.label.shape))[:batch_size]  # distinct pairs
        mb = jax.tree.map(lambda a: a[idx], pairs)
        extra_x = padding.take(x_all, randint(extra_key, (cfg.extra_batch,), padding.count(x_all)))
        (loss, info), grads = jax.value_and_grad(reward_objective, has_aux=True)(
            state.params, prior_params, cfg, mb, extra_x, loss_key
        )
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        return HPLState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), {"loss": loss, **info}

    return update


@functools.lru_cache(maxsize=8)
def make_reward_chunk(cfg: HPLConfig, batch_size: int, length: int) -> Callable:
    """Jitted ``chunk(state, n, pairs, prior_params, x_all, key) -> (state, {loss, bce, reg, acc,
    active} [length])`` (:func:`spot.loop.make_chunk`), kept per config and sizes."""
    return loop.make_chunk(make_reward_update(cfg, batch_size), length, "stack")


@functools.lru_cache(maxsize=8)
def make_evaluate(cfg: HPLConfig) -> Callable:
    """``evaluate(reward_params, prior_params, pairs [M, b, ...], weight [M, b], key)`` ->
    ``(loss, acc, prior_loss, prior_acc)``: posterior-z and prior-marginalised BCE / non-tie accuracy."""

    def evaluate(
        reward_params: Params, prior_params: Params, pairs: LabelledPairs, weight: jax.Array, key: jax.Array
    ) -> tuple[jax.Array, ...]:
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


@functools.partial(jax.jit, static_argnums=1)
def _encode_minibatches(params: Params, cfg: HPLConfig, x: jax.Array, mask: jax.Array) -> jax.Array:
    """Deterministic posterior logits of minibatches ``x [M, b, T, D]`` -> ``[M, b, T, G, C]``."""
    return jax.lax.map(lambda a: encode(params, cfg, *a), (x, mask))


def _checked_pairs(batch: Mapping[str, np.ndarray], cfg: HPLConfig, ds: Any, where: str) -> PrefPairs:
    """:func:`spot.reward.train.pref_pairs` plus HPL's limits: ``T <= seq_len``, the dataset's dims."""
    pairs = pref_pairs(batch, where)
    t, o, a = pairs.obs_1.shape[1], pairs.obs_1.shape[2], pairs.act_1.shape[2]
    if t > cfg.seq_len:
        raise SpotError(
            f"{where}: segments of {t} steps exceed hpl.seq_len {cfg.seq_len}; the hindsight "
            "encoder's positional embedding covers seq_len steps (set hpl.seq_len >= segment length)"
        )
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
        (x_mb, mask_mb), _ = loop.pad_minibatches((x, mask), size)
        post = _encode_minibatches(params, cfg, jnp.asarray(x_mb), jnp.asarray(mask_mb))
        fields.update(
            {
                f"x_{s}": jnp.asarray(x),
                f"mask_{s}": jnp.asarray(mask),
                f"post_{s}": post.reshape(-1, *post.shape[2:])[:q],
            }
        )
    return LabelledPairs(**fields)


def unlabelled(ds: Any, padded: bool = False) -> Any:
    """The dataset's (:class:`spot.data.dataset.Dataset`, qlearning view) transitions as device arrays for segment /
    transition sampling: :class:`Unlabelled`, or with ``padded`` :class:`spot.padding.Rows` of it
    (rows padded to a bucket: one program for every dataset of a bucket, the same draws)."""
    starts, ends = ds.episode_bounds()
    x = np.concatenate([ds.observations, ds.actions], axis=-1).astype(np.float32)
    data = Unlabelled(x, np.repeat(ends, ends - starts).astype(np.int32))
    return jax.device_put(padding.padded(data) if padded else data)


# --------------------------------------------------------------------------- driver
@functools.lru_cache(maxsize=8)
def adam_init(lr: float) -> Callable[[Params], optax.OptState]:
    """``optax.adam(lr).init`` as one jitted program per learning rate (kept): eagerly, one small
    program per parameter shape, again for every new observation size in a process."""
    return jax.jit(optax.adam(lr).init)


def _train_vae(
    cfg: HPLConfig, params: Params, data: Any, key: jax.Array, progress: bool
) -> tuple[Params, dict[str, Any]]:
    """Phase 1: the encoder, prior and decoder for exactly ``cfg.vae_steps`` steps."""
    t0 = time.perf_counter()
    vae_params = {k: params[k] for k in ("encoder", "prior", "decoder")}
    state = HPLState(vae_params, adam_init(cfg.lr)(vae_params), jnp.zeros((), jnp.int32))
    length = loop.chunk_length(cfg.vae_steps, cfg.chunk)
    chunk = make_vae_chunk(cfg, length)
    compile_s = loop.compile_seconds(chunk, state, length, data, key)
    out = loop.run(
        chunk,
        state,
        (data, key),
        steps=cfg.vae_steps,
        length=length,
        losses={"loss": "hpl/vae_loss"},
        progress=progress,
        desc="hpl vae",
    )
    history = {
        "vae_step": loop.column(out.rows, "step"),
        **{f"vae_{name}": loop.column(out.rows, name) for name in ("loss", "recon", "kl")},
        "vae_compile_s": compile_s,
        "vae_loop_s": out.loop_s,
        "vae_s": time.perf_counter() - t0,
    }
    return out.state.params, history


def _train_reward(
    cfg: HPLConfig,
    params: Params,
    train_pairs: PrefPairs,
    eval_pairs: PrefPairs | None,
    x_all: Any,
    key: jax.Array,
    eval_key: jax.Array,
    progress: bool,
) -> tuple[Params, dict[str, Any]]:
    """Phase 2: the reward net for exactly ``cfg.reward_steps`` steps; returns the best held-out one."""
    t0 = time.perf_counter()
    train = _labelled(params, cfg, train_pairs)
    held_out = train if eval_pairs is None else _labelled(params, cfg, eval_pairs)
    q_train, q_eval = int(train.label.shape[0]), int(held_out.label.shape[0])
    eval_data, eval_weight = jax.device_put(loop.pad_minibatches(held_out, min(EVAL_PAIRS, q_eval)))
    batch_size = min(cfg.reward_batch, q_train)
    state = HPLState(params["reward"], adam_init(cfg.lr)(params["reward"]), jnp.zeros((), jnp.int32))
    length = loop.chunk_length(cfg.reward_steps, cfg.chunk)
    chunk, evaluate = make_reward_chunk(cfg, batch_size, length), make_evaluate(cfg)
    args = (train, params["prior"], x_all, key)
    compile_s = loop.compile_seconds(chunk, state, length, *args) + loop.compile_seconds(
        evaluate, state.params, params["prior"], eval_data, eval_weight, eval_key
    )
    names = ("eval_loss", "eval_acc", "eval_prior_loss", "eval_prior_acc")
    out = loop.run(
        chunk,
        state,
        args,
        steps=cfg.reward_steps,
        length=length,
        losses={"loss": "hpl/reward_loss"},
        evaluate=lambda st: dict(
            zip(names, evaluate(st.params, params["prior"], eval_data, eval_weight, eval_key), strict=True)
        ),
        eval_loss=("eval_loss", "hpl/eval_loss"),
        best_by="eval_loss",
        progress=progress,
        desc="hpl reward",
    )
    history = {
        "reward_step": loop.column(out.rows, "step"),
        **{f"train_{name}": loop.column(out.rows, name) for name in ("loss", "bce", "reg", "acc")},
        **{name: loop.column(out.rows, name) for name in names},
        "best_step": out.best["step"],
        "best_eval_loss": out.best["eval_loss"],
        "best_eval_acc": out.best["eval_acc"],
        "batch_size": batch_size,
        "reward_compile_s": compile_s,
        "reward_loop_s": out.loop_s,
    }
    best = jax.device_put(out.best_params)
    history["reward_s"] = time.perf_counter() - t0
    return best, history


def train_hpl(
    key: jax.Array,
    ds: Any,
    train_batch: Mapping[str, np.ndarray],
    eval_batch: Mapping[str, np.ndarray] | None,
    cfg: HPLConfig,
    progress: bool = False,
) -> tuple[Params, dict[str, Any]]:
    """Train HPL: the VAE on unlabelled segments of ``ds``, then the reward on preference pairs.

    Args:
      key: PRNG key (split into init, VAE, reward and eval keys).
      ds: the ``qlearning`` view (:class:`spot.data.dataset.Dataset`; unlabelled segments and the
        regulariser's transitions).
      train_batch, eval_batch: ``segment_batch`` dicts (:func:`spot.reward.train.pref_pairs`), segment
        length <= ``cfg.seq_len``; an empty or missing eval batch evaluates on the training pairs.
      cfg: :class:`HPLConfig`; each phase runs exactly its steps in :mod:`spot.loop` chunks of
        ``cfg.chunk`` steps.
      progress: tqdm bars over steps.

    Returns:
      ``(params, history)``: ``params = {"encoder", "prior", "decoder", "reward"}`` with the reward
      net of the best held-out (posterior-z) loss; ``history`` has per-chunk lists ``vae_step``,
      ``vae_loss``, ``vae_recon``, ``vae_kl``, ``reward_step``, ``train_loss``, ``train_bce``,
      ``train_reg``, ``train_acc`` (chunk means), ``eval_loss``, ``eval_acc``, ``eval_prior_loss``,
      ``eval_prior_acc``; and ``best_step``, ``best_eval_loss``, ``best_eval_acc``, ``eval_on``,
      ``batch_size``, ``vae_s`` / ``reward_s`` (wall seconds of each phase, compile included),
      ``vae_compile_s`` / ``reward_compile_s`` (next to nothing when compiled before in this process),
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
    data = unlabelled(ds, padded=True)  # one program per env (spot.padding)
    params = init_params(init_key, cfg, ds.obs_dim, ds.act_dim)
    vae_params, vae_history = _train_vae(cfg, params, data, vae_key, progress)
    params.update(vae_params)
    params["reward"], history = _train_reward(
        cfg, params, train_pairs, eval_pairs, padding.part(data, lambda u: u.x), reward_key, eval_key, progress
    )
    history.update(vae_history, eval_on=eval_on)
    vae_loop_s, reward_loop_s = history.pop("vae_loop_s"), history.pop("reward_loop_s")
    history.update(
        vae_steps_per_s=cfg.vae_steps / vae_loop_s,
        reward_steps_per_s=cfg.reward_steps / reward_loop_s,
        steps_per_s=(cfg.vae_steps + cfg.reward_steps) / (vae_loop_s + reward_loop_s),
    )
    return params, history
