"""Relabel every transition of an offline dataset with a trained reward model, and normalise.

SPOT's second phase (paper §4.2, Fig. 1 right; eq. 13's ``r_model``) trains IQL on the dataset
relabelled by the reward model. Trajectories are the episodes of the ``qlearning`` view
(``Dataset.episode_bounds()``). Modes (reference/algorithms.md §1.4, §1.6):

* PT ``chunked`` (**default**): each episode is cut into consecutive, non-overlapping chunks of
  ``window`` steps (the last one padded and masked), fed with timesteps ``1..window``; every step
  takes ``r_hat_t`` of its chunk, and the importance weight ``w_t`` (which sums to 1 over a chunk)
  comes for free. One forward pass covers ``window`` transitions, so it is about ``window`` times
  cheaper than ``sliding``; it is how WiseRL and Uni-RLHF relabel, and it matches how PT is trained
  (whole segments with timesteps ``1..T``).
* PT ``sliding``: reproduces the PT repo's IQL rewards (``reward_from_preference_transformer``,
  ``label_mode='last'``): transition ``t`` gets ``r_hat`` at the last position of the causal window
  of the ``window`` steps of its episode ending at ``t``; windows that start before the episode are
  left zero-padded with pad timesteps 0 and mask 0, the real steps get timesteps ``1..t+1``
  (full windows ``1..window``). The last block only computes that last position.
* MR: ``r_phi(s, a)`` of each transition (``reward_from_preference``); ``window`` is unused except
  to size batches.
* HPL (:func:`relabel_hpl`): the reward marginalised over ``hpl.prior_samples`` latents of the
  prior, per transition.

Every mode runs one jitted program with fixed shapes (the last batch is padded), compiled once
per model, window and batch size in a process (jit's own cache). The dataset's arrays it indexes
are padded to a bucket of rows (:mod:`spot.padding`; the padding is never read), so the datasets
of an environment share the program.

:func:`normalize_rewards` then rescales by the spread of the per-episode returns of the *new*
rewards: ``pt``: ``r * 1000 / (R_max - R_min) + 0.5`` (PT repo ``train_offline.py`` for
locomotion), ``iql``: ``r * 1000 / (R_max - R_min)`` (IQL reference, §2.3), ``none``.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from spot import SpotError, loop, padding
from spot.config import HPLConfig, MRConfig, PTConfig, RelabelConfig
from spot.data.dataset import Dataset
from spot.nets import Params
from spot.reward import hpl_nets, mr, pt
from spot.reward.models import RewardModel

NORMALIZE_MODES = ("pt", "iql", "wiserl", "minmax", "none")


class Relabelled(NamedTuple):
    """Output of :func:`relabel_rewards`.

    Attributes:
      rewards: ``[N]`` float32, the model's per-step reward of every transition.
      weights: ``[N]`` float32 PT importance weights (``chunked`` mode only, else None).
      compile_s: seconds spent compiling the forward program (0 if compiled before in this process).
      total_s: wall time of the whole relabelling, compile included.
    """

    rewards: np.ndarray
    weights: np.ndarray | None
    compile_s: float
    total_s: float


def chunk_bounds(ds: Dataset, window: int) -> tuple[np.ndarray, np.ndarray]:
    """``(start, end)`` rows of the consecutive ``window``-step chunks of every episode (end exclusive)."""
    starts, ends = ds.episode_bounds()
    n_chunks = -(-(ends - starts) // window)  # ceil
    episode = np.repeat(np.arange(starts.size), n_chunks)
    k = np.arange(n_chunks.sum()) - np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
    chunk_start = starts[episode] + k * window
    return chunk_start, np.minimum(chunk_start + window, ends[episode])


def _run_batched(
    program: Callable,
    params: Params,
    ds: Dataset,
    inputs: tuple[np.ndarray, ...],
    batch: int,
    progress: bool,
    desc: str,
) -> tuple[tuple[np.ndarray, ...], float]:
    """Run jitted ``program(params, obs_all, act_all, *inputs_batch)`` over ``inputs`` in fixed-size
    batches (the last padded with zeros); returns the concatenated, unpadded outputs and compile
    time."""
    n = inputs[0].shape[0]
    n_batches = max(math.ceil(n / batch), 1)
    padded = [np.concatenate([x, np.zeros((n_batches * batch - n, *x.shape[1:]), x.dtype)]) for x in inputs]
    # rows padded to a bucket (never read: every index is a real row): one program per env
    obs_all, act_all = jax.device_put(
        padding.pad_rows((np.asarray(ds.observations, np.float32), np.asarray(ds.actions, np.float32)))
    )
    compile_s = loop.compile_seconds(program, params, obs_all, act_all, *(x[:batch] for x in padded))
    outputs = []
    for i in tqdm(range(n_batches), desc=desc, disable=not progress, leave=False):
        out = program(params, obs_all, act_all, *(x[i * batch : (i + 1) * batch] for x in padded))
        outputs.append(jax.device_get(out))
    return tuple(np.concatenate(parts)[:n] for parts in zip(*outputs, strict=True)), compile_s


@functools.lru_cache(maxsize=16)
def _chunked_program(cfg: PTConfig, window: int) -> Callable:
    @jax.jit
    def run(
        params: Params, obs_all: jax.Array, act_all: jax.Array, start: jax.Array, end: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        idx = start[:, None] + jnp.arange(window)  # [B, W]
        mask = idx < end[:, None]
        idx = jnp.where(mask, idx, 0)
        timesteps = jnp.where(mask, jnp.arange(1, window + 1), 0)
        r_hat, w, _ = pt.forward(params, cfg, obs_all[idx], act_all[idx], timesteps, mask.astype(jnp.float32))
        return r_hat, w

    return run


@functools.lru_cache(maxsize=16)
def _sliding_program(cfg: PTConfig, window: int) -> Callable:
    @jax.jit
    def run(
        params: Params, obs_all: jax.Array, act_all: jax.Array, row: jax.Array, episode_start: jax.Array
    ) -> tuple[jax.Array]:
        idx = row[:, None] - (window - 1) + jnp.arange(window)  # window ending at row, [B, W]
        mask = idx >= episode_start[:, None]
        pads = (window - 1) - jnp.minimum(row - episode_start, window - 1)  # [B]
        timesteps = jnp.where(mask, jnp.arange(window) - pads[:, None] + 1, 0)
        idx = jnp.where(mask, idx, 0)
        return (pt.last_step_reward(params, cfg, obs_all[idx], act_all[idx], timesteps, mask.astype(jnp.float32)),)

    return run


@functools.lru_cache(maxsize=16)
def _mr_program(cfg: MRConfig) -> Callable:
    @jax.jit
    def run(params: Params, obs_all: jax.Array, act_all: jax.Array, row: jax.Array) -> tuple[jax.Array]:
        return (mr.per_step_reward(params, obs_all[row], act_all[row], cfg),)

    return run


def relabel_rewards(
    model: RewardModel, params: Params, ds: Dataset, relabel_cfg: RelabelConfig, progress: bool = True
) -> Relabelled:
    """Per-transition rewards of ``ds`` from a trained reward model (see module docstring).

    Args:
      model: ``MR(cfg)`` or ``PT(cfg)`` (:mod:`spot.reward.models`); params: its parameters (from
        ``train_reward_model``).
      ds: the ``qlearning`` view; episodes from ``ds.episode_bounds()``.
      relabel_cfg: ``mode`` (PT only), ``window``, ``batch_size`` (windows/chunks per pass; MR uses
        ``batch_size * window`` transitions per pass).
      progress: tqdm bar over batches.

    Returns:
      :class:`Relabelled` (rewards ``[N]`` float32; weights ``[N]`` for PT ``chunked``).
    """
    t0 = time.perf_counter()
    window, batch = relabel_cfg.window, relabel_cfg.batch_size
    rows = np.arange(len(ds), dtype=np.int32)
    weights = None
    if isinstance(model, mr.MR):  # per transition: no sequence modes
        (rewards,), compile_s = _run_batched(
            _mr_program(model.cfg), params, ds, (rows,), batch * window, progress, "relabel (mr)"
        )
    elif isinstance(model, pt.PT):
        rewards, weights, compile_s = _relabel_pt(model.cfg, params, ds, relabel_cfg, progress)
    else:
        raise SpotError(f"relabelling has no program for reward model {model!r}; expected MR or PT")
    return Relabelled(np.asarray(rewards, np.float32), weights, compile_s, time.perf_counter() - t0)


def _relabel_pt(
    cfg: PTConfig, params: Params, ds: Dataset, relabel_cfg: RelabelConfig, progress: bool
) -> tuple[np.ndarray, np.ndarray | None, float]:
    """PT's ``chunked`` or ``sliding`` relabelling: ``(rewards, weights or None, compile_s)``."""
    window, batch = relabel_cfg.window, relabel_cfg.batch_size
    if window > cfg.max_timestep:
        raise SpotError(
            f"relabel.window {window} exceeds pt.max_timestep {cfg.max_timestep}; "
            "timesteps 1..window must fit the timestep embedding"
        )
    if relabel_cfg.mode == "chunked":
        start, end = chunk_bounds(ds, window)
        (r_hat, w), compile_s = _run_batched(
            _chunked_program(cfg, window),
            params,
            ds,
            (start.astype(np.int32), end.astype(np.int32)),
            batch,
            progress,
            "relabel (pt, chunked)",
        )
        idx = start[:, None] + np.arange(window)
        valid = idx < end[:, None]
        rewards = np.empty(len(ds), np.float32)
        weights = np.empty(len(ds), np.float32)
        rewards[idx[valid]] = r_hat[valid]
        weights[idx[valid]] = w[valid]
        return rewards, weights, compile_s
    if relabel_cfg.mode == "sliding":
        starts, ends = ds.episode_bounds()
        episode_start = np.repeat(starts, ends - starts).astype(np.int32)
        (rewards,), compile_s = _run_batched(
            _sliding_program(cfg, window),
            params,
            ds,
            (np.arange(len(ds), dtype=np.int32), episode_start),
            batch,
            progress,
            "relabel (pt, sliding)",
        )
        return rewards, None, compile_s
    raise SpotError(f"relabel.mode '{relabel_cfg.mode}' is not one of 'chunked', 'sliding'")


@functools.lru_cache(maxsize=8)
def _hpl_program(cfg: HPLConfig) -> Callable:
    @jax.jit
    def program(p: Params, x_all: jax.Array, rows: jax.Array, key: jax.Array) -> jax.Array:
        return hpl_nets.prior_marginal_reward(p, cfg, x_all[rows], key)

    return program


def relabel_hpl(
    params: Params, ds: Dataset, cfg: HPLConfig, key: jax.Array, batch_size: int = 4096, progress: bool = False
) -> np.ndarray:
    """HPL's ``r_hat(s, a)`` of every transition of ``ds``:
    :func:`spot.reward.hpl_nets.prior_marginal_reward` of the trained ``params``
    (:func:`spot.reward.hpl.train_hpl`) in jitted batches of ``batch_size`` rows (the last padded);
    batch i uses ``fold_in(key, i)``.

    Returns:
      ``[N]`` float32 (not normalised; see ``relabel.normalize``, HPL's is ``wiserl``).
    """
    x = np.concatenate([ds.observations, ds.actions], axis=-1).astype(np.float32)
    n = x.shape[0]
    x_all = jnp.asarray(padding.pad_rows(x))  # a bucket of rows (spot.padding); rows < n are read
    n_batches = max(-(-n // batch_size), 1)
    rows = np.minimum(np.arange(n_batches * batch_size), n - 1).astype(np.int32).reshape(n_batches, batch_size)
    sub = {"prior": params["prior"], "reward": params["reward"]}
    program = _hpl_program(cfg)
    out = [
        jax.device_get(program(sub, x_all, rows[i], jax.random.fold_in(key, i)))
        for i in tqdm(range(n_batches), desc="relabel (hpl)", disable=not progress, leave=False)
    ]
    return np.concatenate(out)[:n].astype(np.float32)


def normalize_rewards(rewards: np.ndarray, ds: Dataset, mode: str, max_episode_steps: int = 1000) -> np.ndarray:
    """Rescale relabelled rewards by the spread of per-episode returns (computed on ``rewards``).

    ``pt``: ``r * max_episode_steps / (R_max - R_min) + 0.5``; ``iql``: without the ``+ 0.5``;
    ``wiserl``: ``r * max_episode_steps / max(|R_min|, |R_max|, R_max - R_min, 1)`` (HPL's WiseRL
    ``relabel_reward``); ``minmax``: each step's reward first mapped to [0, 1] with the min and max
    over all transitions, then ``iql`` (every step non-negative, so staying alive never costs
    reward: a learned reward's level is not identified by preferences, and a negative level makes
    an IQL policy seek early termination in Hopper/Walker2d); ``none``: unchanged. ``max_episode_steps`` is the 1000 of
    the references
    (locomotion).
    """
    if mode not in NORMALIZE_MODES:
        raise SpotError(f"relabel.normalize '{mode}' is not one of {', '.join(map(repr, NORMALIZE_MODES))}")
    rewards = np.asarray(rewards, np.float32)
    if rewards.shape != (len(ds),):
        raise SpotError(f"rewards have shape {rewards.shape}; expected [{len(ds)}] (one per transition)")
    if mode == "none":
        return rewards.copy()
    if mode == "minmax":
        lo, hi = float(rewards.min()), float(rewards.max())
        if not hi > lo:
            raise SpotError(
                f"cannot normalise rewards of dataset '{ds.name}' with minmax: every step has "
                f"reward {lo:.6g}; use relabel.normalize=none"
            )
        rewards = ((rewards.astype(np.float64) - lo) / (hi - lo)).astype(np.float32)
        mode = "iql"
    starts, _ = ds.episode_bounds()
    returns = np.add.reduceat(rewards.astype(np.float64), starts)
    spread = float(returns.max() - returns.min())
    if mode == "wiserl":
        scale = max(abs(float(returns.min())), abs(float(returns.max())), spread, 1.0)
        return (rewards.astype(np.float64) * (max_episode_steps / scale)).astype(np.float32)
    if not spread > 0.0:
        raise SpotError(
            f"cannot normalise rewards of dataset '{ds.name}': all {returns.size} episode returns are "
            f"equal ({returns.max():.6g}); use relabel.normalize=none"
        )
    out = rewards.astype(np.float64) * (max_episode_steps / spread)
    return (out + 0.5 if mode == "pt" else out).astype(np.float32)
