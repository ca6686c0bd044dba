"""Inverse Preference Learning with IQL (Hejna & Sadigh, 2023, arXiv:2305.15363), IPL-IQL.

IPL trains no reward network. The reward is read off the Q-function through the inverse soft
Bellman operator, ``r_Q(s, a, s') = Q(s, a) - gamma V(s')``, and the preference loss is put
directly on Q. Everything below follows the reference code
[jhejna/inverse-preference-learning : research/algs/ipl_iql.py] (reference/algorithms.md §3.1).

A minibatch is ``B`` preference pairs, cut to one random contiguous window of ``S`` steps
(shared across the batch) so that each segment gives ``S - 1`` transitions
``(s_t, a_t, s_{t+1}) = (obs[t], act[t], obs[t+1])`` with discount ``gamma`` and no terminal.
With replay on, ``iql.batch_size`` dataset transitions are added (their ``mask`` = 1 - terminal).
One update, in the reference's order:

1. value: ``L_V = mix_v(L2_tau(min_i Qbar_i(s, a) - V(s)))`` (expectile loss toward the min of
   the target critics), where ``mix_w(x) = (1 - w) 1/2 (E_seg1 x + E_seg2 x) + w E_replay x``
   and, without replay, ``1/2 (E_seg1 x + E_seg2 x)``;
2. critics, per ensemble member ``i``:
   ``r_i(s, a, s') = Q_i(s, a) - gamma mask V'(s')`` with ``V'`` the just-updated value, no
   gradient, clipped to ``+-1 / (c (1 - gamma))`` when ``target_clipping``;
   ``L_pref = mean_{i, pairs} BCE_logits(sum_t r_i(sigma_2) - sum_t r_i(sigma_1), y)``,
   ``y = 1`` when segment 2 is preferred and ``0.5`` for ties;
   ``L_chi2 = c mix_{w_c}(r^2)`` (mean over members too); the critics minimise ``L_pref + L_chi2``;
3. actor (AWR): ``L_pi = mix_{w_pi}(-min(exp(beta (min_i Qbar_i(s, a) - V'(s))), 100) log pi(a|s))``;
4. target: ``Qbar <- tau Q + (1 - tau) Qbar`` every step.

Reference facts followed (reference/algorithms.md §3): D4RL values chi2_coeff 0.5, expectile
0.7, temperature 3 (reference beta = 1/3 divides the advantage), AWR clip 100, replay weights 0.5,
target clipping on, feedback batch 8, segment 100 cut to 64-step windows, Adam 3e-4 for all three
nets with **no** learning-rate schedule (``configs/gym_locomotion/ipl_iql.yaml``), critic ensemble
of 2, one value net, polyak 0.005. Networks and state are IQL's (:mod:`spot.policy.iql`), so
``iql.act(state.actor.params, obs, iql_cfg)`` runs an IPL policy.

Deviations and choices:

* The window start is uniform over all ``T - S + 1`` positions; the reference's feedback buffer
  draws it from ``randint(0, T - S)``, which never picks the last window (and fails for S = T)
  [jhejna/inverse-preference-learning : research/datasets/feedback_buffer.py].
  ``subsample >= T`` uses whole segments (the reference's ``subsample_size=None``).
* Pairs of one minibatch are drawn without replacement (with replacement only when there are
  fewer pairs than ``feedback_batch``); the reference walks shuffled epochs of the feedback set.
* As in the reference, ``s'`` of a segment's step ``t`` is ``obs[t + 1]`` of the segment, also
  where a segment crosses an episode end (PT's human segments may).
* No terminals inside segments (the reference uses discount ``gamma`` for every feedback step).
* The clip bound uses ``gamma``; the reference uses each row's ``gamma mask``, which differs only
  on replay terminals, where ``mask V(s') = 0`` anyway.
* ``ipl/pref_acc`` (non-tie pairs) uses the ensemble-mean logit; ``chi2_coeff = 0`` disables the
  clipping (its bound is infinite).

Training runs in :mod:`spot.loop` chunks of ``iql_cfg.chunk`` updates (exactly ``iql_cfg.steps``
in all) with minibatches drawn in jit from ``fold_in(key, state.step)``; the state is donated.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from spot import SpotError, loop, padding
from spot.config import IPLConfig, IQLConfig
from spot.nets import Params
from spot.policy import iql
from spot.policy.iql import IQLState, Transitions

FEEDBACK_KEYS = ("obs_1", "act_1", "obs_2", "act_2", "label")


class FeedbackPairs(NamedTuple):
    """Labelled segment pairs on device (float32). Segment 2 is preferred when ``label = 1``.

    Attributes:
      obs_1, obs_2: ``[Q, T, obs_dim]``.
      act_1, act_2: ``[Q, T, act_dim]``.
      label: ``[Q]`` in {0, 0.5, 1}; 0.5 = equally preferred.
    """

    obs_1: jax.Array
    act_1: jax.Array
    obs_2: jax.Array
    act_2: jax.Array
    label: jax.Array


def feedback_from(batch: Mapping[str, np.ndarray], where: str = "IPL feedback") -> FeedbackPairs:
    """Check a :func:`spot.data.labels.segment_batch` dict and move it to the device.

    Extra keys (``rew_*``, ``timesteps_*``) are ignored. Padded steps (a ``mask_*`` key with
    zeros) are refused: IPL sums the implicit reward over every step of a segment.
    """
    missing = [k for k in FEEDBACK_KEYS if k not in batch]
    if missing:
        raise SpotError(f"{where}: missing key(s) {', '.join(missing)}; expected {', '.join(FEEDBACK_KEYS)}")
    q, t = np.shape(batch["obs_1"])[:2]
    for s in ("1", "2"):
        obs, act = np.shape(batch[f"obs_{s}"]), np.shape(batch[f"act_{s}"])
        if len(obs) != 3 or len(act) != 3 or obs[:2] != (q, t) or act[:2] != (q, t):
            raise SpotError(
                f"{where}: segment {s} has obs {obs} and act {act}; expected "
                f"[{q}, {t}, obs_dim] and [{q}, {t}, act_dim]"
            )
        if f"mask_{s}" in batch and not np.all(np.asarray(batch[f"mask_{s}"]) == 1):
            raise SpotError(f"{where}: segment {s} has padded steps (mask_{s} = 0); IPL needs whole segments")
    if t < 2:
        raise SpotError(f"{where}: segments have {t} step(s); IPL needs at least 2 (one transition)")
    if np.shape(batch["label"]) != (q,) or not np.all(np.isin(batch["label"], (0.0, 0.5, 1.0))):
        raise SpotError(f"{where}: 'label' must have shape [{q}] and values 0, 0.5 or 1 (1 = segment 2 preferred)")
    return FeedbackPairs(*(jnp.asarray(batch[k], jnp.float32) for k in FEEDBACK_KEYS))


# --------------------------------------------------------------------------- pure pieces
def target_clip_bound(discount: float, chi2_coeff: float) -> float:
    """``1 / (c (1 - gamma))``: the largest |Q| a chi^2-regularised Q-function reaches."""
    return 1.0 / (chi2_coeff * (1.0 - discount))


def mix(loss_1: jax.Array, loss_2: jax.Array, loss_replay: jax.Array | None, replay_weight: float) -> jax.Array:
    """``(1 - w) 1/2 (mean loss_1 + mean loss_2) + w mean loss_replay``; without replay the
    feedback term alone (the mean over both segments, which have equal sizes)."""
    feedback = 0.5 * (loss_1.mean() + loss_2.mean())
    if loss_replay is None:
        return feedback
    return (1.0 - replay_weight) * feedback + replay_weight * loss_replay.mean()


def preference_loss(r_1: jax.Array, r_2: jax.Array, label: jax.Array) -> jax.Array:
    """Bradley-Terry loss on summed implicit rewards, mean over leading axes and pairs.

    Args:
      r_1, r_2: per-step rewards ``[..., B, T]`` (e.g. ``[n_critics, B, T]``).
      label: ``[B]`` soft targets, 1 = segment 2 preferred, 0.5 = tie.

    Returns:
      ``mean BCE_with_logits(sum_t r_2 - sum_t r_1, label)``.
    """
    if r_1.shape != r_2.shape or r_1.ndim < 2 or r_1.shape[-2:-1] != label.shape:
        raise ValueError(f"expected r_1, r_2 [..., B, T] and label [B], got {r_1.shape}, {r_2.shape}, {label.shape}")
    logits = r_2.sum(axis=-1) - r_1.sum(axis=-1)
    return optax.sigmoid_binary_cross_entropy(logits, jnp.broadcast_to(label, logits.shape)).mean()


def chi2_loss(
    r_1: jax.Array, r_2: jax.Array, r_replay: jax.Array | None, coeff: float, replay_weight: float
) -> jax.Array:
    """``c mix_w(r^2)``: the chi^2 regulariser on implicit rewards of both segments and replay."""
    return coeff * mix(
        jnp.square(r_1), jnp.square(r_2), None if r_replay is None else jnp.square(r_replay), replay_weight
    )


def _accuracy(logits: jax.Array, label: jax.Array) -> jax.Array:
    """Share of non-tie pairs whose logit has the label's sign (0 if all are ties)."""
    non_tie = label != 0.5
    correct = (logits > 0) == (label > 0.5)
    return jnp.sum(correct & non_tie) / jnp.maximum(jnp.sum(non_tie), 1)


def _transitions(fb: FeedbackPairs) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Both segments as flat transitions ``[2 B (S-1), dim]``: segment 1's rows, then segment 2's."""

    def flat(x: jax.Array) -> jax.Array:
        return x.reshape(-1, x.shape[-1])  # shape is (B * (S - 1), dim)

    obs = jnp.concatenate([flat(fb.obs_1[:, :-1]), flat(fb.obs_2[:, :-1])])
    act = jnp.concatenate([flat(fb.act_1[:, :-1]), flat(fb.act_2[:, :-1])])
    next_obs = jnp.concatenate([flat(fb.obs_1[:, 1:]), flat(fb.obs_2[:, 1:])])
    return obs, act, next_obs


# --------------------------------------------------------------------------- state and update
@functools.cache
def _optimizers(iql_cfg: IQLConfig) -> tuple[optax.GradientTransformation, ...]:
    """Actor, critic and value optimizers: Adam at ``iql_cfg.lr``, no schedule (IPL D4RL config).
    Cached so that states built twice share ``tx`` (a static field) and jit does not recompile."""
    return optax.adam(iql_cfg.lr), optax.adam(iql_cfg.lr), optax.adam(iql_cfg.lr)


def init_state(key: jax.Array, obs_dim: int, act_dim: int, iql_cfg: IQLConfig) -> IQLState:
    """Fresh IQL networks (:func:`iql.init_state`: keys ``[S]`` give stacked states) with IPL's
    constant-rate optimizers."""
    return iql.init_state(key, obs_dim, act_dim, iql_cfg, optimizers=_optimizers(iql_cfg))


def _update_rows(
    fb: FeedbackPairs, replay: Transitions | None, gamma: float, use_replay: bool
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The rows one update trains on: ``obs, act, next_obs, discount``, segment 1's transitions,
    then segment 2's (discount ``gamma``, no terminals inside segments), then the replay rows
    (``gamma * mask``) when ``use_replay``."""
    if fb.obs_1.ndim != 3 or fb.obs_1.shape != fb.obs_2.shape or fb.label.shape != fb.obs_1.shape[:1]:
        raise ValueError(
            f"expected obs_1, obs_2 [B, S, o] and label [B], got {fb.obs_1.shape}, {fb.obs_2.shape}, {fb.label.shape}"
        )
    if use_replay and (replay is None or replay.obs.ndim != 2 or replay.obs.shape[1] != fb.obs_1.shape[2]):
        raise ValueError(
            f"use_replay needs replay obs [R, {fb.obs_1.shape[2]}], got {None if replay is None else replay.obs.shape}"
        )
    obs, act, next_obs = _transitions(fb)
    discount = jnp.full((obs.shape[0],), gamma, jnp.float32)
    if use_replay:
        obs = jnp.concatenate([obs, replay.obs])
        act = jnp.concatenate([act, replay.act])
        next_obs = jnp.concatenate([next_obs, replay.next_obs])
        discount = jnp.concatenate([discount, gamma * replay.mask])
    return obs, act, next_obs, discount


def _critic_objective(
    q: jax.Array,
    discount: jax.Array,
    next_v: jax.Array,
    split: Callable,
    label: jax.Array,
    segments: tuple[int, int],
    ipl_cfg: IPLConfig,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """``L_pref + L_chi2`` of the critics' outputs ``q [n_critics, N]`` (module docstring, step 2),
    with the implicit reward ``q - discount * next_v``; ``segments = (B, S - 1)``."""
    reward = q - discount * next_v
    r_1, r_2, r_replay = split(reward)
    r_1 = r_1.reshape(-1, *segments)  # shape is (n_critics, B, S - 1)
    r_2 = r_2.reshape(-1, *segments)
    pref = preference_loss(r_1, r_2, label)
    chi2 = chi2_loss(r_1, r_2, r_replay, ipl_cfg.chi2_coeff, ipl_cfg.chi2_replay_weight)
    logits = (r_2.sum(axis=-1) - r_1.sum(axis=-1)).mean(axis=0)
    info = {
        "ipl/pref_loss": pref,
        "ipl/chi2_loss": chi2,
        "ipl/critic_loss": pref + chi2,
        "ipl/pref_acc": _accuracy(logits, label),
        "ipl/q_mean": q.mean(),
        "ipl/reward_mean": reward.mean(),
        "ipl/reward_std": reward.std(),
        "ipl/reward_feedback_mean": 0.5 * (r_1.mean() + r_2.mean()),
    }
    if r_replay is not None:
        info["ipl/reward_replay_mean"] = r_replay.mean()
    return pref + chi2, info


def update(
    state: IQLState,
    fb: FeedbackPairs,
    replay: Transitions | None,
    iql_cfg: IQLConfig,
    ipl_cfg: IPLConfig,
    dropout_key: jax.Array | None = None,
) -> tuple[IQLState, dict[str, jax.Array]]:
    """One IPL-IQL update (value, critics, actor, target), pure.

    Args:
      state: current state.
      fb: ``B`` pairs already cut to their window, ``obs_* [B, S, obs_dim]``, ``label [B]``.
      replay: a minibatch ``obs [R, obs_dim]`` ... (``rew`` unused); may be ``None`` without replay.
      iql_cfg, ipl_cfg: hyperparameters (static); dropout_key: the actor's dropout masks' key.

    Returns:
      ``(new_state, metrics)`` with scalar metrics named ``ipl/...``.
    """
    use_replay = ipl_cfg.use_replay
    b, s = fb.obs_1.shape[:2]
    n_fb = b * (s - 1)  # transitions per segment side
    gamma = iql_cfg.discount
    obs, act, next_obs, discount = _update_rows(fb, replay, gamma, use_replay)
    n = obs.shape[0]

    def split(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array | None]:
        """Last axis -> (segment 1, segment 2, replay or None)."""
        return x[..., :n_fb], x[..., n_fb : 2 * n_fb], x[..., 2 * n_fb :] if use_replay else None

    # Target critics once: the value loss and the actor's advantages both use min_i Qbar_i(s, a).
    target_q = jnp.min(state.critic.apply_fn(state.target_critic_params, obs, act), axis=0)

    def value_loss_fn(params: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
        v = state.value.apply_fn(params, obs)
        loss = mix(*split(iql.expectile_loss(target_q - v, iql_cfg.expectile)), ipl_cfg.value_replay_weight)
        return loss, {"ipl/value_loss": loss, "ipl/v_mean": v.mean()}

    value_grads, value_info = jax.grad(value_loss_fn, has_aux=True)(state.value.params)
    value = state.value.apply_gradients(grads=value_grads)

    # V' on [s; s'] in one pass: V'(s) for the advantages, V'(s') for the implicit reward.
    v_both = value.apply_fn(value.params, jnp.concatenate([obs, next_obs]))
    v_new, next_v = v_both[:n], v_both[n:]
    clip_frac = jnp.zeros(())
    if ipl_cfg.target_clipping and ipl_cfg.chi2_coeff > 0:
        bound = target_clip_bound(gamma, ipl_cfg.chi2_coeff)
        clip_frac = jnp.mean(jnp.abs(next_v) > bound)
        next_v = jnp.clip(next_v, -bound, bound)

    def critic_loss_fn(params: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
        q = state.critic.apply_fn(params, obs, act)  # shape is (n_critics, N)
        return _critic_objective(q, discount, next_v, split, fb.label, (b, s - 1), ipl_cfg)

    critic_grads, critic_info = jax.grad(critic_loss_fn, has_aux=True)(state.critic.params)
    critic = state.critic.apply_gradients(grads=critic_grads)

    adv = target_q - v_new
    weights = iql.awr_weights(adv, iql_cfg.temperature)

    def actor_loss_fn(params: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
        mean, log_std = iql.apply_actor(iql_cfg, state.actor, params, obs, dropout_key)
        nll = -weights * iql.actor_log_prob(iql_cfg, mean, log_std, act)
        loss = mix(*split(nll), ipl_cfg.policy_replay_weight)
        return loss, {"ipl/actor_loss": loss, "ipl/log_std_mean": log_std.mean()}

    actor_grads, actor_info = jax.grad(actor_loss_fn, has_aux=True)(state.actor.params)
    actor = state.actor.apply_gradients(grads=actor_grads)
    target_params = optax.incremental_update(critic.params, state.target_critic_params, iql_cfg.tau)

    metrics = {
        **value_info,
        **critic_info,
        **actor_info,
        "ipl/adv_mean": adv.mean(),
        "ipl/awr_weight_mean": weights.mean(),
        "ipl/awr_clip_frac": jnp.mean(weights >= iql.AWR_WEIGHT_MAX),
        "ipl/next_v_clip_frac": clip_frac,
    }
    return IQLState(actor, critic, value, target_params, state.step + 1), metrics


def sample_feedback(key: jax.Array, feedback: FeedbackPairs, ipl_cfg: IPLConfig) -> FeedbackPairs:
    """``feedback_batch`` pairs cut to one random window of ``min(subsample, T)`` steps.

    Pairs are distinct when there are at least ``feedback_batch`` of them; the window start is
    uniform in ``0..T - S`` and shared by the whole minibatch (as in the reference).
    """
    pair_key, window_key = jax.random.split(key)
    q, t = feedback.obs_1.shape[:2]
    window = min(ipl_cfg.subsample, t)
    idx = jax.random.choice(pair_key, q, (ipl_cfg.feedback_batch,), replace=q < ipl_cfg.feedback_batch)
    start = jax.random.randint(window_key, (), 0, t - window + 1)

    def cut(x: jax.Array) -> jax.Array:
        x = x[idx]
        return x if x.ndim == 1 else jax.lax.dynamic_slice_in_dim(x, start, window, axis=1)

    return jax.tree.map(cut, feedback)


# --------------------------------------------------------------------------- training
def sampled_update(iql_cfg: IQLConfig, ipl_cfg: IPLConfig) -> Callable[..., tuple[IQLState, dict]]:
    """``update(state, replay_data, feedback, key)``: :func:`update` on a feedback minibatch
    (:func:`sample_feedback`) and, with replay, ``iql_cfg.batch_size`` dataset rows, both drawn from
    ``fold_in(key, state.step)``."""

    def step(
        state: IQLState, replay_data: Any, feedback: FeedbackPairs, key: jax.Array
    ) -> tuple[IQLState, dict[str, jax.Array]]:
        if ipl_cfg.use_replay and replay_data is None:
            raise SpotError("ipl.use_replay is on but no replay data was given")
        step_key = jax.random.fold_in(key, state.step)
        fb_key, replay_key = jax.random.split(step_key)
        dropout_key = jax.random.fold_in(step_key, 1) if iql_cfg.actor_dropout > 0 else None
        replay = None
        if ipl_cfg.use_replay:
            idx = jax.random.randint(replay_key, (iql_cfg.batch_size,), 0, padding.count(replay_data))
            replay = padding.take(replay_data, idx)
        return update(state, sample_feedback(fb_key, feedback, ipl_cfg), replay, iql_cfg, ipl_cfg, dropout_key)

    return step


@functools.lru_cache(maxsize=16)
def make_train_chunk(iql_cfg: IQLConfig, ipl_cfg: IPLConfig) -> Callable[..., tuple[IQLState, dict]]:
    """Jitted ``train_chunk(state, n, replay_data, feedback, key) -> (state, metrics)``.

    Runs ``n <= iql_cfg.chunk`` updates of :func:`sampled_update`, so one key can serve a whole run.
    ``replay_data`` is the whole dataset as :class:`iql.Transitions`, or :class:`spot.padding.Rows`
    of them (one program for every dataset of a bucket; ``None`` allowed when ``use_replay`` is
    off), ``feedback`` all training pairs. Metrics are means over the ``n``
    updates (:func:`spot.loop.make_chunk`, ``"mean"``). ``state`` is donated. Kept per config.
    """
    return loop.make_chunk(sampled_update(iql_cfg, ipl_cfg), iql_cfg.chunk, "mean")


@functools.partial(jax.jit, static_argnames=("iql_cfg", "ipl_cfg"))
def implied_reward(
    state: IQLState, obs: jax.Array, act: jax.Array, next_obs: jax.Array, iql_cfg: IQLConfig, ipl_cfg: IPLConfig
) -> jax.Array:
    """Implicit reward ``mean_i Q_i(s, a) - gamma V(s')`` (``V`` clipped as in training, no
    terminal), shape ``[...]`` for inputs ``[..., dim]``."""
    q = state.critic.apply_fn(state.critic.params, obs, act).mean(axis=0)
    next_v = state.value.apply_fn(state.value.params, next_obs)
    if ipl_cfg.target_clipping and ipl_cfg.chi2_coeff > 0:
        bound = target_clip_bound(iql_cfg.discount, ipl_cfg.chi2_coeff)
        next_v = jnp.clip(next_v, -bound, bound)
    return q - iql_cfg.discount * next_v


def segment_returns(
    state: IQLState, feedback: FeedbackPairs, iql_cfg: IQLConfig, ipl_cfg: IPLConfig
) -> tuple[jax.Array, jax.Array]:
    """Implicit returns ``sum_t r(s_t, a_t, s_{t+1})`` of whole segments, ``([Q], [Q])``."""

    def ret(obs: jax.Array, act: jax.Array) -> jax.Array:
        return implied_reward(state, obs[:, :-1], act[:, :-1], obs[:, 1:], iql_cfg, ipl_cfg).sum(axis=-1)

    return ret(feedback.obs_1, feedback.act_1), ret(feedback.obs_2, feedback.act_2)


def evaluate_preferences(
    state: IQLState, feedback: FeedbackPairs, iql_cfg: IQLConfig, ipl_cfg: IPLConfig
) -> dict[str, float]:
    """Held-out ``ipl/eval_pref_loss`` and ``ipl/eval_pref_acc`` (non-tie pairs) on whole
    segments, from the ensemble-mean implicit reward."""
    ret_1, ret_2 = segment_returns(state, feedback, iql_cfg, ipl_cfg)
    logits = ret_2 - ret_1
    loss = optax.sigmoid_binary_cross_entropy(logits, feedback.label).mean()
    return {"ipl/eval_pref_loss": float(loss), "ipl/eval_pref_acc": float(_accuracy(logits, feedback.label))}


def train_ipl(
    key: jax.Array,
    data: Transitions | None,
    feedback: FeedbackPairs,
    iql_cfg: IQLConfig,
    ipl_cfg: IPLConfig,
    on_chunk: Callable[[int, IQLState, dict], Any] | None = None,
) -> tuple[IQLState, list[dict[str, float]]]:
    """Train IPL for exactly ``iql_cfg.steps`` updates in chunks of ``iql_cfg.chunk``.

    Args:
      key: PRNG key of the IPL stage (split into init and train keys).
      data: replay transitions (``None`` when ``ipl_cfg.use_replay`` is off).
      feedback: training pairs (:func:`feedback_from`).
      on_chunk: called as ``on_chunk(steps_done, state, chunk_metrics)`` after each chunk (do not
        keep ``state``: the next chunk donates it).

    Returns:
      ``(state, history)``, one row of chunk-mean metrics (and ``step``) per chunk. Raises
      :class:`spot.NonFiniteError` on a non-finite loss.
    """
    init_key, train_key = jax.random.split(key)
    state = init_state(init_key, feedback.obs_1.shape[-1], feedback.act_1.shape[-1], iql_cfg)
    callback = None if on_chunk is None else (lambda row, st: on_chunk(row["step"], st, row))
    out = loop.run(
        make_train_chunk(iql_cfg, ipl_cfg),
        state,
        (data, feedback, train_key),
        steps=iql_cfg.steps,
        length=iql_cfg.chunk,
        on_chunk=callback,
    )
    return out.state, out.rows
