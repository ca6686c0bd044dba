"""Implicit Q-Learning (Kostrikov, Nair & Levine, 2021, arXiv:2110.06169), Sec. 4 and Alg. 1.

One update (value, actor, critics, target) with the losses of the paper:

* value, eq. (5): ``L_V = E[L2_tau(min_i Qbar_i(s, a) - V(s))]`` with the expectile loss
  ``L2_tau(u) = |tau - 1(u < 0)| u^2`` against the *target* critics;
* actor, eq. (7) (AWR): ``L_pi = -E[min(exp(beta (min_i Qbar_i(s, a) - V(s))), 100) log pi(a|s)]``;
  pi is a Gaussian with mean ``tanh(MLP(s))`` and a state-independent log-std clipped to [-5, 2],
  no tanh-squash correction (the reference's ``NormalTanhPolicy(state_dependent_std=False,
  tanh_squash_distribution=False)``); ``iql.actor_std=state_dependent``, ``iql.log_std_min`` and
  ``iql.actor_dist=tanh_gaussian`` give HPL's WiseRL actor (a log-std head, [-7, 2], squashed);
  ``iql.actor_dist=deterministic`` replaces ``-log pi(a|s)`` by ``sum_i (tanh(MLP(s))_i - a_i)^2``
  (CORL's deterministic IQL actor, its hopper-medium-replay config);
* critics, eq. (6): ``L_Q = E[sum_i (Q_i(s, a) - r - gamma mask V(s'))^2]``, ``mask = 1 - terminal``;
* target: ``Qbar <- tau_polyak Q + (1 - tau_polyak) Qbar``.

Which value network V feeds the actor's advantages and the critics' targets is
``IQLConfig.order``:

* ``parallel`` (default): the value network as it was at the start of the update, so the three
  losses are independent of each other; the order of CORL's IQL [tinkoff-ai/CORL :
  algorithms/offline/iql.py] and unifloral's [EmptyJackson/unifloral : algorithms/iql.py]. The
  advantages come out of the value loss's own forward pass.
* ``sequential``: the just-updated value V' (V, then actor, then critics), the order of the
  ikostrikov reference that the PT repo vendors (reference/algorithms.md §2.1); V' is evaluated
  once on ``[s; s']``.

The two differ by one Adam step of V (lr 3e-4) in what the actor and critics see. ``parallel``
needs 15 instead of 16 batch-256 passes through a 256x256 layer, and its three independent
updates keep both cores busier; it is the faster of the two on CPU (``spot bench iql --order ...``;
figures in docs/benchmarks.md).

Networks: every MLP is ``IQLConfig.hidden`` (256-256) ReLU with orthogonal init sqrt(2) on all
layers (reference ``common.py``); the two critics are two separate MLPs whose outputs are stacked
(``[NUM_CRITICS, ...]``). The reference vmaps one critic module over stacked weights; on XLA:CPU
the batched matmuls and their layout copies made the update slower than two plain MLPs
(docs/benchmarks.md), which compute the same function (only the initial weights drawn from a key differ). Adam 3e-4
for all three; the actor's learning rate follows a cosine decay to 0 over ``IQLConfig.steps``.

Speed: an update is 15-16 passes of 256x256 matmuls at batch 256, which dominate its time; where
the rest goes, and what was tried, is in docs/benchmarks.md.

Training runs in :mod:`spot.loop` chunks of ``IQLConfig.chunk`` updates with minibatches drawn
inside jit (STYLE.md rules 4 and 7), exactly ``IQLConfig.steps`` updates in all (the last chunk is
shorter when ``steps`` is not a multiple of ``chunk``, so the actor's cosine schedule ends at the
last update); several seeds can run as a vmap axis in one program
(:func:`make_vmapped_train_chunk`). :func:`train` is the run: chunks, the NaN/inf check
(:class:`spot.NonFiniteError` at a chunk boundary) and the evaluation schedule (:func:`eval_steps`:
step 0, every multiple of ``eval.every``, the last step).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

from spot import NonFiniteError, SpotError, loop, padding
from spot.batches import Transitions
from spot.config import IQL_ORDERS, IQLConfig
from spot.nets import MLP, Params, create_train_state, orthogonal_init

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0  # reference learner.py passes log_std_min=-5; policy.py max 2
AWR_WEIGHT_MAX = 100.0  # reference actor.py: exp_a = minimum(exp(beta * adv), 100)
NUM_CRITICS = 2


class IQLState(NamedTuple):
    """Everything an IQL run carries between updates (a pytree; stack it over seeds to vmap)."""

    actor: TrainState
    critic: TrainState
    value: TrainState
    target_critic_params: Params
    step: jax.Array


# --------------------------------------------------------------------------- networks
class Actor(nn.Module):
    """Gaussian policy: mean ``tanh(MLP(s))``, state-independent ``log_std`` (clipped on use).

    ``std="state_dependent"``: ``log_std`` is a second linear head on the trunk (parameters
    ``Dense_1``); ``squash=True``: the returned mean is the pre-tanh ``mu`` of a tanh-squashed
    Gaussian (:func:`actor_log_prob`; the action is ``tanh(mu)``). Both are HPL's WiseRL actor
    (``iql.actor_std``, ``iql.actor_dist``); the defaults keep the reference IQL's parameters.
    """

    hidden: tuple[int, ...]
    act_dim: int
    std: str = "state_independent"
    log_std_min: float = LOG_STD_MIN
    squash: bool = False
    dropout: float = 0.0  # after each hidden layer in training (iql.actor_dropout); none when acting

    @nn.compact
    def __call__(self, obs: jax.Array, deterministic: bool = True) -> tuple[jax.Array, jax.Array]:
        trunk = MLP(self.hidden, activate_final=True, kernel_init=orthogonal_init(), dropout=self.dropout or None)
        h = trunk(obs, deterministic=deterministic)
        mean = nn.Dense(self.act_dim, kernel_init=orthogonal_init())(h)
        if not self.squash:
            mean = nn.tanh(mean)
        if self.std == "state_dependent":
            log_std = nn.Dense(self.act_dim, kernel_init=orthogonal_init())(h)
        else:
            log_std = self.param("log_std", nn.initializers.zeros, (self.act_dim,))
        return mean, jnp.clip(log_std, self.log_std_min, LOG_STD_MAX)


class Value(nn.Module):
    """``V(s)``, shape ``[...]``."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden, out_dim=1, kernel_init=orthogonal_init())(obs)[..., 0]


class Critic(nn.Module):
    """``Q(s, a)`` on ``[s; a]``, shape ``[...]``."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array, act: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, act], axis=-1)
        return MLP(self.hidden, out_dim=1, kernel_init=orthogonal_init())(x)[..., 0]


class Critics(nn.Module):
    """``NUM_CRITICS`` independent critics, outputs stacked ``[NUM_CRITICS, ...]``."""

    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array, act: jax.Array) -> jax.Array:
        return jnp.stack([Critic(self.hidden)(obs, act) for _ in range(NUM_CRITICS)])


def actor_net(cfg: IQLConfig, act_dim: int) -> Actor:
    """The actor module of ``cfg`` (``iql.actor_std``, ``iql.log_std_min``, ``iql.actor_dist``)."""
    return Actor(
        tuple(cfg.hidden),
        act_dim,
        cfg.actor_std,
        cfg.log_std_min,
        cfg.actor_dist == "tanh_gaussian",
        cfg.actor_dropout,
    )


def apply_actor(
    cfg: IQLConfig, state: TrainState, params: Params, obs: jax.Array, dropout_key: jax.Array | None
) -> tuple[jax.Array, jax.Array]:
    """The actor's ``(mean, log_std)`` in training: with dropout (``iql.actor_dropout > 0``) from
    ``dropout_key``, which must then be given."""
    if cfg.actor_dropout > 0:
        if dropout_key is None:
            raise ValueError("iql.actor_dropout > 0 needs a dropout key")
        return state.apply_fn(params, obs, deterministic=False, rngs={"dropout": dropout_key})
    return state.apply_fn(params, obs)


@functools.cache
def _nets(cfg: IQLConfig, act_dim: int) -> tuple[Actor, nn.Module, Value]:
    hidden = tuple(cfg.hidden)
    return actor_net(cfg, act_dim), Critics(hidden), Value(hidden)


@functools.cache
def _optimizers(cfg: IQLConfig) -> tuple[optax.GradientTransformation, ...]:
    """Actor, critic and value optimizers. Cached, like :func:`_nets`, because a TrainState's
    ``apply_fn`` and ``tx`` are static pytree fields: fresh ones would make every new state a
    new jit signature and recompile the train chunk."""
    return optax.adam(optax.cosine_decay_schedule(cfg.lr, cfg.steps)), optax.adam(cfg.lr), optax.adam(cfg.lr)


@functools.cache
def _jitted_init(module: nn.Module) -> Callable[..., Params]:
    """``module.init`` as one jitted program per network (cached; modules are hashable).

    Not one program for all three networks: on CPU (jaxlib 0.10.2) a jitted init of actor,
    critics and value together never finishes once the layers are 64 wide or more; each network
    on its own does. Vmapping these inits over seeds hangs the same way (256 wide, 5 seeds), so
    :func:`init_state` stacks per-seed states instead.
    """
    return jax.jit(module.init)


def _train_state(module: nn.Module, params: Params, tx: optax.GradientTransformation) -> TrainState:
    # An int32 step from the start, so the first chunk call has the same signature as later ones.
    return _jitted_train_state(module, tx)(params)


@functools.cache
def _jitted_train_state(module: nn.Module, tx: optax.GradientTransformation) -> Callable[[Params], TrainState]:
    """:func:`_train_state` as one jitted program per network and optimizer (cached, as
    :func:`_optimizers` keeps the optimizers): run eagerly, the optimizer's zero moments compile a
    small program per parameter shape, again for every new observation size in a process."""
    return jax.jit(lambda params: create_train_state(module, params, tx).replace(step=jnp.zeros((), jnp.int32)))


# --------------------------------------------------------------------------- pure pieces
def expectile_loss(diff: jax.Array, expectile: float) -> jax.Array:
    """Elementwise asymmetric squared loss ``|tau - 1(u < 0)| u^2`` of eq. (5), ``u = Q - V``."""
    weight = jnp.where(diff > 0, expectile, 1.0 - expectile)
    return weight * jnp.square(diff)


def awr_weights(adv: jax.Array, temperature: float) -> jax.Array:
    """AWR weights ``min(exp(beta * adv), 100)`` of eq. (7) (clip as in the reference)."""
    return jnp.minimum(jnp.exp(temperature * adv), AWR_WEIGHT_MAX)


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, act: jax.Array) -> jax.Array:
    """``log N(act; mean, diag(exp(log_std)^2))`` summed over the last axis."""
    z = (act - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * math.log(2.0 * math.pi), axis=-1)


SQUASH_EPS = 1e-6  # dataset actions clipped to +-(1 - eps) before atanh


def tanh_gaussian_log_prob(mu: jax.Array, log_std: jax.Array, act: jax.Array) -> jax.Array:
    """``log pi(a)`` of ``a = tanh(u)``, ``u ~ N(mu, exp(log_std)^2)``: ``log N(atanh(a); mu, sigma)
    - sum log(1 - a^2)``, with ``a`` clipped to ``±(1 - SQUASH_EPS)``."""
    a = jnp.clip(act, -1.0 + SQUASH_EPS, 1.0 - SQUASH_EPS)
    return gaussian_log_prob(mu, log_std, jnp.arctanh(a)) - jnp.sum(jnp.log1p(-jnp.square(a)), axis=-1)


def actor_log_prob(cfg: IQLConfig, mean: jax.Array, log_std: jax.Array, act: jax.Array) -> jax.Array:
    """The actor's ``log pi(a | s)`` from its outputs: Gaussian, tanh-squashed Gaussian, or, for the
    deterministic actor, minus the squared error of its action (``iql.actor_dist``)."""
    if cfg.actor_dist == "tanh_gaussian":
        return tanh_gaussian_log_prob(mean, log_std, act)
    if cfg.actor_dist == "deterministic":  # CORL's DeterministicPolicy loss: exp_adv * sum (pi(s) - a)^2
        return -jnp.sum(jnp.square(mean - act), axis=-1)
    return gaussian_log_prob(mean, log_std, act)


# --------------------------------------------------------------------------- state and update
def init_state(
    key: jax.Array,
    obs_dim: int,
    act_dim: int,
    cfg: IQLConfig,
    optimizers: tuple[optax.GradientTransformation, ...] | None = None,
) -> IQLState:
    """Fresh networks and Adam states; with keys ``[S]``, ``S`` states stacked on a leading axis
    (the input of :func:`make_vmapped_train_chunk`), state ``s`` equal to ``init_state(key[s])``.

    Args:
      key: PRNG key of this run's IQL stage, or keys ``[S]`` for stacked seeds.
      obs_dim, act_dim: data sizes.
      cfg: IQL hyperparameters (``hidden``, ``lr``, ``steps`` for the actor's cosine schedule).
      optimizers: (actor, critic, value) optimizers; default IQL's. Pass the same objects on every
        call (they are static fields of the state: new ones recompile the train chunk).
    """
    if key.ndim == 1:  # one state per seed, stacked (see _jitted_init for why not vmap)
        states = [init_state(k, obs_dim, act_dim, cfg, optimizers) for k in key]
        return jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)
    actor_key, critic_key, value_key = jax.random.split(key, 3)
    actor_def, critic_def, value_def = _nets(cfg, act_dim)
    obs, act = np.zeros((1, obs_dim), np.float32), np.zeros((1, act_dim), np.float32)  # no program per size
    critic_params = _jitted_init(critic_def)(critic_key, obs, act)
    actor_tx, critic_tx, value_tx = optimizers or _optimizers(cfg)
    return IQLState(
        actor=_train_state(actor_def, _jitted_init(actor_def)(actor_key, obs), actor_tx),
        critic=_train_state(critic_def, critic_params, critic_tx),
        value=_train_state(value_def, _jitted_init(value_def)(value_key, obs), value_tx),
        # own buffers (the state is donated): the same program again, not a copy program per shape
        target_critic_params=_jitted_init(critic_def)(critic_key, obs, act),
        step=jnp.zeros((), jnp.int32),
    )


def update(
    state: IQLState, batch: Transitions, cfg: IQLConfig, dropout_key: jax.Array | None = None
) -> tuple[IQLState, dict[str, jax.Array]]:
    """One IQL update (value, actor, critics, target), pure; ``cfg.order`` picks which value
    network the actor and critics see (module docstring).

    Args:
      state: current state.
      batch: a minibatch, ``obs [B, obs_dim]``, ``act [B, act_dim]``, ``rew/mask [B]``.
      cfg: hyperparameters (static).
      dropout_key: key of the actor's dropout masks (only with ``iql.actor_dropout > 0``).

    Returns:
      ``(new_state, metrics)`` with scalar metrics named ``iql/...``.
    """
    if batch.obs.ndim != 2 or batch.rew.shape != batch.obs.shape[:1]:
        raise ValueError(f"expected obs [B, o] and rew [B], got {batch.obs.shape} and {batch.rew.shape}")
    if cfg.order not in IQL_ORDERS:
        raise ValueError(f"iql.order is {cfg.order!r}; expected one of {IQL_ORDERS}")
    batch_size = batch.obs.shape[0]

    # Target critics once: the value loss and the actor's advantages both use min_i Qbar_i(s, a).
    target_q = jnp.min(state.critic.apply_fn(state.target_critic_params, batch.obs, batch.act), axis=0)
    if cfg.order == "parallel":  # V(s') before the value step; nothing below waits for it
        next_v = state.value.apply_fn(state.value.params, batch.next_obs)

    def value_loss_fn(params: Params) -> tuple[jax.Array, tuple[jax.Array, dict[str, jax.Array]]]:
        v = state.value.apply_fn(params, batch.obs)
        adv = target_q - v
        loss = expectile_loss(adv, cfg.expectile).mean()
        return loss, (adv, {"iql/value_loss": loss, "iql/v_mean": v.mean()})

    value_grads, (adv, value_info) = jax.grad(value_loss_fn, has_aux=True)(state.value.params)
    value = state.value.apply_gradients(grads=value_grads)

    if cfg.order == "sequential":  # V' on [s; s'] in one pass: advantages and critic targets
        v_both = value.apply_fn(value.params, jnp.concatenate([batch.obs, batch.next_obs], axis=0))
        adv, next_v = target_q - v_both[:batch_size], v_both[batch_size:]
    weights = awr_weights(adv, cfg.temperature)

    def actor_loss_fn(params: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
        mean, log_std = apply_actor(cfg, state.actor, params, batch.obs, dropout_key)
        log_prob = actor_log_prob(cfg, mean, log_std, batch.act)
        loss = -(weights * log_prob).mean()
        return loss, {"iql/actor_loss": loss, "iql/log_std_mean": log_std.mean()}

    actor_grads, actor_info = jax.grad(actor_loss_fn, has_aux=True)(state.actor.params)
    actor = state.actor.apply_gradients(grads=actor_grads)

    target = batch.rew + cfg.discount * batch.mask * next_v

    def critic_loss_fn(params: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
        q = state.critic.apply_fn(params, batch.obs, batch.act)  # shape is (NUM_CRITICS, B)
        loss = jnp.square(q - target).sum(axis=0).mean()
        return loss, {"iql/critic_loss": loss, "iql/q_mean": q.mean()}

    critic_grads, critic_info = jax.grad(critic_loss_fn, has_aux=True)(state.critic.params)
    critic = state.critic.apply_gradients(grads=critic_grads)
    target_params = optax.incremental_update(critic.params, state.target_critic_params, cfg.tau)

    metrics = {
        **value_info,
        **actor_info,
        **critic_info,
        "iql/adv_mean": adv.mean(),
        "iql/adv_max": adv.max(),
        "iql/awr_weight_mean": weights.mean(),
        "iql/awr_clip_frac": jnp.mean(weights >= AWR_WEIGHT_MAX),
        "iql/target_mean": target.mean(),
    }
    new_state = IQLState(actor, critic, value, target_params, state.step + 1)
    return new_state, metrics


def sampled_update(cfg: IQLConfig) -> Callable[[IQLState, Transitions, jax.Array], tuple[IQLState, dict]]:
    """``update(state, data, key)``: :func:`update` on ``cfg.batch_size`` rows of the whole dataset
    ``data`` drawn with ``fold_in(key, state.step)``, so one key can serve a whole run. ``data``:
    :class:`Transitions`, or :class:`spot.padding.Rows` of them (padded to a bucket, rows drawn
    from the real ones: the same draws, and one program for every dataset of a bucket)."""

    def step(state: IQLState, data: Any, key: jax.Array) -> tuple[IQLState, dict[str, jax.Array]]:
        step_key = jax.random.fold_in(key, state.step)
        idx = jax.random.randint(step_key, (cfg.batch_size,), 0, padding.count(data))
        dropout_key = jax.random.fold_in(step_key, 1) if cfg.actor_dropout > 0 else None
        return update(state, padding.take(data, idx), cfg, dropout_key)

    return step


@functools.lru_cache(maxsize=16)
def make_train_chunk(cfg: IQLConfig) -> Callable[..., tuple[IQLState, dict]]:
    """Jitted ``train_chunk(state, n, data, key) -> (state, metrics)``: ``n`` updates (at most
    ``cfg.chunk`` in a run) of :func:`sampled_update`, metrics averaged over them in the loop carry
    (:func:`spot.loop.make_chunk`, ``"sum"``). ``state`` is donated: do not reuse it. Kept per config;
    compiled once per observation and action size when ``data`` is :func:`spot.padding.padded`.
    """
    return loop.make_chunk(sampled_update(cfg), cfg.chunk, "sum")


@functools.lru_cache(maxsize=16)
def make_vmapped_train_chunk(
    cfg: IQLConfig, per_seed_rewards: bool = False, padded: bool = False
) -> Callable[..., tuple[IQLState, dict]]:
    """Like :func:`make_train_chunk` for ``S`` seeds in one program.

    The returned ``fn(states, n, data, keys)`` takes states stacked over a leading seed axis
    (``init_state(keys, ...)`` with keys ``[S]``), the shared ``n`` and ``data`` and keys ``[S]``;
    metrics come back with shape ``[S]``. With ``per_seed_rewards``, ``data.rew`` is ``[S, N]``
    (each seed's own reward model or shaping) and the other fields are shared. ``padded``: ``data``
    is :class:`spot.padding.Rows` of the transitions (its ``count`` shared by the seeds).
    """
    data_axes = Transitions(None, None, 0, None, None) if per_seed_rewards else None
    if padded and data_axes is not None:
        data_axes = padding.Rows(data_axes, None)
    return loop.make_chunk(sampled_update(cfg), cfg.chunk, "sum", vmap_axes=(0, data_axes, 0))


@dataclass
class Curve:
    """A trained policy's final state and its evaluation curve."""

    state: Any
    steps: list[int]
    scores: list[float]
    eval_s: float  # wall seconds spent evaluating


def eval_steps(steps: int, every: int) -> list[int]:
    """The update counts at which a run of ``steps`` updates is evaluated: 0 (the initial policy),
    every multiple of ``every`` up to ``steps``, and ``steps`` itself
    (``eval_steps(1500, 1000) == [0, 1000, 1500]``)."""
    if steps < 1 or every < 1:
        raise SpotError(f"iql.steps={steps} and eval.every={every} must both be >= 1")
    return sorted({0, *range(every, steps + 1, every), steps})


def train(
    chunk: Callable,
    state: Any,
    args: Callable[[int], tuple],
    cfg: IQLConfig,
    eval_every: int,
    evaluate: Callable[[Params, int], float],
    log: Callable[[dict[str, float], int], None] | None = None,
) -> Curve:
    """Exactly ``cfg.steps`` updates with ``evaluate(actor_params, steps_done) -> score`` at exactly
    :func:`eval_steps`: before the first update, at every multiple of ``eval_every`` and after the
    last. Between two evaluations the updates run in chunks of ``cfg.chunk`` (the last one shorter
    where an evaluation falls inside a chunk); chunks are numbered through the run.

    Args:
      chunk: :func:`make_train_chunk` or IPL's; ``args(c)``: its arguments after ``(state, n)`` for
        chunk ``c``.
      log: ``log(chunk_mean_metrics, steps_done)`` after every chunk.

    Raises:
      NonFiniteError: a ``*loss`` metric is NaN/inf (the step is the chunk's end).
    """
    curve = Curve(state, [], [], 0.0)

    def run_eval(done: int) -> None:
        t0 = time.perf_counter()
        curve.scores.append(float(evaluate(curve.state.actor.params, done)))
        curve.eval_s += time.perf_counter() - t0
        curve.steps.append(done)

    run_eval(0)
    done, chunks = 0, 0
    for stop in eval_steps(cfg.steps, eval_every)[1:]:
        n, first_chunk, offset = stop - done, chunks, done

        def on_chunk(row: dict[str, Any], state: Any, offset: int = offset) -> None:
            if log is not None:
                log({k: v for k, v in row.items() if k != "step"}, offset + row["step"])

        try:
            curve.state = loop.run(
                chunk,
                curve.state,
                lambda c, first=first_chunk: args(first + c),
                steps=n,
                length=cfg.chunk,
                on_chunk=on_chunk,
            ).state
        except NonFiniteError as e:  # the loop counts from this stretch's start
            raise NonFiniteError(offset + e.step, e.loss_name, e.value) from None
        chunks += len(loop.chunk_sizes(n, cfg.chunk))
        done = stop
        run_eval(done)
    return curve


@functools.partial(jax.jit, static_argnames="cfg")
def act(actor_params: Params, obs: jax.Array, cfg: IQLConfig) -> jax.Array:
    """Deterministic (mean) action for ``obs [..., obs_dim]`` -> ``[..., act_dim]`` in [-1, 1]
    (``tanh(mu)`` for the squashed actor)."""
    act_dim = actor_params["params"]["Dense_0"]["bias"].shape[-1]
    mean, _ = actor_net(cfg, act_dim).apply(actor_params, jnp.asarray(obs, jnp.float32))
    return jnp.tanh(mean) if cfg.actor_dist == "tanh_gaussian" else mean
