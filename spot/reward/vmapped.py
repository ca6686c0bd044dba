"""Reward models of several seeds trained as one program (``seed_mode: vmap``).

:func:`train_reward_models` is :func:`spot.reward.train.train_reward_model` for ``S`` seeds whose
preference pairs have one shape (the seeds of one config): the update, the chunking, the held-out
evaluation and the best-checkpoint rule are that module's, vmapped over a leading seed axis. It
lives in its own module so that the stage cache's code version of the one-seed reward stage (which
covers :mod:`spot.reward.train`) does not change with it. The result equals one-seed training up to
rounding (``tests/test_reward.py``), amplified by Adam in the directions the preference loss
cannot see; so a vmap trial stores it under keys of its own (``spot.run.multiseed.KEY_EXTRA``).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from spot import NonFiniteError, SpotError, loop
from spot.config import RewardConfig
from spot.nets import Params
from spot.reward.models import RewardModel
from spot.reward.train import BestRule, _checked_pairs, _history, eval_period, training_steps
from spot.reward.update import PrefPairs, RewardState, init_state, make_evaluate, make_update, num_pairs


def train_reward_models(
    model: RewardModel,
    keys: list[jax.Array],
    train_batches: list[Mapping[str, np.ndarray]],
    eval_batches: list[Mapping[str, np.ndarray] | None],
    reward_cfg: RewardConfig,
    progress: bool = True,
    micro_batch: int = 64,
) -> list[tuple[Params, dict[str, Any]]]:
    """:func:`train_reward_model` for ``S`` seeds at once (``seed_mode: vmap``): one
    ``jit(vmap(chunk))`` over a leading seed axis, each seed with its own key (initial parameters,
    minibatches, dropout), its own training and held-out pairs and its own best checkpoint.

    Every seed's pairs must have the same shapes (the same query counts and segment lengths: seeds
    of one config), else SpotError. Returns one ``(params, history)`` per seed, equal to what
    ``train_reward_model(model, keys[s], train_batches[s], eval_batches[s], ...)`` returns, up to
    the rounding of batched matmuls; ``compile_s`` and ``train_s`` are the shared program's (the
    wall time of all seeds together). No companion (the online CVAE trains one seed at a time)."""
    checked = [_checked_pairs(model, t, e) for t, e in zip(train_batches, eval_batches, strict=True)]
    _check_same_shapes(checked)
    train = _stack([c[0] for c in checked])
    held_out, eval_on = [c[1] for c in checked], checked[0][2]
    pairs_per_run = num_pairs(checked[0][0])
    steps = training_steps(reward_cfg, pairs_per_run)
    split = [jax.random.split(k) for k in keys]
    obs_dim, act_dim = train.obs_1.shape[-1], train.act_1.shape[-1]
    state = _stack([init_state(model, init_key, obs_dim, act_dim, steps) for init_key, _ in split])
    train_keys = jnp.stack([train_key for _, train_key in split])
    batch_size = min(reward_cfg.batch_size, pairs_per_run)
    length = loop.chunk_length(steps, eval_period(reward_cfg, pairs_per_run))
    padded = [loop.pad_minibatches(h, min(reward_cfg.batch_size, num_pairs(h))) for h in held_out]
    eval_data, eval_weight = jax.device_put((_stack([p[0] for p in padded]), np.stack([p[1] for p in padded])))
    train = jax.device_put(train)
    chunk = _vmapped_train_chunk(model, batch_size, length, steps, micro_batch)
    evaluate = _vmapped_evaluate(model)
    compile_s = loop.compile_seconds(chunk, state, length, train, train_keys) + loop.compile_seconds(
        evaluate, state.params, eval_data, eval_weight
    )
    baselines = [None] * len(keys)
    if reward_cfg.eval_initial:  # the untrained models' held-out losses: each seed's first best
        baselines = [float(x) for x in np.asarray(evaluate(state.params, eval_data, eval_weight)[0])]
    rules = [
        BestRule(reward_cfg.best_min_delta, b, lambda st, s=s: jax.tree.map(lambda a: a[s], st.params))
        for s, b in enumerate(baselines)
    ]
    desc = f"reward ({model.kind}, {len(keys)} seeds vmapped)" if progress else None
    held_out_of = lambda st: evaluate(st.params, eval_data, eval_weight)  # noqa: E731
    runs = _run_seeds(chunk, state, (train, train_keys), held_out_of, rules, steps, length, desc)
    out = []
    for r, rule, baseline in zip(runs, rules, baselines, strict=True):
        r.best, r.best_params, improved = rule.result()
        history = _history(r, batch_size, eval_on, compile_s, steps)
        history.update(best_improved=improved, initial_eval_loss=baseline)
        out.append((jax.device_put(r.best_params), history))
    return out


def _stack(trees: list[Any]) -> Any:
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def _check_same_shapes(checked: list[tuple[PrefPairs, PrefPairs, str]]) -> None:
    """Raise SpotError unless every seed's training and held-out pairs have seed 0's shapes."""
    shapes = [(jax.tree.map(np.shape, tr), jax.tree.map(np.shape, ho), on) for tr, ho, on in checked]
    for s, got in enumerate(shapes[1:], start=1):
        if got != shapes[0]:
            raise SpotError(
                f"reward models vmapped over seeds: seed {s}'s preference pairs differ in shape from seed 0's "
                f"({got} vs {shapes[0]}); train them one seed at a time"
            )


@functools.lru_cache(maxsize=8)
def _vmapped_train_chunk(model: RewardModel, batch_size: int, length: int, steps: int, micro_batch: int) -> loop.Chunk:
    return loop.make_chunk(make_update(model, batch_size, steps, micro_batch), length, "stack", vmap_axes=(0, 0, 0))


@functools.lru_cache(maxsize=8)
def _vmapped_evaluate(model: RewardModel) -> Callable:
    return jax.jit(jax.vmap(make_evaluate(model)))


def _run_seeds(
    chunk: loop.Chunk,
    state: RewardState,
    args: tuple,
    evaluate: Callable,
    rules: list[BestRule],
    steps: int,
    length: int,
    desc: str | None,
) -> list[loop.Run]:
    """:func:`spot.loop.run` for a state stacked over seeds: one row per chunk and seed (the NaN/inf
    checks per seed), each seed's checkpoint kept by its :class:`spot.reward.train.BestRule` (as
    :func:`spot.reward.train.train_reward_model` keeps one seed's) and copied to the host."""
    from tqdm.auto import tqdm

    n_seeds = int(np.shape(jax.tree.leaves(state)[0])[0])
    runs = [loop.Run(None) for _ in range(n_seeds)]
    bar = tqdm(total=steps, desc=desc, disable=desc is None, leave=False)
    done, t0 = 0, time.perf_counter()
    for n in loop.chunk_sizes(steps, length):
        state, metrics = chunk(state, n, *args)
        host = jax.device_get(metrics)
        eval_loss, eval_acc = (np.asarray(x) for x in jax.device_get(evaluate(state)))
        for s, r in enumerate(runs):
            row = loop._chunk_row({k: v[s] for k, v in host.items()}, done, n, {"loss": "reward/train_loss"})
            row = {"step": done + n, **row, "eval_loss": float(eval_loss[s]), "eval_acc": float(eval_acc[s])}
            if not np.isfinite(row["eval_loss"]):
                raise NonFiniteError(done + n, "reward/eval_loss", row["eval_loss"])
            rules[s].update(row, state)
            r.rows.append(row)
        done += n
        bar.update(n)
    bar.close()
    for r in runs:
        r.loop_s = time.perf_counter() - t0
    return runs
