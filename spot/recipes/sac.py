"""Soft Actor-Critic (Haarnoja et al., 2018, arXiv:1812.05905), the behaviour-policy learner of the
locomotion recipes (D4RL, Fu et al., 2020, arXiv:2004.07219, made its Gym-MuJoCo data with SAC).

The parts, as in the paper's Algorithm 1 with the automatic temperature of Sec. 5:

* actor: a tanh-squashed Gaussian whose mean and (clipped) log-std depend on the state;
  ``log pi(a|s) = log N(u; mu, sigma) - sum_i log(1 - tanh(u_i)^2)`` with ``a = tanh(u)`` (App. C);
* critic: twin Q networks trained on ``r + gamma (1 - done) (min_j Q'_j(s', a') - alpha log pi(a'|s'))``
  with Polyak-averaged target params (the clipped double-Q of TD3, as the paper does);
* temperature: ``alpha`` tuned by gradient steps on ``alpha (H(pi) - H_target)`` so the policy
  entropy tracks ``H_target = -act_dim`` (Sec. 5).

The environment loop is Python and numpy (gymnasium); the replay buffer is a fixed-capacity pytree
of device arrays; every ``update_every`` environment steps one jitted ``lax.scan`` runs
``update_every`` gradient updates, so Python costs little. Actions must lie in ``[-1, 1]``, as in
Hopper and Walker2d.

A run stops after ``total_steps`` or, with ``target_return`` set, once ``stop_evals`` evaluations
in a row have a mean return that reaches it (``total_steps`` is then a cap); ``stop_policy`` says
whose return: the deterministic (mean-action) policy's or the stochastic one's, which the datasets
are rolled out with. A run can write checkpoints
(learner and optimiser states, the replay buffer so far, the snapshots, the random generators and
the training env's simulator state); :func:`train_sac` resumes from one and continues bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
import math
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import gymnasium as gym
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax
from flax import serialization
from flax.training.train_state import TrainState
from tqdm.auto import tqdm

from spot import SpotError, store

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


@partial(jax.jit, static_argnames=("deterministic", "cfg"))
def _act_at(
    params: Params, obs: jax.Array, key: jax.Array, step: int, deterministic: bool, cfg: SACConfig
) -> jax.Array:
    # act with key fold_in(key, step) folded inside jit: an eager fold_in costs ~0.4 ms on CPU.
    return act(params, obs, jax.random.fold_in(key, step), deterministic, cfg)


# ----------------------------------------------------------------------------- environment loop
def make_env(env_id: str, cfg: SACConfig, **make_kwargs: Any) -> gym.Env:
    """``gym.make`` with the config's time limit (and ``make_kwargs``, e.g. ``xml_file``); raises
    unless actions lie in ``[-1, 1]``."""
    env = gym.make(env_id, max_episode_steps=cfg.max_episode_steps, **make_kwargs)
    space = env.action_space
    if not (np.all(space.low == -1.0) and np.all(space.high == 1.0)):
        env.close()
        raise SpotError(f"{env_id}: SAC here needs actions in [-1, 1], got [{space.low}, {space.high}]")
    return env


def run_episode(
    env: gym.Env, params: Params, key: jax.Array, deterministic: bool, cfg: SACConfig, seed: int | None = None
) -> dict[str, np.ndarray]:
    """One episode of the actor ``params`` in ``env`` (reset with ``seed`` if given).

    Returns the D4RL-style rows: ``observations``, ``actions``, ``rewards``, ``next_observations``,
    ``terminals`` (``[-1]`` set if the environment terminated) and ``timeouts`` (``[-1]`` set if
    the time limit cut it instead). Step ``t`` samples with ``fold_in(key, t)``.
    """
    obs, _ = env.reset(seed=seed)
    rows: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations")}
    for t in range(cfg.max_episode_steps + 1):
        action = np.asarray(_act_at(params, obs, key, t, deterministic, cfg))
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for k, v in zip(rows, (obs, action, reward, next_obs), strict=True):
            rows[k].append(v)
        obs = next_obs
        if terminated or truncated:
            break
    n = len(rows["rewards"])
    ep = {k: np.asarray(v, np.float32) for k, v in rows.items()}
    ep["terminals"] = np.zeros(n, bool)
    ep["timeouts"] = np.zeros(n, bool)
    ep["terminals"][-1] = terminated
    ep["timeouts"][-1] = not terminated  # an episode that both terminates and times out is a terminal
    return ep


def evaluate(
    env: gym.Env, params: Params, episodes: int, seed: int, cfg: SACConfig, key: jax.Array | None = None
) -> np.ndarray:
    """Returns of ``episodes`` episodes; the first reset uses ``seed``. Deterministic (mean
    actions) without ``key``; with it, sampled actions, episode ``i`` with ``fold_in(key, i)``."""
    deterministic = key is None
    key = jax.random.key(0) if key is None else key  # unused when deterministic
    return np.array(
        [
            run_episode(env, params, jax.random.fold_in(key, i), deterministic, cfg, seed=seed if i == 0 else None)[
                "rewards"
            ].sum()
            for i in range(episodes)
        ]
    )


@dataclass(frozen=True)
class Snapshot:
    """The actor at one evaluation: host (numpy) params, its deterministic eval returns and, where
    the stop rule reads the stochastic policy, that policy's (else None)."""

    step: int
    eval_return: float
    eval_return_std: float
    actor_params: Params
    stochastic_return: float | None = None
    stochastic_return_std: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """msgpack-able fields (the stochastic returns only where measured)."""
        out = {"step": self.step, "eval_return": self.eval_return, "eval_return_std": self.eval_return_std}
        if self.stochastic_return is not None:
            out |= {"stochastic_return": self.stochastic_return, "stochastic_return_std": self.stochastic_return_std}
        return {**out, "actor_params": self.actor_params}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Snapshot:
        stoch = d.get("stochastic_return")
        return cls(
            int(d["step"]),
            float(d["eval_return"]),
            float(d["eval_return_std"]),
            d["actor_params"],
            None if stoch is None else float(stoch),
            None if stoch is None else float(d["stochastic_return_std"]),
        )


def stop_reached(snapshots: Sequence[Snapshot], cfg: SACConfig) -> bool:
    """Whether the last ``cfg.stop_evals`` evaluations all reach ``cfg.target_return`` with the
    return of ``cfg.stop_policy`` (False without a target)."""
    if cfg.target_return is None or len(snapshots) < cfg.stop_evals:
        return False
    last = snapshots[len(snapshots) - cfg.stop_evals :]
    values = [stop_value(s, cfg) for s in last]
    return all(v is not None and v >= cfg.target_return for v in values)


def stop_value(snapshot: Snapshot, cfg: SACConfig) -> float | None:
    """The return of ``snapshot`` that ``cfg``'s stop rule reads (None: not measured)."""
    return snapshot.stochastic_return if cfg.stop_policy == "stochastic" else snapshot.eval_return


@dataclass(frozen=True)
class SACResult:
    """What :func:`train_sac` returns.

    Attributes:
      snapshots: one per evaluation, in step order; the last is the final policy.
      replay: the replay buffer in collection order (numpy; as many rows as steps were run: fewer
        than ``total_steps`` when ``target_return`` stopped the run): the D4RL raw keys
        ``observations``, ``actions``, ``rewards``, ``next_observations``, ``terminals``,
        ``timeouts``. Row ``t`` is environment step ``t``.
      timing: seconds, summed over every session of the run: ``total``, ``env`` (stepping and
        acting), ``update`` (chunks, incl. compilation), ``eval``, ``checkpoint``; and
        ``peak_rss_mb``, the largest peak resident memory of the sessions' processes.
      resumed_from: the steps at which the run was resumed from a checkpoint, in order.
    """

    env_id: str
    seed: int
    config: SACConfig
    snapshots: list[Snapshot]
    replay: dict[str, np.ndarray]
    timing: dict[str, float]
    resumed_from: tuple[int, ...] = ()

    @property
    def target_reached(self) -> bool | None:
        """Whether the run ended by its stop rule (:func:`stop_reached`; ``None`` without a target)."""
        if self.config.target_return is None:
            return None
        return stop_reached(self.snapshots, self.config)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (``getrusage``; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


_REPLAY_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
CHECKPOINT_FORMAT = 1
_MJ_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, act, warm start, time, controls...


class _Run:
    """The mutable state of one SAC training run: exactly what a checkpoint holds.

    Everything random is either stateless (jax keys folded with the step) or saved (the numpy
    generator of the random start actions, the training env's MuJoCo integration state, time-limit
    counter and reset generator), so a run resumed from a checkpoint continues bit for bit.
    """

    def __init__(self, env_id: str, cfg: SACConfig, seed: int, make_kwargs: dict[str, Any]):
        self.env_id, self.cfg, self.seed = env_id, cfg, seed
        self.env, self.eval_env = make_env(env_id, cfg, **make_kwargs), make_env(env_id, cfg, **make_kwargs)
        self.obs_dim = self.env.observation_space.shape[0]
        self.act_dim = self.env.action_space.shape[0]
        init_key, self.train_key, self.act_key = jax.random.split(jax.random.key(seed), 3)
        self.state = init_state(init_key, self.obs_dim, self.act_dim, cfg)
        n, dims = (
            cfg.total_steps,
            {"observations": self.obs_dim, "next_observations": self.obs_dim, "actions": self.act_dim},
        )
        self.host = {
            k: np.zeros((n, dims[k]) if k in dims else n, bool if k in ("terminals", "timeouts") else np.float32)
            for k in _REPLAY_KEYS
        }
        self.random_actions = np.random.default_rng(seed)
        self.eval_seed = int(np.random.SeedSequence([seed, 1]).generate_state(1)[0])
        # the stochastic evaluations (stop_policy stochastic): their own env seed and action keys
        self.stochastic_seed = int(np.random.SeedSequence([seed, 4]).generate_state(1)[0])
        self.stochastic_key = jax.random.fold_in(jax.random.key(seed), 4)
        self.snapshots: list[Snapshot] = []
        self.timing = {"total": 0.0, "env": 0.0, "update": 0.0, "eval": 0.0, "checkpoint": 0.0, "peak_rss_mb": 0.0}
        self.resumed_from: list[int] = []
        self.chunk_metrics: dict[str, Any] = {}
        self.t = 0
        self.obs, _ = self.env.reset(seed=seed)
        self.session_start, self.total_before = time.perf_counter(), 0.0
        self.replay: Replay | None = None

    # ---------------------------------------------------------------------------- one chunk
    def collect(self) -> None:
        """``update_every`` environment steps into the host buffer."""
        cfg, tic = self.cfg, time.perf_counter()
        for t in range(self.t, self.t + cfg.update_every):
            if t < cfg.start_steps:
                action = self.random_actions.uniform(-1.0, 1.0, self.act_dim).astype(np.float32)
            else:
                action = np.asarray(_act_at(self.state.actor.params, self.obs, self.act_key, t, False, cfg))
            next_obs, reward, terminated, truncated, _ = self.env.step(action)
            for k, v in zip(
                _REPLAY_KEYS,
                (self.obs, action, reward, next_obs, terminated, truncated and not terminated),
                strict=True,
            ):
                self.host[k][t] = v
            self.obs = self.env.reset()[0] if terminated or truncated else next_obs
        self.timing["env"] += time.perf_counter() - tic

    def learn(self) -> None:
        """Copy the chunk's rows to the device buffer; one update chunk once past ``start_steps``."""
        cfg, tic = self.cfg, time.perf_counter()
        start, end = self.t, self.t + cfg.update_every
        if self.replay is None:  # the whole buffer, once per session (zeros past row `start`)
            self.replay = Replay(*(jnp.asarray(self.host[k], jnp.float32) for k in Replay._fields))
        else:
            rows = Replay(*(jnp.asarray(self.host[k][start:end], jnp.float32) for k in Replay._fields))
            self.replay = insert(self.replay, rows, start)
        if end > cfg.start_steps:
            self.state, self.chunk_metrics = train_chunk(
                self.state, self.replay, jnp.int32(end), jax.random.fold_in(self.train_key, end), cfg, cfg.update_every
            )
            jax.block_until_ready(self.state)
        self.t = end
        self.timing["update"] += time.perf_counter() - tic

    def evaluate(self) -> dict[str, float]:
        """Snapshot the actor, evaluate it deterministically (and with sampled actions where the stop
        rule reads those); the metrics for ``on_eval``."""
        tic = time.perf_counter()
        metrics = {}
        if self.t > self.cfg.start_steps:
            metrics = {k: float(v) for k, v in jax.device_get(self.chunk_metrics).items()}
            if not all(math.isfinite(v) for v in metrics.values()):
                raise FloatingPointError(
                    f"SAC {self.env_id} seed {self.seed}: non-finite metrics at step {self.t}: {metrics}"
                )
        params = jax.tree.map(lambda x: np.array(x, copy=True), self.state.actor.params)
        returns = evaluate(self.eval_env, params, self.cfg.eval_episodes, self.eval_seed, self.cfg)
        metrics |= {"eval/return_mean": float(returns.mean()), "eval/return_std": float(returns.std())}
        stoch = (None, None)
        if self.cfg.stop_policy == "stochastic":
            key = jax.random.fold_in(self.stochastic_key, self.t)
            sampled = evaluate(self.eval_env, params, self.cfg.eval_episodes, self.stochastic_seed, self.cfg, key)
            stoch = (float(sampled.mean()), float(sampled.std()))
            metrics |= {"eval/stochastic_return_mean": stoch[0], "eval/stochastic_return_std": stoch[1]}
        self.snapshots.append(Snapshot(self.t, float(returns.mean()), float(returns.std()), params, *stoch))
        self.timing["eval"] += time.perf_counter() - tic
        return metrics

    # ---------------------------------------------------------------------------- checkpoints
    def payload(self) -> dict[str, Any]:
        """Everything needed to continue the run (msgpack-able; big ints travel as JSON text)."""
        u = self.env.unwrapped
        mj_state = np.empty(mujoco.mj_stateSize(u.model, _MJ_STATE))
        mujoco.mj_getState(u.model, u.data, mj_state, _MJ_STATE)
        return {
            "format": CHECKPOINT_FORMAT,
            "run": json.dumps({"env_id": self.env_id, "seed": self.seed, "config": identity(self.cfg)}, sort_keys=True),
            "t": self.t,
            "learner": serialization.to_state_dict(self.state),
            "host": {k: v[: self.t] for k, v in self.host.items()},
            "snapshots": {str(i): s.to_dict() for i, s in enumerate(self.snapshots)},
            "timing": {
                **self.timing,
                "total": self.elapsed(),
                "peak_rss_mb": max(self.timing["peak_rss_mb"], peak_rss_mb()),
            },
            "resumed_from": np.asarray(self.resumed_from, np.int64),
            "random_actions": json.dumps(self.random_actions.bit_generator.state),
            "env": {
                "obs": self.obs,
                "mj_state": mj_state,
                "elapsed_steps": self.env._elapsed_steps,
                "np_random": json.dumps(u.np_random.bit_generator.state),
            },
        }

    def restore(self, payload: dict[str, Any], path: Path) -> None:
        """Continue from :meth:`payload`'s output; raises :class:`SpotError` if it is another run's."""
        mine = json.dumps({"env_id": self.env_id, "seed": self.seed, "config": identity(self.cfg)}, sort_keys=True)
        if payload.get("format") != CHECKPOINT_FORMAT or payload.get("run") != mine:
            raise SpotError(
                f"SAC checkpoint {path} belongs to another run or format (it holds "
                f"{payload.get('run')}, format {payload.get('format')}; expected {mine}, "
                f"format {CHECKPOINT_FORMAT}); delete it to start over"
            )
        self.t = int(payload["t"])
        self.state = serialization.from_state_dict(self.state, payload["learner"])
        for k in _REPLAY_KEYS:
            self.host[k][: self.t] = payload["host"][k]
        snaps = [payload["snapshots"][str(i)] for i in range(len(payload["snapshots"]))]
        self.snapshots = [Snapshot.from_dict(s) for s in snaps]
        self.timing.update({k: float(v) for k, v in payload["timing"].items()})
        self.total_before = self.timing["total"]
        self.resumed_from = [int(x) for x in payload["resumed_from"]] + [self.t]
        self.random_actions.bit_generator.state = json.loads(payload["random_actions"])
        env, u = payload["env"], self.env.unwrapped
        mujoco.mj_setState(u.model, u.data, np.array(env["mj_state"], np.float64), _MJ_STATE)
        self.env._elapsed_steps = int(env["elapsed_steps"])
        u.np_random.bit_generator.state = json.loads(env["np_random"])
        self.obs = np.asarray(env["obs"])

    def save(self, path: Path) -> None:
        """Write :meth:`payload` to ``path`` atomically (temporary file, fsync, rename)."""
        tic = time.perf_counter()
        store.write_atomic(path, serialization.msgpack_serialize(self.payload()), fsync=True)  # full disk: SpotError
        self.timing["checkpoint"] += time.perf_counter() - tic

    def elapsed(self) -> float:
        """Seconds of this run so far, over all its sessions."""
        return self.total_before + time.perf_counter() - self.session_start

    def close(self) -> None:
        self.env.close()
        self.eval_env.close()


def train_sac(
    env_id: str,
    cfg: SACConfig,
    seed: int,
    on_eval: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = True,
    checkpoint: Path | None = None,
    checkpoint_every: int = 0,
    make_kwargs: dict[str, Any] | None = None,
) -> SACResult:
    """Train SAC in ``env_id`` for ``cfg.total_steps`` environment steps, or until its stop rule
    (:func:`stop_reached`: ``cfg.stop_evals`` evaluations in a row reach ``cfg.target_return``).

    Args:
      env_id: a gymnasium id with actions in ``[-1, 1]`` (``Hopper-v5``, ``Walker2d-v5``).
      cfg: hyperparameters, run length (a cap when ``target_return`` is set) and stop rule.
      seed: seeds the networks, the action noise, the random start actions and both environments;
        the same seed gives the same run on the same machine.
      on_eval: called after each evaluation with ``(step, metrics)``; metrics holds
        ``eval/return_mean``, ``eval/return_std``, under a stochastic stop rule
        ``eval/stochastic_return_mean`` and ``_std``, and the chunk's ``sac/...`` means.
      progress: show a tqdm bar over environment steps.
      checkpoint: a file to resume from if it exists, and to save to every ``checkpoint_every``
        steps (after that step's evaluation; a multiple of ``cfg.eval_every``; 0: never). A run
        resumed from it gives the same result as one that was never stopped. The caller deletes
        it once the result is stored.
      make_kwargs: extra ``gym.make`` arguments of both environments (e.g. ``xml_file``).
    Returns:
      A :class:`SACResult` with the snapshots, the replay buffer and timings.
    """
    if checkpoint_every < 0 or checkpoint_every % cfg.eval_every:
        raise SpotError(
            f"train_sac: checkpoint_every = {checkpoint_every}; expected 0 or a multiple "
            f"of eval_every ({cfg.eval_every})"
        )
    run = _Run(env_id, cfg, seed, dict(make_kwargs or {}))
    if checkpoint is not None and Path(checkpoint).exists():
        run.restore(serialization.msgpack_restore(Path(checkpoint).read_bytes()), Path(checkpoint))
    bar = tqdm(total=cfg.total_steps, initial=run.t, desc=f"SAC {env_id}", unit="step", disable=not progress)
    while run.t < cfg.total_steps:
        run.collect()
        run.learn()
        bar.update(cfg.update_every)
        if run.t % cfg.eval_every:
            continue
        metrics = run.evaluate()
        if on_eval is not None:
            on_eval(run.t, metrics)
        bar.set_postfix(eval_return=f"{metrics['eval/return_mean']:.0f}")
        if stop_reached(run.snapshots, cfg):
            break
        if checkpoint is not None and checkpoint_every and run.t % checkpoint_every == 0 and run.t < cfg.total_steps:
            run.save(Path(checkpoint))
    bar.close()
    run.close()
    run.timing["total"] = run.elapsed()
    run.timing["peak_rss_mb"] = max(run.timing["peak_rss_mb"], peak_rss_mb())
    replay = {k: v[: run.t] for k, v in run.host.items()}
    return SACResult(env_id, seed, cfg, run.snapshots, replay, run.timing, tuple(run.resumed_from))
