"""Markovian reward model (MR): ``r_phi(s, a) = MLP([s; a])``, the PT paper's MR baseline.

Architecture as in the PT repo [csmile-1006/PreferenceTransformer : JaxPref/MR.py, JaxPref/model.py]
(reference/algorithms.md §1.5): hidden sizes ``MRConfig.hidden`` (256-256), ReLU, flax default
Dense init, output layer ``variance_scaling(1e-2, fan_in, uniform)``, no output activation.

The segment logit is the **mean** over the (unpadded) steps, ``l(sigma) = (1/T) sum_t r_phi(s_t, a_t)``
(PT repo ``train_type="mean"``), not the sum of eq. (1) of the paper; under the softmax of eq. (1)-(2)
this only rescales the reward by 1/T. The per-step "importance" of MR is uniform, ``w_t = 1/T``, so MR
exposes the same ``forward -> (r_hat, w, logit)`` interface as :mod:`spot.reward.pt`.

:class:`MR` is this model behind the reward-model interface (:class:`spot.reward.models.RewardModel`):
``init``, ``apply`` and ``optimizer`` (Adam at ``MRConfig.lr``, constant).
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

from spot.config import MRConfig
from spot.nets import MLP, Params, jit_init

OUTPUT_INIT = nn.initializers.variance_scaling(1e-2, "fan_in", "uniform")


def make_model(cfg: MRConfig) -> MLP:
    """The reward MLP on ``[s; a]`` with one output."""
    return MLP(hidden=tuple(cfg.hidden), out_dim=1, activation=nn.relu, output_kernel_init=OUTPUT_INIT)


@functools.lru_cache(maxsize=16)
def _init_program(cfg: MRConfig, obs_dim: int, act_dim: int) -> Callable[[jax.Array], Params]:
    """The jitted init, kept per config and sizes (compiled once per process, as PT's)."""
    return jit_init(make_model(cfg), np.zeros((1, obs_dim + act_dim), np.float32))  # no program per size


def init_params(key: jax.Array, cfg: MRConfig, obs_dim: int, act_dim: int) -> Params:
    return _init_program(cfg, obs_dim, act_dim)(key)


def per_step_reward(params: Params, obs: jax.Array, act: jax.Array, cfg: MRConfig) -> jax.Array:
    """``r_phi(s, a)`` for any leading shape: ``obs [..., o]``, ``act [..., a]`` -> ``[...]``."""
    if obs.shape[:-1] != act.shape[:-1]:
        raise ValueError(f"obs {obs.shape} and act {act.shape} have different leading shapes")
    x = jnp.concatenate([obs, act], axis=-1).astype(jnp.float32)
    return make_model(cfg).apply(params, x)[..., 0]


def forward(
    params: Params, cfg: MRConfig, obs: jax.Array, act: jax.Array, mask: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per-step reward, uniform weights and the segment logit.

    Args:
      obs: ``[B, T, o]``; act: ``[B, T, a]``; mask: ``[B, T]``, 1 for real steps, 0 for padding.

    Returns:
      ``r_hat [B, T]``, ``w [B, T]`` (``mask / sum(mask)``) and ``logit [B] = sum_t w_t r_hat_t``.
    """
    if obs.ndim != 3 or mask.shape != obs.shape[:2]:
        raise ValueError(f"expected obs [B, T, o] and mask [B, T], got {obs.shape} and {mask.shape}")
    r_hat = per_step_reward(params, obs, act, cfg)
    valid = mask.astype(jnp.float32)
    w = valid / jnp.maximum(valid.sum(axis=1, keepdims=True), 1.0)
    return r_hat, w, jnp.sum(w * r_hat, axis=1)


@dataclass(frozen=True)
class MR:
    """The MR reward model of config ``cfg`` (hashable: jitted programs are kept per model)."""

    cfg: MRConfig
    kind: str = "mr"

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
        """``(r_hat, w, logit)`` (:func:`forward`); MR ignores timesteps and has no dropout."""
        del timesteps, dropout_key
        return forward(params, self.cfg, obs, act, mask)

    def optimizer(self, total_steps: int) -> optax.GradientTransformation:
        """Adam, constant learning rate ``cfg.lr``."""
        del total_steps
        return optax.adam(self.cfg.lr)

    def check_timesteps(self, lo: int, hi: int, where: str) -> None:
        """MR reads no timesteps: any range is fine."""
