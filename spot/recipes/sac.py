"""Soft Actor-Critic (Haarnoja et al., 2018, arXiv:1812.05905), the behaviour-policy learner of the
locomotion recipes (D4RL, Fu et al., 2020, arXiv:2004.07219, made its Gym-MuJoCo data with SAC).

The parts, as in the paper's Algorithm 1 with the automatic temperature of Sec. 5:

* actor: a tanh-squashed Gaussian whose mean and (clipped) log-std depend on the state;
  ``log pi(a|s) = log N(u; mu, sigma) - sum_i log(1 - tanh(u_i)^2)`` with ``a = tanh(u)`` (App. C);
* critic: twin Q networks trained on ``r + gamma (1 - done) (min_j Q'_j(s', a') - alpha log pi(a'|s'))``
  with Polyak-averaged target params (the clipped double-Q of TD3, as the paper does);
* temperature: ``alpha`` tuned by gradient steps on ``alpha (H(pi) - H_target)`` so the policy
  entropy tracks ``H_target = -act_dim`` (Sec. 5).

This module holds the config, the networks and the updates: the replay buffer is a fixed-capacity
pytree of device arrays, and :func:`train_chunk` runs ``update_every`` gradient updates in one
jitted ``lax.scan``. The online training loop (environment, evaluations, stop rule, checkpoints) is
:func:`spot.recipes.sac_train.train_sac`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax.training.train_state import TrainState

from spot import SpotError

Params = Any


STOP_POLICIES = ("deterministic", "stochastic")
# Config fields added after SAC runs were cached: left out of a run's identity (cache name,
# checkpoint) while at these defaults, so runs cached before them keep their names.
_LATER_FIELDS = {"stop_policy": "deterministic", "stop_evals": 1}


@dataclass(frozen=True)
class SACConfig:
    """SAC hyperparameters and the length of a training run (defaults: the SAC paper, App. D)."""

    hidden_dims: tuple[int, ...] = (256, 256)
    """Hidden layer widths of the actor and of each Q network (ReLU)."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 3e-4
    """Adam learning rate of the twin critics."""
    temperature_lr: float = 3e-4
    """Adam learning rate of ``log alpha``."""
    batch_size: int = 256
    """Transitions per gradient update, drawn uniformly from the replay buffer."""
    discount: float = 0.99
    """Discount factor gamma."""
    tau: float = 0.005
    """Polyak step of the target critics: ``target <- tau * online + (1 - tau) * target``."""
    init_temperature: float = 1.0
    """Initial entropy temperature alpha."""
    target_entropy: float | None = None
    """Entropy the temperature aims for; ``None`` means ``-act_dim`` (Sec. 5)."""
    log_std_min: float = -5.0
    """Lower clip of the actor's log standard deviation."""
    log_std_max: float = 2.0
    """Upper clip of the actor's log standard deviation."""
    total_steps: int = 1_000_000
    """Environment steps of the run (one transition each), a multiple of ``eval_every``."""
    start_steps: int = 5000
    """First steps with uniform random actions and no updates, a multiple of ``update_every``."""
    update_every: int = 1000
    """Environment steps between update chunks; each chunk runs this many updates (one per step)."""
    eval_every: int = 10_000
    """Environment steps between evaluations (each one stores an actor snapshot), a multiple of
    ``update_every``."""
    eval_episodes: int = 10
    """Episodes of the deterministic (mean) policy per evaluation."""
    max_episode_steps: int = 1000
    """Time limit of an episode; reaching it is a truncation (a D4RL timeout), not a terminal."""
    target_return: float | None = None
    """Stop once ``stop_evals`` evaluations in a row have a mean return (of ``stop_policy``) that
    reaches this (D4RL's expert level); ``total_steps`` is then a cap. ``None`` runs all ``total_steps``."""
    stop_policy: str = "deterministic"
    """Whose return the stop rule reads: ``"deterministic"`` (the mean action, the evaluation every
    run makes) or ``"stochastic"`` (sampled actions, as the datasets are rolled out: each evaluation
    then also runs ``eval_episodes`` stochastic episodes)."""
    stop_evals: int = 1
    """Evaluations in a row whose return must reach ``target_return`` (1: the first one stops)."""

    def __post_init__(self) -> None:
        for name in ("total_steps", "update_every", "eval_every", "eval_episodes", "batch_size", "stop_evals"):
            if getattr(self, name) <= 0:
                raise SpotError(f"SACConfig.{name} = {getattr(self, name)}; expected a positive integer")
        if self.stop_policy not in STOP_POLICIES:
            raise SpotError(f"SACConfig.stop_policy = {self.stop_policy!r}; expected one of {', '.join(STOP_POLICIES)}")
        if self.target_return is None and (self.stop_policy, self.stop_evals) != ("deterministic", 1):
            raise SpotError(
                f"SACConfig: stop_policy = {self.stop_policy!r} and stop_evals = {self.stop_evals} shape a stop "
                "rule, but target_return is None (no rule: the run is total_steps long)"
            )
        if self.start_steps < 0 or self.start_steps % self.update_every:
            raise SpotError(
                f"SACConfig.start_steps = {self.start_steps}; expected a non-negative multiple of "
                f"update_every ({self.update_every})"
            )
        if self.eval_every % self.update_every or self.total_steps % self.eval_every:
            raise SpotError(
                f"SACConfig: eval_every ({self.eval_every}) must be a multiple of update_every "
                f"({self.update_every}) and total_steps ({self.total_steps}) a multiple of eval_every"
            )
        if self.start_steps >= self.total_steps:
            raise SpotError(
                f"SACConfig.start_steps = {self.start_steps} leaves no updates in total_steps = {self.total_steps}"
            )


def identity(cfg: SACConfig) -> dict[str, Any]:
    """The config as a run's identity: its fields, less those of :data:`_LATER_FIELDS` at their defaults."""
    return {k: v for k, v in dataclasses.asdict(cfg).items() if not (k in _LATER_FIELDS and v == _LATER_FIELDS[k])}


# --------------------------------------------------------------------------------------- networks
class MLP(nn.Module):
    """ReLU multilayer perceptron with a linear output layer."""

    hidden_dims: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden_dims:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.out_dim)(x)


class Actor(nn.Module):
    """State-dependent Gaussian over the pre-tanh action: returns ``(mean, log_std)``, ``[..., act_dim]``."""

    hidden_dims: Sequence[int]
    act_dim: int
    log_std_min: float
    log_std_max: float

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = obs
        for width in self.hidden_dims:
            x = nn.relu(nn.Dense(width)(x))
        mean = nn.Dense(self.act_dim, name="mean")(x)
        log_std = nn.Dense(self.act_dim, name="log_std")(x)
        return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class QNetwork(nn.Module):
    hidden_dims: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        return MLP(self.hidden_dims, 1)(jnp.concatenate([obs, action], axis=-1))[..., 0]


class TwinCritic(nn.Module):
    """Two independent Q networks (``nn.vmap`` over params); output shape ``[2, B]``."""

    hidden_dims: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        ensemble = nn.vmap(
            QNetwork,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=2,
        )
        return ensemble(self.hidden_dims)(obs, action)


def _actor_def(cfg: SACConfig, act_dim: int) -> Actor:
    return Actor(cfg.hidden_dims, act_dim, cfg.log_std_min, cfg.log_std_max)


# ------------------------------------------------------------------------------ tanh-Gaussian
def tanh_gaussian_log_prob(pre_tanh: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """Log density of ``a = tanh(u)``, ``u ~ N(mean, exp(log_std)^2)`` per dimension, summed over the
    last axis (SAC App. C).

    Uses ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))``, which stays finite for large ``|u|``.
    """
    z = (pre_tanh - mean) * jnp.exp(-log_std)
    gaussian = -0.5 * z**2 - log_std - 0.5 * math.log(2.0 * math.pi)
    log_det = 2.0 * (math.log(2.0) - pre_tanh - jax.nn.softplus(-2.0 * pre_tanh))
    return jnp.sum(gaussian - log_det, axis=-1)


def sample_tanh_gaussian(key: jax.Array, mean: jax.Array, log_std: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Reparameterised sample ``a = tanh(mean + std * eps)`` and its log-probability."""
    pre_tanh = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
    return jnp.tanh(pre_tanh), tanh_gaussian_log_prob(pre_tanh, mean, log_std)


# ---------------------------------------------------------------------------------- state, data
class SACState(NamedTuple):
    """Learner state. ``temperature.params`` is ``{"log_alpha": []}``; targets have no optimizer."""

    actor: TrainState
    critic: TrainState
    target_critic_params: Params
    temperature: TrainState
    step: jax.Array


class Replay(NamedTuple):
    """Fixed-capacity replay buffer on device; rows ``[0, size)`` are filled (size kept by the caller).

    Shapes: ``observations``/``next_observations`` ``[C, obs_dim]``, ``actions`` ``[C, act_dim]``,
    ``rewards`` and ``terminals`` (1.0 where the environment terminated, not on timeouts) ``[C]``.
    """

    observations: jax.Array
    actions: jax.Array
    rewards: jax.Array
    next_observations: jax.Array
    terminals: jax.Array


@partial(jax.jit, static_argnums=(1, 2, 3))
def init_state(key: jax.Array, obs_dim: int, act_dim: int, cfg: SACConfig) -> SACState:
    """Fresh networks, Adam optimizers and target params equal to the online critic's.

    Jitted: eager flax init compiles every op on its own, which takes seconds on CPU.
    """
    actor_key, critic_key = jax.random.split(key)
    obs = jnp.zeros((1, obs_dim), jnp.float32)
    action = jnp.zeros((1, act_dim), jnp.float32)
    actor_def = _actor_def(cfg, act_dim)
    critic_def = TwinCritic(cfg.hidden_dims)
    actor = TrainState.create(
        apply_fn=actor_def.apply, params=actor_def.init(actor_key, obs), tx=optax.adam(cfg.actor_lr)
    )
    critic_params = critic_def.init(critic_key, obs, action)
    critic = TrainState.create(apply_fn=critic_def.apply, params=critic_params, tx=optax.adam(cfg.critic_lr))
    temperature = TrainState.create(
        apply_fn=None,
        params={"log_alpha": jnp.asarray(math.log(cfg.init_temperature), jnp.float32)},
        tx=optax.adam(cfg.temperature_lr),
    )
    target_critic_params = jax.tree.map(jnp.copy, critic_params)
    return SACState(actor, critic, target_critic_params, temperature, jnp.zeros((), jnp.int32))


@partial(jax.jit, donate_argnums=0)
def insert(replay: Replay, rows: Replay, start: jax.Array) -> Replay:
    """Write ``rows`` (a ``Replay`` of ``K`` rows) into ``replay`` at ``[start, start + K)``."""
    return jax.tree.map(lambda buf, new: jax.lax.dynamic_update_slice_in_dim(buf, new, start, axis=0), replay, rows)


# ---------------------------------------------------------------------------------------- update
def update(state: SACState, batch: Replay, key: jax.Array, cfg: SACConfig) -> tuple[SACState, dict]:
    """One SAC step: critic, then actor and temperature, then the Polyak target update.

    Args:
      state: current learner state.
      batch: a ``Replay`` of ``[B, ...]`` transitions.
      key: randomness for the next-state and current-state action samples.
      cfg: hyperparameters (static).
    Returns:
      The new state and a flat dict of scalar ``sac/...`` metrics.
    """
    assert batch.observations.ndim == 2 and batch.rewards.shape == (batch.observations.shape[0],)
    next_key, actor_key = jax.random.split(key)
    act_dim = batch.actions.shape[-1]
    target_entropy = -float(act_dim) if cfg.target_entropy is None else cfg.target_entropy
    alpha = jnp.exp(state.temperature.params["log_alpha"])

    mean, log_std = state.actor.apply_fn(state.actor.params, batch.next_observations)
    next_action, next_log_prob = sample_tanh_gaussian(next_key, mean, log_std)
    next_q = state.critic.apply_fn(state.target_critic_params, batch.next_observations, next_action)
    soft_next_v = next_q.min(axis=0) - alpha * next_log_prob  # [B]
    target_q = batch.rewards + cfg.discount * (1.0 - batch.terminals) * soft_next_v

    def critic_loss_fn(params):
        q = state.critic.apply_fn(params, batch.observations, batch.actions)  # [2, B]
        loss = ((q - target_q[None]) ** 2).mean(axis=1).sum()
        return loss, {"sac/critic_loss": loss, "sac/q": q.mean()}

    critic_grads, critic_info = jax.grad(critic_loss_fn, has_aux=True)(state.critic.params)
    critic = state.critic.apply_gradients(grads=critic_grads)

    def actor_loss_fn(params):
        mean, log_std = state.actor.apply_fn(params, batch.observations)
        action, log_prob = sample_tanh_gaussian(actor_key, mean, log_std)
        q = critic.apply_fn(critic.params, batch.observations, action).min(axis=0)
        loss = (alpha * log_prob - q).mean()
        return loss, {"sac/actor_loss": loss, "sac/entropy": -log_prob.mean()}

    actor_grads, actor_info = jax.grad(actor_loss_fn, has_aux=True)(state.actor.params)
    actor = state.actor.apply_gradients(grads=actor_grads)

    entropy = jax.lax.stop_gradient(actor_info["sac/entropy"])

    def temperature_loss_fn(params):
        return jnp.exp(params["log_alpha"]) * (entropy - target_entropy)

    temperature_grads = jax.grad(temperature_loss_fn)(state.temperature.params)
    temperature = state.temperature.apply_gradients(grads=temperature_grads)

    target = optax.incremental_update(critic.params, state.target_critic_params, cfg.tau)
    metrics = {**critic_info, **actor_info, "sac/alpha": alpha}
    return SACState(actor, critic, target, temperature, state.step + 1), metrics


@partial(jax.jit, static_argnames=("cfg", "num_updates"), donate_argnums=0)
def train_chunk(
    state: SACState, replay: Replay, size: jax.Array, key: jax.Array, cfg: SACConfig, num_updates: int
) -> tuple[SACState, dict]:
    """``num_updates`` updates in one ``lax.scan``, each on a batch drawn from rows ``[0, size)``.

    Returns the new state and the metrics averaged over the chunk.
    """

    def body(state, i):
        batch_key, update_key = jax.random.split(jax.random.fold_in(key, i))
        idx = jax.random.randint(batch_key, (cfg.batch_size,), 0, size)
        batch = jax.tree.map(lambda x: x[idx], replay)
        return update(state, batch, update_key, cfg)

    state, metrics = jax.lax.scan(body, state, jnp.arange(num_updates))
    return state, jax.tree.map(jnp.mean, metrics)


@partial(jax.jit, static_argnames=("deterministic", "cfg"))
def act(params: Params, obs: jax.Array, key: jax.Array, deterministic: bool, cfg: SACConfig) -> jax.Array:
    """Action of the actor ``params`` at ``obs`` (``[obs_dim]`` or ``[B, obs_dim]``).

    ``deterministic`` takes ``tanh(mean)`` (evaluation); otherwise a sample (rollouts, as D4RL).
    ``key`` is ignored when deterministic. The action size is read from the params' shapes.
    """
    actor_def = _actor_def(cfg, params["params"]["mean"]["kernel"].shape[-1])
    mean, log_std = actor_def.apply(params, jnp.asarray(obs, jnp.float32))
    if deterministic:
        return jnp.tanh(mean)
    return sample_tanh_gaussian(key, mean, log_std)[0]
