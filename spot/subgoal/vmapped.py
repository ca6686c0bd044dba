"""CVAEs of several seeds trained as one program (``seed_mode: vmap``).

:func:`train_cvaes` is :func:`spot.subgoal.cvae.train_cvae` for ``S`` seeds at once: the same
update (:func:`spot.subgoal.cvae.make_update`), split, padding, chunking and held-out metrics,
vmapped over a leading seed axis. Each seed's triplets are padded to the largest seed's
:func:`~spot.subgoal.cvae.bucket` (training draws from the first ``count`` rows only, so the
padding changes nothing) and its held-out triplets likewise with weight-0 rows. It lives in its
own module so that the code version of the one-seed CVAE stage (which covers
:mod:`spot.subgoal.cvae`) does not change with it; the result equals one-seed training to float
tolerance (``tests/test_subgoal.py``) and a vmap trial stores it under keys of its own
(``spot.run.multiseed.KEY_EXTRA``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from spot import NonFiniteError, SpotError, loop
from spot.config import CVAEConfig
from spot.subgoal import cvae
from spot.subgoal.cvae import CVAEParams, Triplets


class _Seed:
    """One seed's keys, triplets (float32) and train / held-out rows, as :func:`cvae.train_cvae` splits them."""

    def __init__(self, key: jax.Array, s: Any, a: Any, g: Any, holdout: float, groups: Any, goal_actions: bool):
        self.s, self.a, self.g = (np.asarray(x, dtype=np.float32) for x in (s, a, g))
        m = self.s.shape[0]
        goal_dim = self.s.shape[-1] + (self.a.shape[-1] if goal_actions else 0)
        if m == 0 or self.a.shape[0] != m or self.g.shape != (m, goal_dim):
            raise SpotError(
                f"triplets have shapes s {self.s.shape}, a {self.a.shape}, g {self.g.shape}; expected "
                f"[M, obs_dim], [M, act_dim], [M, {'obs_dim + act_dim' if goal_actions else 'obs_dim'}] with M > 0"
            )
        self.init_key, split_key, self.train_key, self.eval_key = jax.random.split(key, 4)
        self.train_idx, self.held_idx = cvae._split(split_key, m, holdout, groups)

    def rows(self, idx: np.ndarray, rows: int) -> Triplets:
        return Triplets(*(cvae.pad_rows(x[idx], rows) for x in (self.s, self.a, self.g)))


def train_cvaes(
    keys: Sequence[jax.Array],
    triplets: Sequence[tuple[Any, Any, Any]],
    cfg: CVAEConfig,
    obs_stats: tuple[np.ndarray, np.ndarray],
    progress: bool = True,
    *,
    log_every: int = 500,
    holdout: float | None = None,
    groups: Sequence[np.ndarray | None] | None = None,
    goal_actions: bool = False,
) -> list[tuple[CVAEParams, list[dict[str, float]]]]:
    """:func:`spot.subgoal.cvae.train_cvae` for the seeds' ``keys`` and ``triplets`` ``(s, a, g)``
    (one ``groups`` array per seed) as one vmapped program; one ``(params, history)`` per seed.

    Raises SpotError when the seeds cannot share one program: different observation or action
    sizes, or held-out triplets for some seeds and none for others."""
    groups = list(groups) if groups is not None else [None] * len(keys)
    holdout = cfg.holdout if holdout is None else holdout  # cvae.holdout, as train_cvae
    seeds = [_Seed(k, *t, holdout, grp, goal_actions) for k, t, grp in zip(keys, triplets, groups, strict=True)]
    if len({(x.s.shape[1:], x.a.shape[1:], x.g.shape[1:], x.held_idx.size > 0) for x in seeds}) > 1:
        raise SpotError(
            "CVAEs vmapped over seeds: the seeds' triplets differ in their sizes, or only some seeds have "
            "held-out triplets; train them one seed at a time"
        )
    if cfg.inputs == "raw":  # identity standardisation
        obs_dim = seeds[0].s.shape[-1]
        obs_stats = (np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32))
    rows = max(cvae.bucket(x.train_idx.size) for x in seeds)
    data = jax.device_put(_stack([x.rows(x.train_idx, rows) for x in seeds]))
    count = jnp.asarray([x.train_idx.size for x in seeds], jnp.int32)
    held = weight = None
    if seeds[0].held_idx.size:
        held_rows = max(cvae.bucket(x.held_idx.size) for x in seeds)
        held = jax.device_put(_stack([x.rows(x.held_idx, held_rows) for x in seeds]))
        weight = jnp.asarray(np.stack([cvae.pad_rows(np.ones(x.held_idx.size, np.float32), held_rows) for x in seeds]))
    state = _stack([cvae.init(x.init_key, x.s.shape[1], x.a.shape[1], cfg, obs_stats, goal_actions) for x in seeds])
    length = loop.chunk_length(cfg.steps, log_every)
    train_keys, eval_keys = jnp.stack([x.train_key for x in seeds]), jnp.stack([x.eval_key for x in seeds])
    heldout = _vmapped_heldout(cfg)
    evaluate = (lambda st: heldout(st.params, held, weight, eval_keys)) if held is not None else None
    chunk = _vmapped_chunk(cfg, length)
    state, rows_per_seed = _run_seeds(chunk, state, (data, count), train_keys, evaluate, cfg.steps, length, progress)
    return [(jax.tree.map(lambda a, s=s: a[s], state.params), r) for s, r in enumerate(rows_per_seed)]


def _stack(trees: list[Any]) -> Any:
    return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *trees)


@functools.lru_cache(maxsize=8)
def _vmapped_chunk(cfg: CVAEConfig, length: int) -> loop.Chunk:
    return loop.make_chunk(cvae.make_update(cfg), length, "mean", vmap_axes=(0, 0, 0, 0))


@functools.lru_cache(maxsize=8)
def _vmapped_heldout(cfg: CVAEConfig) -> Callable:
    return jax.jit(jax.vmap(lambda p, b, w, k: cvae.loss_fn(p, b, k, cfg, w)[1]))


def _run_seeds(
    chunk: loop.Chunk,
    state: Any,
    data: tuple,
    train_keys: jax.Array,
    evaluate: Callable | None,
    steps: int,
    length: int,
    progress: bool,
) -> tuple[Any, list[list[dict[str, float]]]]:
    """:func:`spot.loop.run` for a state stacked over seeds: chunk ``c`` trains seed ``s`` with
    ``fold_in(train_keys[s], c)``; one history row per chunk and seed, the losses checked per seed."""
    fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
    n_seeds = int(train_keys.shape[0])
    history: list[list[dict[str, float]]] = [[] for _ in range(n_seeds)]
    bar = tqdm(total=steps, desc=f"cvae ({n_seeds} seeds vmapped)", disable=not progress, leave=False)
    done = 0
    for c, n in enumerate(loop.chunk_sizes(steps, length)):
        state, metrics = chunk(state, n, *data, fold(train_keys, c))
        host = jax.device_get(metrics)
        held = jax.device_get(evaluate(state)) if evaluate is not None else {}
        done += n
        for s, rows in enumerate(history):
            row = {
                "step": done,
                **loop._chunk_row({k: v[s] for k, v in host.items()}, done - n, n, {"cvae/loss": "cvae/loss"}),
            }
            row.update({k.replace("cvae/", "cvae/heldout_"): float(v[s]) for k, v in held.items()})
            if "cvae/heldout_loss" in row and not np.isfinite(row["cvae/heldout_loss"]):
                raise NonFiniteError(done, "cvae/heldout_loss", row["cvae/heldout_loss"])
            rows.append(row)
        bar.update(n)
    bar.close()
    return state, history
