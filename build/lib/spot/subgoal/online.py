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
* :func:`subgoal_mask`: the filter of eq. 5-6 with the same groups, quantiles (linear, per
  segment), reward criterion and ``subgoal.last_step`` as :func:`spot.subgoal.extract.subgoal_mask`
  (float32 here, float64 there: a weight equal to a threshold in the last bits may fall either way);
* :func:`triplet_steps`: ``subgoal.triplets=interval``: one uniform draw from every non-empty
  interval ``[g_(i-1), g_i)`` (``g_0 = 0``) paired with ``g_i``, redrawn at every step (the authors'
  one draw per interval; ``subgoal.interval_draws`` sizes the offline fixed set only);
  ``next_subgoal``: every step paired with the first subgoal at or after it.

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
from spot.subgoal import cvae
from spot.subgoal.extract import Triplets


def step_scores(r_hat: jax.Array, attn: jax.Array, weight: str, filter_on: str) -> tuple[jax.Array, jax.Array]:
    """``(w [Q, T], r [Q, T])`` from ``r_hat [Q, T]`` and ``attn [Q, T, T]`` (``attn[q, t, j] = A_tj``):
    ``column_mean`` ``w_j = mean_t A_tj`` or ``diagonal`` ``w_t = A_tt``; ``r_hat`` or ``z_t = Σ_j A_tj r̂_j``."""
    w = attn.mean(axis=1) if weight == "column_mean" else jnp.diagonal(attn, axis1=1, axis2=2)
    r = r_hat if filter_on == "r_hat" else jnp.einsum("qtj,qj->qt", attn, r_hat)
    return w, r


def subgoal_mask(w: jax.Array, r: jax.Array, cfg: SubgoalConfig) -> jax.Array:
    """``[Q, T]`` bool: eq. 5-6 as :func:`spot.subgoal.extract.subgoal_mask` (its docstring has the groups)."""
    k = cfg.top_k / 100.0

    def q(level: float) -> jax.Array:
        return jnp.quantile(w, float(np.clip(level, 0.0, 1.0)), axis=1, keepdims=True)

    if cfg.group == "top":
        mask = w >= q(1 - k)
    elif cfg.group == "top_next":
        mask = (w >= q(1 - 2 * k)) & (w < q(1 - k))
    elif cfg.group == "bottom_next":
        mask = (w > q(k)) & (w <= q(2 * k))
    else:
        mask = w <= q(k)
    if cfg.reward_filter and (cfg.group == "top" or cfg.filter_groups == "all"):
        mask = mask & (r >= r.mean(axis=1, keepdims=True))
    if cfg.last_step:
        mask = mask.at[:, -1].set(True)
    return mask


def triplet_steps(mask: jax.Array, mode: str, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(step, goal, ok)``, each ``[Q, T]``: at position ``t`` of row ``q`` a triplet
    ``(s_step, a_step, g_goal)`` exists where ``ok``. ``interval``: one per subgoal step ``t`` whose
    interval ``[previous subgoal or 0, t)`` is not empty, its step drawn uniformly from the interval
    (``key``); ``next_subgoal``: one per step ``t`` with a subgoal at or after it."""
    length = mask.shape[1]
    t = jnp.broadcast_to(jnp.arange(length), mask.shape)
    if mode == "next_subgoal":
        nxt = jax.lax.cummin(jnp.where(mask, t, length), axis=1, reverse=True)
        return t, jnp.minimum(nxt, length - 1), nxt < length
    last = jax.lax.cummax(jnp.where(mask, t, -1), axis=1)  # the last subgoal at or before t
    prev = jnp.maximum(jnp.concatenate([jnp.full_like(last[:, :1], -1), last[:, :-1]], axis=1), 0)
    ok = mask & (t > prev)
    u = jax.random.uniform(key, mask.shape)
    step = jnp.minimum(prev + jnp.floor(u * (t - prev)).astype(t.dtype), jnp.maximum(t - 1, 0))
    return step, t, ok


def minibatch_triplets(fp: Any, cfg: SubgoalConfig, key: jax.Array, goal_actions: bool) -> tuple[Triplets, jax.Array]:
    """The triplets of one training minibatch as a fixed batch and its 0/1 weight ``[Q·T]``.

    ``fp``: the reward trainer's forward pass (:class:`spot.reward.train.ForwardPass`: ``obs_1``,
    ``act_1``, ``r_hat_1``, ``attn_1``, the same for side 2, ``label [Q]``, 1 = segment 2 preferred).
    """
    w1, r1 = step_scores(fp.r_hat_1, fp.attn_1, cfg.weight, cfg.filter_on)
    w2, r2 = step_scores(fp.r_hat_2, fp.attn_2, cfg.weight, cfg.filter_on)
    second = (fp.label > 0.5)[:, None]  # segment 2 preferred
    valid = fp.label != 0.5  # a tie selects no segment
    obs = jnp.where(second[..., None], fp.obs_2, fp.obs_1)
    act = jnp.where(second[..., None], fp.act_2, fp.act_1)
    mask = subgoal_mask(jnp.where(second, w2, w1), jnp.where(second, r2, r1), cfg) & valid[:, None]
    step, goal, ok = triplet_steps(mask, cfg.triplets, key)

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
