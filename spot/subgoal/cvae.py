"""Conditional VAE over subgoals, ``p(g | s, a)`` (SPOT paper, §4.1.3, eq. 7-9, Table 6, Table 7).

Three :class:`spot.nets.MLP` networks (hidden sizes ``cfg.hidden``, Table 6 ``[32, 64, 32]``, ReLU):

* encoder ``q_φ(z | g, s, a)`` and prior ``p_ψ(z | s, a)``: mean and log-std of ``z``
  (``cfg.latent_dim``), log-std clipped to ``[-5, 2]`` (``cvae.log_std_clip``; the authors' CVAE
  leaves its log-variance unclipped);
* decoder ``p_θ(g | z, s, a) = N(μ_θ(z, s, a), I)``: only the mean is learned.

The loss per triplet (eq. 7-9 and the variants of Table 7 and the authors' code) is
:mod:`spot.subgoal.cvae_loss`'s; :func:`loss_fn` runs the networks and adds it up.

Normalisation: ``s`` and ``g`` are z-scored with the dataset's observation mean and std (std
floored at 1e-3), which live in :class:`CVAEParams` next to the network weights. Actions go in
raw (they are bounded in ``[-1, 1]`` in every dataset we use). The decoder outputs a normalised
subgoal and :func:`generate` maps it back, so callers pass and receive raw states.

State and action subgoals (``shaping.state_action``, the authors' ``state_action`` option):
``g = [g_s, g_a]``, the subgoal step's state and action; the decoder outputs both (its state part
normalised, its action part raw), the encoder reads both (the loss of both parts:
:mod:`spot.subgoal.cvae_loss`).

Generation (eq. 10): ``ĝ = μ_θ(z, s, a)`` with ``z`` the prior mean (``mode="mean"``) or a prior
sample (``mode="sample"``).

Training (:func:`train_cvae`, ``cvae.schedule=offline``): Adam (``cfg.lr``), minibatches of
``cfg.batch_size`` triplets drawn with replacement on device, exactly ``cfg.steps`` steps in
:mod:`spot.loop` chunks (state donated, per-step keys ``fold_in(key, step)``), a held-out loss after
every chunk, and :class:`spot.NonFiniteError` on a NaN/inf loss. The final parameters are
returned. ``cvae.schedule=online`` trains it one step per reward-model step instead
(:mod:`spot.subgoal.online`), through :func:`loss_fn` with a per-row weight.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from spot import SpotError, loop, padding
from spot.config import CVAEConfig
from spot.nets import MLP, Params
from spot.subgoal.cvae_loss import loss_terms
from spot.subgoal.extract import Triplets

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
STD_FLOOR = 1e-3


# --------------------------------------------------------------------------- networks
class GaussianMLP(nn.Module):
    """``x -> (mean, log_std)`` of a diagonal Gaussian."""

    hidden: Sequence[int]
    out_dim: int
    clip: bool = True  # log-std clipped to [LOG_STD_MIN, LOG_STD_MAX]

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean, log_std = jnp.split(MLP(self.hidden, 2 * self.out_dim)(x), 2, axis=-1)
        return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX) if self.clip else log_std


class CVAE(nn.Module):
    """Encoder, prior and decoder on normalised states ``s_n``, ``g_n`` and raw actions ``a``; the
    subgoal ``g`` is a state, or a state and an action (``goal_act_dim > 0``: ``[g_s_n, g_a]``)."""

    obs_dim: int
    latent_dim: int
    hidden: Sequence[int]
    goal_act_dim: int = 0
    log_std_clip: bool = True

    def setup(self) -> None:
        self.encoder = GaussianMLP(self.hidden, self.latent_dim, self.log_std_clip)
        self.prior_net = GaussianMLP(self.hidden, self.latent_dim, self.log_std_clip)
        self.decoder = MLP(self.hidden, self.obs_dim + self.goal_act_dim)

    def posterior(self, g_n: jax.Array, s_n: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
        return self.encoder(jnp.concatenate([g_n, s_n, a], axis=-1))

    def prior(self, s_n: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
        return self.prior_net(jnp.concatenate([s_n, a], axis=-1))

    def decode(self, z: jax.Array, s_n: jax.Array, a: jax.Array) -> jax.Array:
        return self.decoder(jnp.concatenate([z, s_n, a], axis=-1))

    def __call__(self, g_n: jax.Array, s_n: jax.Array, a: jax.Array) -> jax.Array:
        """Touches every sub-network (used by ``init``); returns the decoder mean at the posterior mean."""
        q_mean, _ = self.posterior(g_n, s_n, a)
        self.prior(s_n, a)
        return self.decode(q_mean, s_n, a)


class CVAEParams(struct.PyTreeNode):
    """Network weights, the observation statistics, and the (static) architecture.

    ``goal_act_dim``: 0 when the subgoal is a state; the action size when it is a state and an
    action (``shaping.state_action``), the decoded goal then being ``[ĝ_s, ĝ_a]``."""

    net: Params
    obs_mean: jax.Array  # [obs_dim]
    obs_std: jax.Array  # [obs_dim], floored at STD_FLOOR
    hidden: tuple[int, ...] = struct.field(pytree_node=False)
    latent_dim: int = struct.field(pytree_node=False)
    goal_act_dim: int = struct.field(pytree_node=False, default=0)
    log_std_clip: bool = struct.field(pytree_node=False, default=True)

    @property
    def obs_dim(self) -> int:
        return int(self.obs_mean.shape[-1])

    @property
    def module(self) -> CVAE:
        return CVAE(
            obs_dim=self.obs_dim,
            latent_dim=self.latent_dim,
            hidden=self.hidden,
            goal_act_dim=self.goal_act_dim,
            log_std_clip=self.log_std_clip,
        )

    def normalize(self, x: jax.Array) -> jax.Array:
        return (x - self.obs_mean) / self.obs_std

    def denormalize(self, x_n: jax.Array) -> jax.Array:
        return x_n * self.obs_std + self.obs_mean

    def normalize_goal(self, g: jax.Array) -> jax.Array:
        """A goal ``[g_s]`` or ``[g_s, g_a]`` with its state part z-scored (actions stay raw)."""
        if not self.goal_act_dim:
            return self.normalize(g)
        return jnp.concatenate([self.normalize(g[..., : self.obs_dim]), g[..., self.obs_dim :]], axis=-1)

    def denormalize_goal(self, g_n: jax.Array) -> jax.Array:
        if not self.goal_act_dim:
            return self.denormalize(g_n)
        return jnp.concatenate([self.denormalize(g_n[..., : self.obs_dim]), g_n[..., self.obs_dim :]], axis=-1)


class CVAEState(NamedTuple):
    """Training state: the parameters, Adam's state over ``params.net`` and the step counter."""

    params: CVAEParams
    opt_state: optax.OptState
    step: jax.Array  # [] int32, gradient steps taken


def obs_stats(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mean, std)`` of ``obs [N, obs_dim]`` over rows, float32."""
    obs = np.asarray(obs, dtype=np.float64)
    return obs.mean(axis=0).astype(np.float32), obs.std(axis=0).astype(np.float32)


# --------------------------------------------------------------------------- loss
def loss_fn(
    params: CVAEParams, batch: Triplets, key: jax.Array, cfg: CVAEConfig, weight: jax.Array | None = None
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 9 on a batch of raw triplets ``s [B, o]``, ``a [B, a]``, ``g [B, o]`` (or ``[B, o + a]``:
    a state and an action, when ``params.goal_act_dim``).

    ``weight [B]`` (optional, 0 or 1): the loss and metrics average over the rows of weight 1 only
    (the online CVAE's fixed-size batches of a variable number of triplets).

    Returns:
      ``(loss, info)`` with ``cvae/recon``, ``cvae/kl``, ``cvae/cos``, ``cvae/loss`` and
      ``cvae/mse`` (per-dimension MSE in normalised units). ``cvae/cos`` is logged for
      ``cfg.loss = "mse"`` too, but only added to the loss for ``"mse_cos"``. With a state and
      action goal, ``cvae/cos`` is the state part's and the ``mse_cos`` loss adds the action part's
      ``½ (1 - cos(ĝ_a, g_a))`` too (the shaping term reads both, eq. 11 per part).
    """
    s, a, g = batch
    o = params.obs_dim
    assert s.ndim == 2 and g.shape == (s.shape[0], o + params.goal_act_dim) and a.shape[0] == s.shape[0], (
        s.shape,
        a.shape,
        g.shape,
    )
    model = params.module
    s_n, g_n = params.normalize(s), params.normalize_goal(g)
    q_mean, q_log_std = model.apply({"params": params.net}, g_n, s_n, a, method=CVAE.posterior)
    p_mean, p_log_std = model.apply({"params": params.net}, s_n, a, method=CVAE.prior)
    z = q_mean + jnp.exp(q_log_std) * jax.random.normal(key, q_mean.shape)
    g_hat_n = model.apply({"params": params.net}, z, s_n, a, method=CVAE.decode)

    g_hat = params.denormalize_goal(g_hat_n)
    return loss_terms(
        g_n, g_hat_n, g, g_hat, (q_mean, q_log_std), (p_mean, p_log_std), o, params.goal_act_dim, cfg, weight
    )


# --------------------------------------------------------------------------- training
def _optimizer(cfg: CVAEConfig) -> optax.GradientTransformation:
    return optax.adam(cfg.lr)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _init_net(model: CVAE, act_dim: int, key: jax.Array) -> Params:
    zeros_g = jnp.zeros((1, model.obs_dim + model.goal_act_dim))
    zeros_o, zeros_a = jnp.zeros((1, model.obs_dim)), jnp.zeros((1, act_dim))
    return model.init(key, zeros_g, zeros_o, zeros_a)["params"]


def init(
    key: jax.Array,
    obs_dim: int,
    act_dim: int,
    cfg: CVAEConfig,
    stats: tuple[np.ndarray, np.ndarray],
    goal_actions: bool = False,
) -> CVAEState:
    """Fresh CVAE weights and Adam state; ``stats = (obs_mean, obs_std)`` of the dataset;
    ``goal_actions``: the subgoal is a state and an action (``shaping.state_action``)."""
    mean, std = (np.asarray(x, dtype=np.float32) for x in stats)
    if mean.shape != (obs_dim,) or std.shape != (obs_dim,):
        raise SpotError(f"obs_stats have shapes {mean.shape}, {std.shape}; expected ({obs_dim},)")
    goal_act_dim = act_dim if goal_actions else 0
    model = CVAE(
        obs_dim=obs_dim,
        latent_dim=cfg.latent_dim,
        hidden=tuple(cfg.hidden),
        goal_act_dim=goal_act_dim,
        log_std_clip=cfg.log_std_clip,
    )
    net = _init_net(model, act_dim, key)
    params = CVAEParams(
        net=net,
        obs_mean=jnp.asarray(mean),
        obs_std=jnp.maximum(jnp.asarray(std), STD_FLOOR),
        hidden=tuple(cfg.hidden),
        latent_dim=cfg.latent_dim,
        goal_act_dim=goal_act_dim,
        log_std_clip=cfg.log_std_clip,
    )
    return CVAEState(params=params, opt_state=_optimizer(cfg).init(net), step=jnp.zeros((), jnp.int32))


def bucket(m: int) -> int:
    """Rows a set of ``m`` triplets is padded to on device: the next power of two (at least 64).

    The number of triplets depends on the seed and the reward model, so unpadded every run would
    compile its own CVAE programs; padded, runs whose counts fall in one bucket share them (the
    in-process jit cache and the persistent compilation cache) at most doubling the rows held
    (:func:`spot.padding.bucket` with a smaller minimum than a dataset's).
    """
    return padding.bucket(int(m), min_rows=64)


def pad_rows(x: np.ndarray, rows: int) -> np.ndarray:
    """``x`` with zero rows appended up to ``rows`` rows (:func:`spot.padding.pad_rows`)."""
    return padding.pad_rows(x, max(rows, x.shape[0]))


def make_update(cfg: CVAEConfig) -> Callable[..., tuple[CVAEState, dict[str, jax.Array]]]:
    """``update(state, data, count, key) -> (state, info)``: one Adam step on ``cfg.batch_size``
    rows drawn with replacement from the first ``count`` rows of the training triplets ``data``
    (the rest is padding, :func:`bucket`), with ``fold_in(key, state.step)``. The rows drawn are
    those of unpadded data (``randint`` with a traced bound draws what it draws with a static one)."""
    opt = _optimizer(cfg)

    def update(
        state: CVAEState, data: Triplets, count: jax.Array, key: jax.Array
    ) -> tuple[CVAEState, dict[str, jax.Array]]:
        step_key = jax.random.fold_in(key, state.step)
        idx_key, loss_key = jax.random.split(step_key)
        idx = jax.random.randint(idx_key, (cfg.batch_size,), 0, count)
        batch = Triplets(*(x[idx] for x in data))

        def net_loss(net: Params) -> tuple[jax.Array, dict[str, jax.Array]]:
            return loss_fn(state.params.replace(net=net), batch, loss_key, cfg)

        grads, info = jax.grad(net_loss, has_aux=True)(state.params.net)
        updates, opt_state = opt.update(grads, state.opt_state, state.params.net)
        params = state.params.replace(net=optax.apply_updates(state.params.net, updates))
        return CVAEState(params, opt_state, state.step + 1), info

    return update


@functools.lru_cache(maxsize=16)
def make_train_chunk(cfg: CVAEConfig, length: int) -> Callable[..., tuple[CVAEState, dict[str, jax.Array]]]:
    """Jitted ``train_chunk(state, n, data, count, key) -> (state, metrics)``: ``n <= length`` steps of
    :func:`make_update` in one scan (:func:`spot.loop.make_chunk`); ``metrics`` are means over
    the ``n`` steps. The state is donated. Kept per ``(cfg, length)``, so repeated trainings in
    one process (a sweep trial, the tests) reuse the compiled chunk for data of the same shape.
    """
    return loop.make_chunk(make_update(cfg), length, "mean")


@functools.lru_cache(maxsize=16)
def _heldout_fn(cfg: CVAEConfig) -> Callable[[CVAEParams, Triplets, jax.Array, jax.Array], dict[str, jax.Array]]:
    """Jitted ``(params, held, weight, key) -> metrics``: :func:`loss_fn`'s metrics over the rows of
    weight 1 (the held-out triplets, padded to a :func:`bucket` with weight-0 rows)."""
    return jax.jit(lambda p, b, w, k: loss_fn(p, b, k, cfg, w)[1])


def _split(key: jax.Array, n: int, holdout: float, groups: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Train / held-out row indices; whole groups (segments) go to one side when given."""
    if groups is None:
        groups = np.arange(n)
    uniq = np.unique(groups)
    n_held = int(round(holdout * uniq.size))
    if n_held == 0 or n_held == uniq.size:
        return np.arange(n), np.zeros(0, np.int64)
    perm = np.asarray(jax.random.permutation(key, uniq.size))
    held = np.isin(groups, uniq[perm[:n_held]])
    return np.flatnonzero(~held), np.flatnonzero(held)


def _on_device(s: np.ndarray, a: np.ndarray, g: np.ndarray, idx: np.ndarray) -> tuple[Triplets, jax.Array]:
    """Rows ``idx`` of the triplets on device, padded to a :func:`bucket` (compiled programs shared
    across runs), and their count; only the first ``count`` rows are drawn or weighted, so training
    is that of the unpadded triplets."""
    rows = bucket(idx.size)
    return Triplets(*(jnp.asarray(pad_rows(x[idx], rows)) for x in (s, a, g))), jnp.asarray(idx.size, jnp.int32)


def train_cvae(
    key: jax.Array,
    s: np.ndarray,
    a: np.ndarray,
    g: np.ndarray,
    cfg: CVAEConfig,
    obs_stats: tuple[np.ndarray, np.ndarray],
    progress: bool = True,
    *,
    log_every: int = 500,
    holdout: float | None = None,
    groups: np.ndarray | None = None,
    goal_actions: bool = False,
) -> tuple[CVAEParams, list[dict[str, float]]]:
    """Train the CVAE for exactly ``cfg.steps`` steps on raw triplets.

    Args:
      key: root key of this stage; split into init / split / train / eval keys.
      s, a, g: ``[M, obs_dim]``, ``[M, act_dim]``, ``[M, obs_dim]`` triplets (:mod:`extract`);
        ``g [M, obs_dim + act_dim]`` (a state and an action) with ``goal_actions``.
      cfg: CVAE config.
      obs_stats: ``(mean, std)`` of the dataset's observations (:func:`obs_stats`); replaced by
        ``(0, 1)`` when ``cfg.inputs = "raw"``.
      progress: show a progress bar on stderr.
      log_every: steps per jitted chunk (= log interval); the last chunk is shorter when
        ``cfg.steps`` is not a multiple (the same compiled program, :mod:`spot.loop`). Chunk ``c``
        trains with the key ``fold_in(train_key, c)``.
      holdout: fraction of triplets (or of ``groups``) held out for the ``cvae/heldout_*``
        metrics; no held-out split when it rounds to zero groups. None: ``cfg.holdout``
        (``cvae.holdout``: 0.1 by default, 0 under the ``paper`` and ``authors`` variants).
      groups: optional ``[M]`` segment id per triplet, so a segment's triplets are not split
        across train and held-out sets.
      goal_actions: the subgoal is a state and an action (``shaping.state_action``).

    Returns:
      ``(params, history)``; ``history`` is one dict per chunk with ``step``, the chunk means
      of the :func:`loss_fn` metrics and, with a held-out split, ``cvae/heldout_loss`` etc.

    Raises:
      NonFiniteError: a logged loss is NaN or inf.
    """
    s, a, g = (np.asarray(x, dtype=np.float32) for x in (s, a, g))
    if cfg.inputs == "raw":  # identity standardisation
        obs_stats = (np.zeros(s.shape[-1], np.float32), np.ones(s.shape[-1], np.float32))
    m = s.shape[0]
    goal_dim = s.shape[-1] + (a.shape[-1] if goal_actions else 0)
    if m == 0 or a.shape[0] != m or g.shape != (m, goal_dim):
        raise SpotError(
            f"triplets have shapes s {s.shape}, a {a.shape}, g {g.shape}; expected "
            f"[M, obs_dim], [M, act_dim], [M, {'obs_dim + act_dim' if goal_actions else 'obs_dim'}] with M > 0"
        )
    init_key, split_key, train_key, eval_key = jax.random.split(key, 4)
    del key
    train_idx, held_idx = _split(split_key, m, cfg.holdout if holdout is None else holdout, groups)
    data, count = _on_device(s, a, g, train_idx)
    held, held_weight = _on_device(s, a, g, held_idx) if held_idx.size else (None, None)
    if held is not None:
        held_weight = jnp.asarray(pad_rows(np.ones(held_idx.size, np.float32), bucket(held_idx.size)))

    length = loop.chunk_length(cfg.steps, log_every)
    heldout = _heldout_fn(cfg)

    def evaluate(state: CVAEState) -> dict[str, jax.Array]:
        metrics = heldout(state.params, held, held_weight, eval_key)
        return {k.replace("cvae/", "cvae/heldout_"): v for k, v in metrics.items()}

    state = init(init_key, s.shape[1], a.shape[1], cfg, obs_stats, goal_actions)
    out = loop.run(
        make_train_chunk(cfg, length),
        state,
        lambda c: (data, count, jax.random.fold_in(train_key, c)),
        steps=cfg.steps,
        length=length,
        losses={"cvae/loss": "cvae/loss"},
        evaluate=evaluate if held is not None else None,
        eval_loss=("cvae/heldout_loss", "cvae/heldout_loss"),
        progress=progress,
        desc="cvae",
    )
    return out.state.params, out.rows


# --------------------------------------------------------------------------- generation
def sample_subgoal(params: CVAEParams, s: jax.Array, a: jax.Array, key: jax.Array | None = None) -> jax.Array:
    """Raw subgoals ``ĝ [B, obs_dim]`` (``[B, obs_dim + act_dim]``, state then action, when the CVAE
    decodes actions too) from raw ``s [B, o]``, ``a [B, a]`` (eq. 10); pure, jittable.

    ``key=None`` decodes the prior mean; a key decodes one prior sample per row.
    """
    model = params.module
    s_n = params.normalize(s)
    p_mean, p_log_std = model.apply({"params": params.net}, s_n, a, method=CVAE.prior)
    z = p_mean if key is None else p_mean + jnp.exp(p_log_std) * jax.random.normal(key, p_mean.shape)
    return params.denormalize_goal(model.apply({"params": params.net}, z, s_n, a, method=CVAE.decode))


@jax.jit
def _generate_mean(params: CVAEParams, s: jax.Array, a: jax.Array) -> jax.Array:
    return sample_subgoal(params, s, a)


@jax.jit
def _generate_sample(params: CVAEParams, s: jax.Array, a: jax.Array, key: jax.Array) -> jax.Array:
    return sample_subgoal(params, s, a, key)


def generate(
    params: CVAEParams,
    s: np.ndarray,
    a: np.ndarray,
    key: jax.Array | None = None,
    mode: str = "mean",
    batch_size: int = 4096,
    with_actions: bool = False,
) -> np.ndarray:
    """Subgoals for a whole dataset, in fixed-size batches (the last one padded; one compile).

    Args:
      params: trained :class:`CVAEParams`.
      s, a: raw ``[N, obs_dim]``, ``[N, act_dim]``.
      key: required for ``mode="sample"``; batch ``i`` uses ``fold_in(key, i)``.
      mode: ``"mean"`` decodes the prior mean, ``"sample"`` a prior sample.
      batch_size: rows per jitted call.
      with_actions: for a CVAE that decodes a state and an action (``goal_act_dim > 0``), return
        both, ``[N, obs_dim + act_dim]`` (:func:`split_goal`); otherwise the state part only.

    Returns:
      ``ĝ [N, obs_dim]`` float32 numpy, in raw state units.
    """
    if mode not in ("mean", "sample"):
        raise SpotError(f"subgoal mode {mode!r}; expected 'mean' or 'sample'")
    if mode == "sample" and key is None:
        raise SpotError("mode='sample' needs a key")
    s, a = np.asarray(s, dtype=np.float32), np.asarray(a, dtype=np.float32)
    n, bs = s.shape[0], batch_size
    out = np.empty((n, params.obs_dim + params.goal_act_dim), np.float32)
    for i, start in enumerate(range(0, n, bs)):
        s_b, a_b = s[start : start + bs], a[start : start + bs]
        pad = bs - s_b.shape[0]
        if pad:
            s_b = np.concatenate([s_b, np.zeros((pad, s.shape[1]), np.float32)])
            a_b = np.concatenate([a_b, np.zeros((pad, a.shape[1]), np.float32)])
        if mode == "mean":
            g_b = _generate_mean(params, s_b, a_b)
        else:
            g_b = _generate_sample(params, s_b, a_b, jax.random.fold_in(key, i))
        out[start : start + bs] = np.asarray(g_b)[: bs - pad]
    return out if with_actions else out[:, : params.obs_dim]


def split_goal(params: CVAEParams, g: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``(ĝ_s [N, obs_dim], ĝ_a [N, act_dim] or None)`` of generated goals ``g`` (:func:`generate`)."""
    o = params.obs_dim
    return g[:, :o], (g[:, o:] if params.goal_act_dim else None)
