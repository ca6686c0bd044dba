"""The online CVAE (``cvae.schedule=online``): one CVAE step per reward-model step, on the subgoal
triplets of that step's minibatch (the authors' code, SGPbrl a5b03df ``JaxPref/PrefTransformer.py``
``train``: ``_train_pref_step``, then ``extract_and_accumulate_subgoals`` on the same batch, then
one ``vae_train_step`` on all of that batch's triplets).

The reward-model trainer (:func:`spot.reward.train.train_reward_model`, ``companion=``) calls an
:class:`OnlineCVAE` after every update with the training forward pass it just took: the
minibatch's segments, PT's per-step rewards ``r̂`` and preference attention ``A`` of both sides,
computed with dropout on and the parameters before the update (as the authors read
``importance_weight`` and ``trans_pred`` from their training step). From them, inside jit:

* :func:`step_scores`: ``w_t`` and the value the reward filter reads (``subgoal.weight``,
  ``subgoal.filter_on``), as :func:`spot.subgoal.extract.step_scores`;
* the preferred segment of every non-tied query (a tie selects none, as offline);
* :func:`subgoal_selection`: the filter of eq. 5-6 with the same groups, quantiles (linear, per
  segment) or the authors' rank thresholds (``subgoal.selection``), reward criterion and
  ``subgoal.last_step`` as :func:`spot.subgoal.extract.subgoal_selection`, and each segment's
  first step (float32 here, float64 there: a weight equal to a quantile in the last bits may fall
  either way; rank thresholds are weights themselves and select the same steps);
* :func:`triplet_steps`: ``subgoal.triplets=interval``: one uniform draw from every non-empty
  interval ``[g_(i-1), g_i)`` (``g_0`` = the segment's first step: 0, or under the authors'
  selection its first subgoal when the group selected all its steps) paired with ``g_i``, redrawn
  at every step (the authors' one draw per interval; ``subgoal.interval_draws`` sizes the offline
  fixed set only); ``next_subgoal``: every step from the first on paired with the first subgoal
  at or after it.

The triplets of one minibatch vary in number, so they are a fixed ``[P·T]`` batch with a 0/1
weight, and :func:`spot.subgoal.cvae.loss_fn` averages over the rows of weight 1: the loss of the
authors' batch of exactly those triplets (their padded subgoal list's spurious triplets aside:
docs/fidelity.md row 27). A minibatch with no triplet (all ties) takes no step. ``cvae.steps``
and ``cvae.batch_size`` do not apply: the CVAE takes as many steps as the reward model, and each
step's batch is its minibatch's triplets. The CVAE after the reward model's last step is the one
used (the authors save it every 1000 steps; at 10 000 steps the last save is the last step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from spot.config import CVAEConfig, SubgoalConfig
from spot.subgoal import cvae, extract
from spot.subgoal.extract import Triplets


def step_scores(r_hat: jax.Array, attn: jax.Array, weight: str, filter_on: str) -> tuple[jax.Array, jax.Array]:
    """``(w [Q, T], r [Q, T])`` from ``r_hat [Q, T]`` and ``attn [Q, T, T]`` (``attn[q, t, j] = A_tj``):
    ``column_mean`` ``w_j = mean_t A_tj`` or ``diagonal`` ``w_t = A_tt``; ``r_hat`` or ``z_t = Σ_j A_tj r̂_j``."""
    w = attn.mean(axis=1) if weight == "column_mean" else jnp.diagonal(attn, axis1=1, axis2=2)
    r = r_hat if filter_on == "r_hat" else jnp.einsum("qtj,qj->qt", attn, r_hat)
    return w, r


def subgoal_mask(w: jax.Array, r: jax.Array, cfg: SubgoalConfig) -> jax.Array:
    """``[Q, T]`` bool: eq. 5-6 as :func:`spot.subgoal.extract.subgoal_mask` (its docstring has the groups)."""
    return subgoal_selection(w, r, cfg)[0]


def subgoal_selection(w: jax.Array, r: jax.Array, cfg: SubgoalConfig) -> tuple[jax.Array, jax.Array]:
    """``(mask [Q, T] bool, start [Q] int)`` as :func:`spot.subgoal.extract.subgoal_selection`."""
    reward_ok = r >= r.mean(axis=1, keepdims=True)
    use_reward = cfg.reward_filter and (cfg.group == "top" or cfg.filter_groups == "all")
    length = w.shape[1]
    if cfg.selection == "authors":
        passing, size = _rank_group(w, cfg.top_k, cfg.group)
        if use_reward:
            passing = passing & reward_ok
        mask = passing & (jnp.cumsum(passing, axis=1) <= size)  # the first `size` in time
        padded = passing.sum(axis=1) < size
    else:
        mask = _quantile_group(w, cfg.top_k, cfg.group)
        if use_reward:
            mask = mask & reward_ok
    if cfg.last_step:
        mask = mask.at[:, -1].set(True)
    if cfg.selection != "authors":
        return mask, jnp.zeros(w.shape[0], jnp.int32)
    first = jnp.where(mask.any(axis=1), jnp.argmax(mask, axis=1), length)
    return mask, jnp.where(padded, 0, first).astype(jnp.int32)


def _quantile_group(w: jax.Array, top_k: float, group: str) -> jax.Array:
    k = top_k / 100.0

    def q(level: float) -> jax.Array:
        return jnp.quantile(w, float(np.clip(level, 0.0, 1.0)), axis=1, keepdims=True)

    if group == "top":
        return w >= q(1 - k)
    if group == "top_next":
        return (w >= q(1 - 2 * k)) & (w < q(1 - k))
    if group == "bottom_next":
        return (w > q(k)) & (w <= q(2 * k))
    return w <= q(k)


def _rank_group(w: jax.Array, top_k: float, group: str) -> tuple[jax.Array, int]:
    """The authors' rank thresholds (:func:`spot.subgoal.extract.rank_thresholds`)."""
    length = w.shape[1]
    s = jnp.sort(w, axis=1)
    lo, hi, strict = extract.rank_thresholds(top_k, group)
    ok = jnp.ones(w.shape, bool)
    if lo is not None:
        i = extract.rank_index(length, lo)
        ok = ok & (w > s[:, i : i + 1] if strict == "lower" else w >= s[:, i : i + 1])
    if hi is not None:
        i = extract.rank_index(length, hi)
        ok = ok & (w < s[:, i : i + 1] if strict == "upper" else w <= s[:, i : i + 1])
    return ok, extract.rank_size(length, top_k, group)


def triplet_steps(
    mask: jax.Array, mode: str, key: jax.Array, start: jax.Array | None = None
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(step, goal, ok)``, each ``[Q, T]``: at position ``t`` of row ``q`` a triplet
    ``(s_step, a_step, g_goal)`` exists where ``ok``. ``interval``: one per subgoal step ``t`` whose
    interval ``[previous subgoal or the row's start, t)`` is not empty, its step drawn uniformly
    from the interval (``key``); ``next_subgoal``: one per step ``t >= start`` with a subgoal at or
    after it. ``start [Q]``: each row's first step (default 0)."""
    length = mask.shape[1]
    t = jnp.broadcast_to(jnp.arange(length), mask.shape)
    first = jnp.zeros((mask.shape[0], 1), t.dtype) if start is None else start.astype(t.dtype)[:, None]
    if mode == "next_subgoal":
        nxt = jax.lax.cummin(jnp.where(mask, t, length), axis=1, reverse=True)
        return t, jnp.minimum(nxt, length - 1), (nxt < length) & (t >= first)
    last = jax.lax.cummax(jnp.where(mask, t, -1), axis=1)  # the last subgoal at or before t
    before = jnp.concatenate([jnp.full_like(last[:, :1], -1), last[:, :-1]], axis=1)
    prev = jnp.where(before < 0, first, before)
    ok = mask & (t > prev)
    u = jax.random.uniform(key, mask.shape)
    step = jnp.minimum(prev + jnp.floor(u * (t - prev)).astype(t.dtype), jnp.maximum(t - 1, 0))
    return step, t, ok


def minibatch_triplets(fp: Any, cfg: SubgoalConfig, key: jax.Array, goal_actions: bool) -> tuple[Triplets, jax.Array]:
    """The triplets of one training minibatch as a fixed batch and its 0/1 weight ``[Q·T]``.

    ``fp``: the reward trainer's forward pass (:class:`spot.reward.update.ForwardPass`: ``obs_1``,
    ``act_1``, ``r_hat_1``, ``attn_1``, the same for side 2, ``label [Q]``, 1 = segment 2 preferred).
    """
    w1, r1 = step_scores(fp.r_hat_1, fp.attn_1, cfg.weight, cfg.filter_on)
    w2, r2 = step_scores(fp.r_hat_2, fp.attn_2, cfg.weight, cfg.filter_on)
    second = (fp.label > 0.5)[:, None]  # segment 2 preferred
    valid = fp.label != 0.5  # a tie selects no segment
    obs = jnp.where(second[..., None], fp.obs_2, fp.obs_1)
    act = jnp.where(second[..., None], fp.act_2, fp.act_1)
    mask, start = subgoal_selection(jnp.where(second, w2, w1), jnp.where(second, r2, r1), cfg)
    step, goal, ok = triplet_steps(mask & valid[:, None], cfg.triplets, key, start)

    def take(x: jax.Array, idx: jax.Array) -> jax.Array:
        return jnp.take_along_axis(x, idx[..., None], axis=1).reshape(-1, x.shape[-1])

    g = take(obs, goal)
    if goal_actions:
        g = jnp.concatenate([g, take(act, goal)], axis=-1)
    return Triplets(take(obs, step), take(act, step), g), ok.reshape(-1).astype(jnp.float32)


def init_state(
    key: jax.Array, observations: np.ndarray, act_dim: int, cfg: CVAEConfig, goal_actions: bool
) -> cvae.CVAEState:
    """A fresh CVAE for the online schedule (inputs z-scored with the dataset's observation
    statistics, or raw with ``cvae.inputs=raw``, as :func:`spot.subgoal.cvae.train_cvae`)."""
    obs_dim = observations.shape[-1]
    if cfg.inputs == "raw":
        stats = (np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32))
    else:
        stats = cvae.obs_stats(observations)
    return cvae.init(key, obs_dim, act_dim, cfg, stats, goal_actions)


@dataclass(frozen=True)
class OnlineCVAE:
    """``step(state, fp, key) -> (state, metrics)``: one Adam step of the CVAE on the triplets of
    the forward pass ``fp`` (none when it has no triplet). Hashable: the reward trainer keeps its
    compiled programs per companion."""

    subgoal: SubgoalConfig
    cvae: CVAEConfig
    goal_actions: bool = False

    def __call__(self, state: cvae.CVAEState, fp: Any, key: jax.Array) -> tuple[cvae.CVAEState, dict]:
        draw_key, loss_key = jax.random.split(key)
        batch, weight = minibatch_triplets(fp, self.subgoal, draw_key, self.goal_actions)
        opt = cvae._optimizer(self.cvae)  # the optimizer init_state's Adam state belongs to

        def net_loss(net: Any) -> tuple[jax.Array, dict[str, jax.Array]]:
            return cvae.loss_fn(state.params.replace(net=net), batch, loss_key, self.cvae, weight)

        grads, info = jax.grad(net_loss, has_aux=True)(state.params.net)
        updates, opt_state = opt.update(grads, state.opt_state, state.params.net)
        params = state.params.replace(net=optax.apply_updates(state.params.net, updates))
        stepped = cvae.CVAEState(params, opt_state, state.step + 1)
        n = weight.sum()
        state = jax.tree.map(lambda new, old: jnp.where(n > 0, new, old), stepped, state)
        return state, {**info, "cvae/triplets": n}
