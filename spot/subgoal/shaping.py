"""Subgoal-guided reward shaping (SPOT paper, §4.2, eq. 10-13; Table 3's three variants).

For every transition ``(s, a, s')`` the CVAE proposes ``ĝ = G(s, a)`` (eq. 10) and a shaping
term measures how ``s'`` relates to it:

* ``cosine`` (eq. 11-12, SPOT's choice): ``r_shape = (cos(s', ĝ) + 1) / 2 ∈ [0, 1]``, with
  ``cos(x, y) = x·y / max(||x|| ||y||, 1e-8)`` so a zero state gives ``r_shape = ½``;
* ``neg_distance``: ``r_shape = -||s' - ĝ||``;
* ``constant`` (a control, not in the paper): every transition gets the mean of the ``cosine``
  term over the dataset, a bonus of the same size that carries no information about subgoals. On
  Hopper and Walker2d a positive per-step bonus alone rewards staying alive, so SPOT beating this
  control is what shows the subgoals matter;
* ``potential`` (Ng et al., 1999): ``r_shape = γ Φ(s') - Φ(s)`` with ``Φ(x) = -||x - ĝ||``. Both
  potentials use the *same* ``ĝ = G(s, a)`` (the CVAE has no ``a'`` for ``s'``), so the term
  telescopes only while ĝ stays put; Φ(s') is set to 0 at terminal transitions (absorbing state)
  when ``terminals`` are given (``shaping.potential_terminal``). The paper does not define Φ; the
  authors' code uses ``Φ(x) = +||x - ĝ||`` without the terminal mask
  (``shaping.potential_sign=pos``, ``shaping.potential_terminal=false``), so the λ axis of their
  Table 3 is the negative of the ``neg`` sign's; ``sweeps/paper/table3_shaping.yaml`` uses theirs.

* ``shaping.state_action`` (the authors' ``state_action`` option, SGPbrl ``critic.py``
  ``update_q``): the CVAE decodes a subgoal state *and* action, ``(ĝ_s, ĝ_a) = G(s, a)``, and the
  cosine term reads the *current* state and action,
  ``r_shape = (cos(s, ĝ_s) + 1) / 2 + (cos(a, ĝ_a) + 1) / 2 ∈ [0, 2]``
  (:func:`state_action_cosine`; ``constant`` is then the dataset mean of this term).

All distances and cosines are taken on raw states, as eq. 11 writes them.

The final reward (eq. 13) is ``r_final = r_model + λ · r_shape``.

Where normalisation sits: ``r_model`` is the reward model's output *after* the relabelling
stage's normalisation (PT repo: ``r · 1000 / (R_max - R_min) + 0.5`` for locomotion), and the
shaping term is added afterwards, unnormalised. So ``λ = 1`` puts a ``[0, 1]`` cosine bonus beside
a model reward on its usual IQL scale, which is how eq. 13 reads (the paper says ``r_shape`` is
kept in ``[0, 1]`` "for a consistent scale for reward combination"). Normalising after shaping
would instead rescale the bonus by the return range of the shaped rewards.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from spot import SpotError
from spot.config import ShapingConfig
from spot.subgoal.cvae import CVAEParams, generate, split_goal
from spot.subgoal.cvae_loss import cosine_similarity

KINDS = ("none", "cosine", "neg_distance", "potential", "constant")
POTENTIAL_SIGNS = ("neg", "pos")


class ShapedRewards(NamedTuple):
    """Per-transition outputs of :func:`shaped_rewards`, all ``[N]`` float32.

    Attributes:
      reward: ``r_final = r_model + λ r_shape`` (eq. 13).
      shape: ``r_shape`` (zeros for ``kind="none"``).
      cos_to_subgoal: ``cos(s, ĝ)`` of the *current* state and its subgoal, the proximity axis
        of the extrapolation-error analysis (§5.3, Fig. 2).
    """

    reward: np.ndarray
    shape: np.ndarray
    cos_to_subgoal: np.ndarray


def shape_reward(
    kind: str,
    next_obs: jax.Array,
    g_hat: jax.Array,
    obs: jax.Array | None = None,
    gamma: float = 0.99,
    terminals: jax.Array | None = None,
    potential_sign: str = "neg",
) -> jax.Array:
    """Shaping term ``r_shape [N]`` for raw ``next_obs [N, o]`` and subgoals ``g_hat [N, o]``.

    Args:
      kind: ``none`` | ``cosine`` | ``neg_distance`` | ``potential`` (module docstring).
      next_obs: ``s'``.
      g_hat: ``ĝ = G(s, a)``.
      obs: ``s``; required for ``potential``.
      gamma: discount of the potential-based term.
      terminals: optional ``[N]`` bool; ``Φ(s') = 0`` where set (``potential`` only).
      potential_sign: ``neg``: ``Φ(x) = -||x - ĝ||``; ``pos``: ``Φ(x) = +||x - ĝ||`` (the
        authors' code; the same term as ``neg`` at ``-λ`` where no terminal is masked).
    """
    if kind not in KINDS:
        raise SpotError(f"shaping kind {kind!r}; expected one of {KINDS}")
    if next_obs.shape != g_hat.shape:
        raise SpotError(f"next_obs {next_obs.shape} and g_hat {g_hat.shape} must have the same shape")
    if kind == "none":
        return jnp.zeros(next_obs.shape[:-1])
    if kind in ("cosine", "constant"):
        cos = 0.5 * (cosine_similarity(next_obs, g_hat) + 1.0)
        return cos if kind == "cosine" else jnp.full_like(cos, cos.mean())
    if kind == "neg_distance":
        return -jnp.linalg.norm(next_obs - g_hat, axis=-1)
    if obs is None:
        raise SpotError("potential-based shaping needs obs (s) as well as next_obs (s')")
    if potential_sign not in POTENTIAL_SIGNS:
        raise SpotError(f"potential_sign {potential_sign!r}; expected one of {POTENTIAL_SIGNS}")
    sign = -1.0 if potential_sign == "neg" else 1.0
    phi_next = sign * jnp.linalg.norm(next_obs - g_hat, axis=-1)
    if terminals is not None:
        phi_next = jnp.where(jnp.asarray(terminals, bool), 0.0, phi_next)
    phi = sign * jnp.linalg.norm(obs - g_hat, axis=-1)
    return gamma * phi_next - phi


def state_action_cosine(obs: jax.Array, act: jax.Array, g_state: jax.Array, g_action: jax.Array) -> jax.Array:
    """``(cos(s, ĝ_s) + 1) / 2 + (cos(a, ĝ_a) + 1) / 2`` per row, ``[N]`` in ``[0, 2]``: the
    state+action cosine term of the authors' code, on the current ``s [N, o]`` and ``a [N, a]``."""
    if obs.shape != g_state.shape or act.shape != g_action.shape:
        raise SpotError(
            f"obs {obs.shape} / g_state {g_state.shape} and act {act.shape} / g_action {g_action.shape} must match"
        )
    return 0.5 * (cosine_similarity(obs, g_state) + 1.0) + 0.5 * (cosine_similarity(act, g_action) + 1.0)


def final_reward(r_model: jax.Array, r_shape: jax.Array, weight: float) -> jax.Array:
    """Eq. 13: ``r_model + λ · r_shape``."""
    return r_model + weight * r_shape


def shaped_rewards(
    cvae_params: CVAEParams,
    ds_obs: np.ndarray,
    ds_act: np.ndarray,
    ds_next_obs: np.ndarray,
    r_model_normalised: np.ndarray,
    cfg: ShapingConfig,
    key: jax.Array,
    *,
    gamma: float = 0.99,
    terminals: np.ndarray | None = None,
    batch_size: int = 4096,
) -> tuple[ShapedRewards, dict[str, float]]:
    """Relabel a whole dataset with eq. 13 (subgoals generated in fixed-size jitted batches).

    Args:
      cvae_params: trained CVAE.
      ds_obs, ds_act, ds_next_obs: raw ``[N, o]``, ``[N, a]``, ``[N, o]``.
      r_model_normalised: ``[N]`` reward-model output, already normalised (module docstring).
      cfg: shaping kind, weight λ and subgoal mode (prior mean or sample).
      key: used for ``cfg.subgoal = "sample"``.
      gamma: discount of the potential-based term (pass the policy's discount).
      terminals: ``[N]`` true terminations, for the potential-based term.
      batch_size: rows per jitted CVAE call.

    Returns:
      ``(ShapedRewards, info)`` with ``shaping/*`` summary statistics for logging.
    """
    n = ds_obs.shape[0]
    if not (ds_act.shape[0] == n and ds_next_obs.shape == ds_obs.shape and np.shape(r_model_normalised) == (n,)):
        raise SpotError(
            f"dataset arrays disagree: obs {ds_obs.shape}, act {ds_act.shape}, next_obs "
            f"{ds_next_obs.shape}, r_model {np.shape(r_model_normalised)}"
        )
    goals = generate(cvae_params, ds_obs, ds_act, key=key, mode=cfg.subgoal, batch_size=batch_size, with_actions=True)
    g_hat, g_act = split_goal(cvae_params, goals)
    obs, next_obs = np.asarray(ds_obs, np.float32), np.asarray(ds_next_obs, np.float32)
    if cfg.state_action != (g_act is not None):
        raise SpotError(
            f"shaping.state_action={cfg.state_action} needs a CVAE that decodes "
            f"{'a state and an action' if cfg.state_action else 'a state'}; this one decodes "
            f"{'both' if g_act is not None else 'a state'}"
        )
    if cfg.state_action and cfg.kind in ("cosine", "constant"):
        r_shape = np.asarray(state_action_cosine(obs, np.asarray(ds_act, np.float32), g_hat, g_act), np.float32)
        r_shape = r_shape if cfg.kind == "cosine" else np.full_like(r_shape, r_shape.mean())
    else:
        masked = terminals if cfg.potential_terminal else None
        r_shape = np.asarray(
            shape_reward(cfg.kind, next_obs, g_hat, obs, gamma, masked, cfg.potential_sign), np.float32
        )
    r_model = np.asarray(r_model_normalised, np.float32)
    reward = np.asarray(final_reward(r_model, r_shape, cfg.weight), np.float32)
    cos_s = np.asarray(cosine_similarity(obs, g_hat), np.float32)
    info = {
        "shaping/r_shape_mean": float(r_shape.mean()),
        "shaping/r_shape_std": float(r_shape.std()),
        "shaping/r_shape_min": float(r_shape.min()),
        "shaping/r_shape_max": float(r_shape.max()),
        "shaping/r_model_mean": float(r_model.mean()),
        "shaping/r_model_std": float(r_model.std()),
        "shaping/r_final_mean": float(reward.mean()),
        "shaping/r_final_std": float(reward.std()),
        "shaping/cos_to_subgoal_mean": float(cos_s.mean()),
    }
    return ShapedRewards(reward=reward, shape=r_shape, cos_to_subgoal=cos_s), info
