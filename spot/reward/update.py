"""The Bradley-Terry loss of reward-model training and the jitted programs
:func:`spot.reward.train.train_reward_model` runs: one update (alone or with a companion's step),
a chunk of updates (:mod:`spot.loop`), and the held-out evaluation.

Loss (paper §3, eq. 1-2; PT repo ``JaxPref/jax_utils.py``): with segment logits ``l_1, l_2`` (the
mean over steps of PT's ``z_t`` or MR's ``r_phi``), ``P[sigma_2 > sigma_1] = softmax([l_1, l_2])_2``
and the loss is the softmax cross-entropy with soft targets ``[1 - y, y]`` (``y = 0.5`` for ties),
averaged over the batch. Accuracy counts non-tie pairs only.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from spot import loop
from spot.nets import Params
from spot.reward.models import RewardModel


class RewardState(NamedTuple):
    """Training state of a reward model: parameters, optimizer state and steps taken (int32 ``[]``)."""

    params: Params
    opt_state: optax.OptState
    step: jax.Array


class PrefPairs(NamedTuple):
    """Preference pairs on device. Segment 2 is preferred when ``label = 1``.

    Shapes: ``obs_* [Q, T, obs_dim]``, ``act_* [Q, T, act_dim]``, ``timesteps_* [Q, T]`` int32,
    ``mask_* [Q, T]`` float32 (1 = real step), ``label [Q]`` float32 in {0, 0.5, 1}.
    """

    obs_1: jax.Array
    act_1: jax.Array
    timesteps_1: jax.Array
    mask_1: jax.Array
    obs_2: jax.Array
    act_2: jax.Array
    timesteps_2: jax.Array
    mask_2: jax.Array
    label: jax.Array


class ForwardPass(NamedTuple):
    """One update's training forward pass, as a companion sees it: the minibatch's segments
    (``obs_* [B, T, o]``, ``act_* [B, T, a]``), PT's per-step rewards ``r_hat_* [B, T]`` and
    preference attention ``attn_* [B, T, T]`` (dropout on), and ``label [B]``."""

    obs_1: jax.Array
    act_1: jax.Array
    r_hat_1: jax.Array
    attn_1: jax.Array
    obs_2: jax.Array
    act_2: jax.Array
    r_hat_2: jax.Array
    attn_2: jax.Array
    label: jax.Array


def num_pairs(pairs: PrefPairs) -> int:
    """Number of pairs ``Q``."""
    return int(pairs.label.shape[0])


# --------------------------------------------------------------------------- loss
def _pair_terms(logit_1: jax.Array, logit_2: jax.Array, label: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per-pair cross-entropy ``[B]``, correctness ``[B]`` and non-tie flag ``[B]``."""
    logits = jnp.stack([logit_1, logit_2], axis=-1).astype(jnp.float32)
    target = jnp.stack([1.0 - label, label], axis=-1)
    ce = -jnp.sum(target * jax.nn.log_softmax(logits, axis=-1), axis=-1)
    non_tie = label != 0.5
    correct = (logit_2 > logit_1) == (label > 0.5)
    return ce, correct, non_tie


def pref_loss(logit_1: jax.Array, logit_2: jax.Array, label: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Soft-target softmax cross-entropy (eq. 2), batch mean, and accuracy on non-tie pairs.

    Args:
      logit_1, logit_2: ``[B]`` segment logits; label: ``[B]`` in {0, 0.5, 1}, 1 = segment 2 preferred.

    Returns:
      ``(loss, accuracy)``; accuracy is 0 when every pair is a tie.
    """
    if logit_1.shape != logit_2.shape or logit_1.shape != label.shape or logit_1.ndim != 1:
        raise ValueError(f"expected three [B] arrays, got {logit_1.shape}, {logit_2.shape}, {label.shape}")
    ce, correct, non_tie = _pair_terms(logit_1, logit_2, label)
    acc = jnp.sum(correct & non_tie) / jnp.maximum(jnp.sum(non_tie), 1)
    return ce.mean(), acc


# --------------------------------------------------------------------------- model
def both_segments(pairs: PrefPairs) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """``(obs, act, timesteps, mask)`` of the ``2B`` segments of one forward pass: first segments,
    then second segments."""
    cat = functools.partial(jnp.concatenate, axis=0)
    return (
        cat([pairs.obs_1, pairs.obs_2]),
        cat([pairs.act_1, pairs.act_2]),
        cat([pairs.timesteps_1, pairs.timesteps_2]),
        cat([pairs.mask_1, pairs.mask_2]),
    )


def _pair_logits(
    model: RewardModel, params: Params, pairs: PrefPairs, dropout_key: jax.Array | None
) -> tuple[jax.Array, jax.Array]:
    """Both segments in one forward pass of ``2B`` segments."""
    _, _, logit = model.apply(params, *both_segments(pairs), dropout_key)
    b = pairs.label.shape[0]
    return logit[:b], logit[b:]


def init_state(model: RewardModel, key: jax.Array, obs_dim: int, act_dim: int, steps: int) -> RewardState:
    """Fresh parameters, the state of the optimizer of a ``steps``-step run, and step 0."""
    params = model.init(key, obs_dim, act_dim)
    return RewardState(params, _optimizer_init(model, steps)(params), jnp.zeros((), jnp.int32))


@functools.lru_cache(maxsize=32)
def _optimizer_init(model: RewardModel, steps: int) -> Callable[[Params], optax.OptState]:
    """``model.optimizer(steps).init`` as one jitted program per model and run length (kept): run
    eagerly, the zero moments compile a small program per parameter shape, again for every new
    observation size in a process. The same zeros."""
    return jax.jit(model.optimizer(steps).init)


# --------------------------------------------------------------------------- jitted programs
def batch_indices(key: jax.Array, num_pairs: int, batch_size: int) -> jax.Array:
    """Indices of one minibatch: ``batch_size`` distinct pairs out of ``num_pairs``."""
    return jax.random.permutation(key, num_pairs)[:batch_size]


def micro_batches(batch_size: int, micro_batch: int) -> int:
    """Number of equal gradient-accumulation micro-batches of at most ~``micro_batch`` pairs."""
    n = max(1, batch_size // micro_batch)
    while batch_size % n:
        n -= 1
    return n


def make_update(
    model: RewardModel, batch_size: int, steps: int, micro_batch: int = 64
) -> Callable[[RewardState, PrefPairs, jax.Array], tuple[RewardState, dict]]:
    """``update(state, data, key) -> (state, {loss, acc})``: one step on a minibatch of
    ``batch_size`` pairs drawn with ``fold_in(key, state.step)`` (also the dropout key), with the
    optimizer of a ``steps``-step run.

    The minibatch's gradient is accumulated over :func:`micro_batches` equal slices (a scan): the
    same mean loss and gradient as one pass (dropout masks aside), with a fraction of the
    activation memory, and faster on CPU at PT's batch of 256 pairs (docs/benchmarks.md).
    """
    tx = model.optimizer(steps)
    n_micro = micro_batches(batch_size, micro_batch)

    def micro_loss(params: Params, mb: PrefPairs, dropout_key: jax.Array) -> tuple[jax.Array, jax.Array]:
        logit_1, logit_2 = _pair_logits(model, params, mb, dropout_key)
        ce, correct, non_tie = _pair_terms(logit_1, logit_2, mb.label)
        return ce.mean(), jnp.stack([jnp.sum(correct & non_tie), jnp.sum(non_tie)]).astype(jnp.float32)

    def update(state: RewardState, data: PrefPairs, key: jax.Array) -> tuple[RewardState, dict]:
        batch_key, dropout_key = jax.random.split(jax.random.fold_in(key, state.step))
        idx = batch_indices(batch_key, num_pairs(data), batch_size).reshape(n_micro, -1)

        def accumulate(carry: tuple, i: jax.Array) -> tuple[tuple, None]:
            mb = jax.tree.map(lambda x: x[idx[i]], data)
            (loss, counts), grads = jax.value_and_grad(micro_loss, has_aux=True)(
                state.params, mb, jax.random.fold_in(dropout_key, i)
            )
            return jax.tree.map(jnp.add, carry, (loss, counts, grads)), None

        zeros = (jnp.zeros(()), jnp.zeros(2), jax.tree.map(jnp.zeros_like, state.params))
        (loss, counts, grads), _ = jax.lax.scan(accumulate, zeros, jnp.arange(n_micro))
        grads = jax.tree.map(lambda g: g / n_micro, grads)  # mean loss over equal micro-batches
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = {"loss": loss / n_micro, "acc": counts[0] / jnp.maximum(counts[1], 1.0)}
        return RewardState(params, opt_state, state.step + 1), metrics

    return update


COMPANION_STREAM = 0x5EED5
"""``fold_in(step_key, COMPANION_STREAM)`` is a companion's key at a step: no key of the reward
model's (with ``jax_threefry_partitionable``, on by default, ``split(step_key)`` is
``fold_in(step_key, 0)`` and ``fold_in(step_key, 1)``; this is ``fold_in(step_key, 0x5EED5)``)."""


def make_companion_update(
    model: RewardModel, batch_size: int, steps: int, micro_batch: int, companion_step: Callable
) -> Callable[[tuple, PrefPairs, jax.Array], tuple[tuple, dict]]:
    """``update((reward_state, companion_state), data, key)``: :func:`make_update`'s step of the
    reward model (the same minibatch, dropout masks, loss and parameters), reading the preference
    attention of the same pass (``model.apply_attention``), then one ``companion_step`` on that
    pass (:class:`ForwardPass`) with the key ``fold_in(step_key, COMPANION_STREAM)``."""
    tx = model.optimizer(steps)
    n_micro = micro_batches(batch_size, micro_batch)

    def micro_loss(params: Params, mb: PrefPairs, dropout_key: jax.Array) -> tuple[jax.Array, tuple]:
        r_hat, attn, logit = model.apply_attention(params, *both_segments(mb), dropout_key)
        b = mb.label.shape[0]
        ce, correct, non_tie = _pair_terms(logit[:b], logit[b:], mb.label)
        counts = jnp.stack([jnp.sum(correct & non_tie), jnp.sum(non_tie)]).astype(jnp.float32)
        return ce.mean(), (counts, (r_hat[:b], attn[:b], r_hat[b:], attn[b:]))

    def update(state: tuple, data: PrefPairs, key: jax.Array) -> tuple[tuple, dict]:
        rs, cs = state
        step_key = jax.random.fold_in(key, rs.step)
        batch_key, dropout_key = jax.random.split(step_key)
        idx = batch_indices(batch_key, num_pairs(data), batch_size).reshape(n_micro, -1)

        def accumulate(carry: tuple, i: jax.Array) -> tuple[tuple, tuple]:
            mb = jax.tree.map(lambda x: x[idx[i]], data)
            (loss, (counts, out)), grads = jax.value_and_grad(micro_loss, has_aux=True)(
                rs.params, mb, jax.random.fold_in(dropout_key, i)
            )
            return jax.tree.map(jnp.add, carry, (loss, counts, grads)), out

        zeros = (jnp.zeros(()), jnp.zeros(2), jax.tree.map(jnp.zeros_like, rs.params))
        (loss, counts, grads), outs = jax.lax.scan(accumulate, zeros, jnp.arange(n_micro))
        grads = jax.tree.map(lambda g: g / n_micro, grads)
        updates, opt_state = tx.update(grads, rs.opt_state, rs.params)
        rs_next = RewardState(optax.apply_updates(rs.params, updates), opt_state, rs.step + 1)
        r1, a1, r2, a2 = (x.reshape(-1, *x.shape[2:]) for x in outs)  # [n_micro, b, ...] -> [B, ...]
        mb = jax.tree.map(lambda x: x[idx.reshape(-1)], data)
        fp = ForwardPass(mb.obs_1, mb.act_1, r1, a1, mb.obs_2, mb.act_2, r2, a2, mb.label)
        cs, c_metrics = companion_step(cs, fp, jax.random.fold_in(step_key, COMPANION_STREAM))
        metrics = {"loss": loss / n_micro, "acc": counts[0] / jnp.maximum(counts[1], 1.0), **c_metrics}
        return (rs_next, cs), metrics

    return update


def make_train_chunk(
    model: RewardModel,
    batch_size: int,
    length: int,
    steps: int,
    micro_batch: int = 64,
    companion_step: Callable | None = None,
) -> loop.Chunk:
    """Jitted ``chunk(state, n, data, key) -> (state, {loss, acc, active} [length])``: ``n <= length``
    steps of :func:`make_update` (:func:`spot.loop.make_chunk`, ``"stack"``), or of
    :func:`make_companion_update` with a ``companion_step`` (the state is then ``(reward_state,
    companion_state)``). Kept per arguments, so a second run with the same model and sizes reuses
    the compiled program."""
    return _train_chunk(model, batch_size, length, steps, micro_batch, companion_step)


@functools.lru_cache(maxsize=16)
def _train_chunk(
    model: RewardModel, batch_size: int, length: int, steps: int, micro_batch: int, companion_step: Callable | None
) -> loop.Chunk:
    if companion_step is None:
        return loop.make_chunk(make_update(model, batch_size, steps, micro_batch), length, "stack")
    update = make_companion_update(model, batch_size, steps, micro_batch, companion_step)
    return loop.make_chunk(update, length, "stack")


@functools.lru_cache(maxsize=16)
def make_evaluate(model: RewardModel) -> Callable[[Params, PrefPairs, jax.Array], tuple]:
    """``evaluate(params, data, weight) -> (loss, acc)`` over minibatches ``data [M, b, ...]``
    (deterministic); ``weight [M, b]`` is 0 for padding pairs."""

    def evaluate(params: Params, data: PrefPairs, weight: jax.Array) -> tuple[jax.Array, jax.Array]:
        def one(args: tuple[PrefPairs, jax.Array]) -> jax.Array:
            mb, wt = args
            ce, correct, non_tie = _pair_terms(*_pair_logits(model, params, mb, None), mb.label)
            counted = wt * non_tie
            return jnp.stack([jnp.sum(wt * ce), jnp.sum(wt), jnp.sum(counted * correct), jnp.sum(counted)])

        sums = jax.lax.map(one, (data, weight)).sum(axis=0)
        return sums[0] / sums[1], sums[2] / jnp.maximum(sums[3], 1.0)

    return jax.jit(evaluate)
