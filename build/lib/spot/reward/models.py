"""The reward-model interface that MR (:mod:`spot.reward.mr`) and PT (:mod:`spot.reward.pt`) share,
and the one place that picks a model from the config.

Training (:mod:`spot.reward.train`) and relabelling (:mod:`spot.reward.relabel`) take a model
object, not a kind string with per-kind config options. Models are frozen dataclasses over their
config, so jitted programs can be kept per model.
"""

from __future__ import annotations

from typing import Protocol

import jax
import optax

from spot import SpotError
from spot.config import ExperimentConfig
from spot.nets import Params
from spot.reward.mr import MR
from spot.reward.pt import PT

MODELS = {"mr": MR, "pt": PT}


class RewardModel(Protocol):
    """A preference reward model ``(s_t, a_t, t) -> r_hat_t`` with per-step importance weights."""

    kind: str

    def init(self, key: jax.Array, obs_dim: int, act_dim: int) -> Params:
        """Fresh parameters."""

    def apply(
        self,
        params: Params,
        obs: jax.Array,
        act: jax.Array,
        timesteps: jax.Array,
        mask: jax.Array,
        dropout_key: jax.Array | None = None,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``obs [B, T, o]``, ``act [B, T, a]``, ``timesteps [B, T]``, ``mask [B, T]`` ->
        ``(r_hat [B, T], w [B, T], logit [B])``; dropout on iff ``dropout_key`` is given."""

    def optimizer(self, total_steps: int) -> optax.GradientTransformation:
        """The optimiser of a run of ``total_steps`` steps (schedules may depend on its length)."""

    def check_timesteps(self, lo: int, hi: int, where: str) -> None:
        """Raise :class:`spot.SpotError` if timesteps in ``[lo, hi]`` do not fit the model."""


def from_config(cfg: ExperimentConfig) -> RewardModel:
    """The reward model of ``cfg.reward.kind`` (``mr`` or ``pt``) with its config section."""
    kind = cfg.reward.kind
    if kind not in MODELS:
        raise SpotError(f"reward.kind={kind!r} has no reward model; expected one of {', '.join(MODELS)}")
    return MODELS[kind](getattr(cfg, kind))
