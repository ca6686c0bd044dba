"""Preference Transformer (Kim et al., ICLR 2023), the reward model of SPOT (paper §3 eq. 3, §4.1.1
eq. 4, App. B.1.1 Table 5).

Architecture exactly as ``TransRewardModel`` of the PT repo with the preference-attention layer
**on** (``use_weighted_sum=True``); reference/algorithms.md §1.1:

1. ``e^s_t = Dense_D(s_t) + E[tau_t]``, ``e^a_t = Dense_D(a_t) + E[tau_t]``; ``E`` is a learned
   timestep embedding with ``max_timestep + 1`` rows; no positional embedding.
2. Tokens interleaved ``(a_1, s_1, ..., a_T, s_T)``, LayerNorm (eps 1e-5), embedding dropout.
3. ``n_layer`` causal pre-LN GPT-2 blocks (:class:`spot.nets.TransformerBlock`, relu MLP of width
   4D, dropout on attention and residuals), padded keys masked, then a final LayerNorm.
4. ``x_t`` = output at the **state** token of step t (it has seen ``a_1, s_1, ..., a_t, s_t``).
5. Preference attention: ``Dense(2P + 1)(x_t) -> q_t, k_t, r_hat_t``; single head, bidirectional,
   **unscaled** ``A_tj = softmax_j(q_t . k_j)`` with padded keys masked, ``z_t = sum_j A_tj r_hat_j``.
6. ``logit = mean_t z_t = sum_j w_j r_hat_j`` with the importance weight ``w_j = mean_t A_tj``
   (column mean; ``sum_j w_j = 1``). These ``w_t`` are SPOT's attention weights (eq. 4) and
   ``r_hat_t`` its per-step rewards (eq. 5).

With padding, the means in 6 run over the real query steps only (the PT repo trains on unpadded
segments, where both agree).

Cost: only state tokens are read out, so the last block computes its queries, attention output and
MLP at the T state tokens only (keys/values still cover all 2T tokens). The numbers are the same as
running the full block, for a fraction of the FLOPs (docs/benchmarks.md).

Mixed precision (``PTConfig.dtype = "bfloat16"``): the transformer blocks' matmuls run in bfloat16;
parameters, the residual stream, the embeddings, every softmax, the preference-attention head and
the loss stay float32.

:class:`PT` is this model behind the reward-model interface (:class:`spot.reward.models.RewardModel`):
``init``, ``apply`` and ``optimizer`` (AdamW(0.9, ``pt.b2``), weight decay ``PTConfig.weight_decay``,
learning rate by default linear from 0 to ``PTConfig.lr`` over ``warmup_steps``, then constant;
:func:`learning_rate` has the PT repo's warmup-cosine schedule too).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from spot import SpotError
from spot.config import PTConfig
from spot.nets import LN_EPS, MASKED_LOGIT, Dropout, Params, TransformerBlock, jit_init

DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


class PreferenceTransformer(nn.Module):
    """PT reward model. Attributes mirror :class:`spot.config.PTConfig`; ``dtype`` is the block
    compute dtype."""

    embd_dim: int
    n_layer: int
    n_head: int
    dropout: float
    pref_attn_dim: int
    max_timestep: int
    dtype: jnp.dtype = jnp.float32

    def setup(self) -> None:
        self.embed_obs = nn.Dense(self.embd_dim)
        self.embed_act = nn.Dense(self.embd_dim)
        self.embed_time = nn.Embed(self.max_timestep + 1, self.embd_dim)
        self.embed_ln = nn.LayerNorm(epsilon=LN_EPS)
        self.embed_drop = Dropout(self.dropout)
        self.blocks = [
            TransformerBlock(self.embd_dim, self.n_head, self.dropout, nn.relu, 4, self.dtype)
            for _ in range(self.n_layer)
        ]
        self.final_ln = nn.LayerNorm(epsilon=LN_EPS)
        self.pref_head = nn.Dense(2 * self.pref_attn_dim + 1)

    def _state_hidden(
        self,
        obs: jax.Array,
        act: jax.Array,
        timesteps: jax.Array,
        mask: jax.Array,
        deterministic: bool,
        last_only: bool,
    ) -> jax.Array:
        """Transformer output at the state tokens: ``[B, T, D]`` (``[B, 1, D]`` if ``last_only``)."""
        batch, length = obs.shape[:2]
        time = self.embed_time(timesteps)
        e_s = self.embed_obs(obs) + time
        e_a = self.embed_act(act) + time
        x = jnp.stack([e_a, e_s], axis=2).reshape(batch, 2 * length, self.embd_dim)  # (a_1, s_1, ...)
        x = self.embed_drop(self.embed_ln(x), deterministic=deterministic)

        tokens = 2 * length
        key_valid = jnp.repeat(mask > 0, 2, axis=1)[:, None, :]  # [B, 1, 2T]
        causal = np.tril(np.ones((tokens, tokens), dtype=bool))
        state_index = np.arange(1, tokens, 2) if not last_only else np.array([tokens - 1])
        for i, block in enumerate(self.blocks):
            rows = state_index if i == self.n_layer - 1 else np.arange(tokens)
            x = block(
                x,
                causal[rows][None] & key_valid,
                deterministic=deterministic,
                query_index=None if rows.size == tokens else rows,
            )
        return self.final_ln(x)

    def __call__(
        self, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array, deterministic: bool = True
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Args: ``obs [B, T, o]``, ``act [B, T, a]``, ``timesteps [B, T]`` int in
        ``[0, max_timestep]``, ``mask [B, T]`` (1 = real step, 0 = padding).

        Returns: ``r_hat [B, T]``, ``w [B, T]``, ``logit [B]``, all float32.
        """
        r_hat, w, logit, _ = self.with_attention(obs, act, timesteps, mask, deterministic)
        return r_hat, w, logit

    def with_attention(
        self, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array, deterministic: bool = True
    ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """``(r_hat, w, logit)`` of :meth:`__call__` and the preference attention ``A [B, T, T]`` of the
        same pass (the online CVAE reads the training pass's, dropout on: ``spot.subgoal.online``)."""
        r_hat, attn = self.attention(obs, act, timesteps, mask, deterministic)
        valid = mask > 0
        row_weight = valid.astype(jnp.float32)
        row_weight = row_weight / jnp.maximum(row_weight.sum(axis=1, keepdims=True), 1.0)
        w = jnp.einsum("bt,btj->bj", row_weight, attn)  # column mean over real query rows
        logit = jnp.sum(w * r_hat, axis=1)  # == mean_t z_t, z_t = sum_j A_tj r_hat_j
        return r_hat, w, logit, attn

    def attention(
        self, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array, deterministic: bool = True
    ) -> tuple[jax.Array, jax.Array]:
        """``r_hat [B, T]`` and the preference attention ``A [B, T, T]`` (``A[b, t, j] = A_tj``,
        softmax over keys j, padded keys masked)."""
        x = self._state_hidden(obs, act, timesteps, mask, deterministic, last_only=False)
        head = self.pref_head(x)
        p = self.pref_attn_dim
        q, k, r_hat = head[..., :p], head[..., p : 2 * p], head[..., 2 * p]
        logits = jnp.einsum("btp,bjp->btj", q, k)  # unscaled, as in the PT repo
        attn = jax.nn.softmax(jnp.where((mask > 0)[:, None, :], logits, MASKED_LOGIT), axis=-1)
        return r_hat, attn

    def last_step_reward(self, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array) -> jax.Array:
        """``r_hat`` at the last position of each window, ``[B]`` (deterministic).

        Equals ``self(...)[0][:, -1]``; the last block only computes the last state token.
        """
        x = self._state_hidden(obs, act, timesteps, mask, deterministic=True, last_only=True)
        return self.pref_head(x)[:, 0, 2 * self.pref_attn_dim]


def make_model(cfg: PTConfig) -> PreferenceTransformer:
    if cfg.embd_dim % cfg.n_head:
        raise ValueError(f"pt.embd_dim {cfg.embd_dim} must be divisible by pt.n_head {cfg.n_head}")
    return PreferenceTransformer(
        embd_dim=cfg.embd_dim,
        n_layer=cfg.n_layer,
        n_head=cfg.n_head,
        dropout=cfg.dropout,
        pref_attn_dim=cfg.pref_attn_dim,
        max_timestep=cfg.max_timestep,
        dtype=DTYPES[cfg.dtype],
    )


@functools.lru_cache(maxsize=16)
def _init_program(cfg: PTConfig, obs_dim: int, act_dim: int) -> Callable[[jax.Array], Params]:
    """The jitted init, kept per config and sizes: a later run in the process (a reused sweep
    trial, another dataset of the env) neither traces nor compiles it again."""
    length = 2
    return jit_init(
        make_model(cfg),
        np.zeros((1, length, obs_dim), np.float32),  # numpy: no program per size
        np.zeros((1, length, act_dim), np.float32),
        np.ones((1, length), np.int32),
        np.ones((1, length), np.float32),
    )


def init_params(key: jax.Array, cfg: PTConfig, obs_dim: int, act_dim: int) -> Params:
    return _init_program(cfg, obs_dim, act_dim)(key)


def forward(
    params: Params,
    cfg: PTConfig,
    obs: jax.Array,
    act: jax.Array,
    timesteps: jax.Array,
    mask: jax.Array,
    dropout_key: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(r_hat [B, T], w [B, T], logit [B])``; dropout is on iff ``dropout_key`` is given."""
    if (
        obs.ndim != 3
        or act.shape[:2] != obs.shape[:2]
        or timesteps.shape != obs.shape[:2]
        or mask.shape != obs.shape[:2]
    ):
        raise ValueError(
            f"expected obs [B, T, o], act [B, T, a], timesteps [B, T], mask [B, T]; got "
            f"{obs.shape}, {act.shape}, {timesteps.shape}, {mask.shape}"
        )
    deterministic = dropout_key is None
    return make_model(cfg).apply(
        params,
        obs,
        act,
        timesteps,
        mask,
        deterministic=deterministic,
        rngs=None if deterministic else {"dropout": dropout_key},
    )


def attention(
    params: Params, cfg: PTConfig, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """``(r_hat [B, T], A [B, T, T])``: per-step rewards and the preference attention
    (deterministic); SPOT's subgoal weights are read from ``A`` (``spot.subgoal.extract.step_scores``)."""
    return make_model(cfg).apply(params, obs, act, timesteps, mask, method=PreferenceTransformer.attention)


def last_step_reward(
    params: Params, cfg: PTConfig, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array
) -> jax.Array:
    """``r_hat`` at the last window position, ``[B]`` (PT repo relabelling, ``label_mode='last'``)."""
    return make_model(cfg).apply(params, obs, act, timesteps, mask, method=PreferenceTransformer.last_step_reward)


def learning_rate(cfg: PTConfig, total_steps: int | None = None) -> float | optax.Schedule:
    """PT's learning rate (``pt.schedule``): ``warmup_constant`` rises linearly from 0 to ``lr``
    over the warmup, then stays (Table 5); ``warmup_cosine`` rises from ``lr`` to
    ``pt.peak_factor * lr`` over the warmup, then falls along a cosine to ``lr`` at
    ``total_steps`` (the PT repo's ``warmup_cosine_decay_schedule``). The warmup is
    ``pt.warmup_steps``, or ``pt.warmup_fraction`` of ``total_steps`` when that is > 0 (PT repo: 10 %)."""
    warmup = cfg.warmup_steps
    if cfg.warmup_fraction > 0 or cfg.schedule == "warmup_cosine":
        if total_steps is None:
            raise ValueError("pt.schedule=warmup_cosine and pt.warmup_fraction need the total number of steps")
        if cfg.warmup_fraction > 0:
            warmup = int(cfg.warmup_fraction * total_steps)
    if cfg.schedule == "warmup_cosine":
        return optax.warmup_cosine_decay_schedule(
            init_value=cfg.lr,
            peak_value=cfg.peak_factor * cfg.lr,
            warmup_steps=warmup,
            decay_steps=max(total_steps, warmup + 1),
            end_value=cfg.lr,
        )
    return cfg.lr if warmup == 0 else optax.warmup_constant_schedule(0.0, cfg.lr, warmup)


@dataclass(frozen=True)
class PT:
    """The Preference Transformer of config ``cfg`` (hashable: jitted programs are kept per model)."""

    cfg: PTConfig
    kind: str = "pt"

    def init(self, key: jax.Array, obs_dim: int, act_dim: int) -> Params:
        return init_params(key, self.cfg, obs_dim, act_dim)

    def apply(
        self,
        params: Params,
        obs: jax.Array,
        act: jax.Array,
        timesteps: jax.Array,
        mask: jax.Array,
        dropout_key: jax.Array | None = None,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``(r_hat, w, logit)`` (:func:`forward`); dropout on iff ``dropout_key`` is given."""
        return forward(params, self.cfg, obs, act, timesteps, mask, dropout_key)

    def apply_attention(
        self,
        params: Params,
        obs: jax.Array,
        act: jax.Array,
        timesteps: jax.Array,
        mask: jax.Array,
        dropout_key: jax.Array | None = None,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``(r_hat [B, T], A [B, T, T], logit [B])`` of one pass (dropout on iff ``dropout_key``):
        :meth:`apply`'s reward and logit with the preference attention of the same pass."""
        deterministic = dropout_key is None
        r_hat, _, logit, attn = make_model(self.cfg).apply(
            params,
            obs,
            act,
            timesteps,
            mask,
            deterministic,
            method=PreferenceTransformer.with_attention,
            rngs=None if deterministic else {"dropout": dropout_key},
        )
        return r_hat, attn, logit

    def optimizer(self, total_steps: int) -> optax.GradientTransformation:
        """AdamW(0.9, ``pt.b2``) with :func:`learning_rate` (Table 5: b2 0.99, linear warmup, constant)."""
        cfg = self.cfg
        return optax.adamw(learning_rate(cfg, total_steps), b1=0.9, b2=cfg.b2, weight_decay=cfg.weight_decay)

    def check_timesteps(self, lo: int, hi: int, where: str) -> None:
        """Timesteps index the learned embedding: they must lie in ``[0, max_timestep]``."""
        if lo < 0 or hi > self.cfg.max_timestep:
            raise SpotError(
                f"{where} has timesteps in [{lo}, {hi}]; pt.max_timestep is {self.cfg.max_timestep}, "
                "expected 0 <= timestep <= pt.max_timestep"
            )
