"""The policy slot: IQL (or IPL) on the policy's reward, evaluated in the env on a schedule, and the
evaluation helpers (:func:`eval_policy`: the policy program every evaluation uses; :func:`eval_seed`,
:func:`eval_episodes`, :func:`log_evaluation`)."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from spot import config as config_lib
from spot import padding, phases
from spot.config import ExperimentConfig
from spot.run.context import Context, Labelled, Policy, Shaped


def eval_episodes(cfg: ExperimentConfig, step: int) -> int:
    """Episodes of the evaluation after ``step`` updates: ``eval.final_episodes`` after the last
    update when it is set, else ``eval.episodes``."""
    final = cfg.eval.final_episodes
    return final if final > 0 and step >= cfg.iql.steps else cfg.eval.episodes


def eval_seed(cfg: ExperimentConfig) -> int:
    """The base seed of a run's evaluation episodes (episode ``i`` is seeded ``eval_seed + i``; the
    same episodes at every evaluation, and in ``spot eval``)."""
    return 10_000 * (cfg.seed + 1)


@functools.cache
def _act_each(iql_cfg: config_lib.IQLConfig) -> Callable[[Any, Any], Any]:
    """One jitted program: actor params stacked on a leading axis ``[R]`` and observations
    ``[R, n, obs_dim]`` -> mean actions ``[R, n, act_dim]``, each observation's action computed
    alone (a ``lax.map`` over runs and one over rows, one observation per matrix product): a
    product's rows differ in their last bits with the batch's size, so the episodes of a batched
    evaluation get the actions they get evaluated one at a time, whatever else runs beside them.
    Cached per config: compiled once per batch shape in a process."""
    import jax

    from spot.policy import iql

    def one(params: Any, obs: Any) -> Any:
        return iql.act(params, obs[None], iql_cfg)[0]

    def each(params: Any, obs: Any) -> Any:
        return jax.lax.map(lambda run: jax.lax.map(lambda o: one(run[0], o), run[1]), (params, obs))

    return jax.jit(each)


def eval_policy(
    actor_params: Any, iql_cfg: config_lib.IQLConfig, runs: bool = False
) -> Callable[[np.ndarray], np.ndarray]:
    """The ``policy_fn`` of :func:`spot.evaluation.evaluate` for an IQL actor (the policy's mean action,
    one jitted call per step, each row computed alone); ``runs=True``: that of
    :func:`spot.evaluation.evaluate_runs` for actor params stacked over runs (a vmapped trial's seeds)."""
    import jax

    act = _act_each(iql_cfg)
    if runs:
        return lambda obs: np.asarray(act(actor_params, obs))
    stacked = jax.tree.map(lambda a: jax.device_put(np.array(a)[None]), actor_params)  # a copy; no program per shape
    return lambda obs: np.asarray(act(stacked, obs[None]))[0]


def log_evaluation(ctx: Context, res: dict[str, Any], step: int) -> None:
    """Log an evaluation's result after ``step`` updates to ``ctx`` (and its ``on_eval``)."""
    ctx.log(
        {
            "eval/score": res["score_mean"],
            "eval/score_std": res["score_std"],
            "eval/return": res["return_mean"],
            "eval/length": res["episode_length_mean"],  # a fall (locomotion) ends an episode early
        },
        step=step,
    )
    if ctx.on_eval is not None:
        ctx.on_eval({"step": step, "score": float(res["score_mean"])})
    if ctx.progress:  # the policy stage is a run's longest: one line per evaluation (not with --quiet)
        cfg = ctx.cfg
        print(
            f"spot: {cfg.method} seed {cfg.seed}: policy step {step:,}/{cfg.iql.steps:,}: "
            f"score {res['score_mean']:.1f} ± {res['score_std']:.1f}",
            file=sys.stderr,
            flush=True,
        )


def _evaluate_fn(ctx: Context) -> Callable[[Any, int], dict[str, float]]:
    """``evaluate(actor_params, step)``: the policy's mean action in the evaluation env, its
    episodes stepped together (:func:`eval_policy`)."""
    from spot import evaluation

    cfg = ctx.cfg

    def evaluate(actor_params: Any, step: int) -> dict[str, float]:
        with phases.phase("evaluate"):  # a sweep trial's time breakdown (spot.phases)
            res = evaluation.evaluate(
                eval_policy(actor_params, cfg.iql),
                ctx.env_name,
                eval_episodes(cfg, step),
                seed=eval_seed(cfg),
                max_steps=cfg.eval.max_steps,
                stepper=cfg.eval.stepper,
            )
        log_evaluation(ctx, res, step)
        return res

    return evaluate


def _train_policy(ctx: Context, state: Any, train_chunk: Callable, args: Callable[[Any], tuple]) -> Policy:
    """:func:`spot.policy.iql.train`: ``iql.steps`` updates, chunk metrics logged, the policy
    evaluated in the env before the first update, at every multiple of ``eval.every`` and after the
    last (:func:`spot.policy.iql.eval_steps`); chunk ``c`` gets the key
    ``fold_in(train_key, c)`` (``args(key)``: the chunk's arguments after ``(state, n)``)."""
    import jax

    from spot.policy import iql

    _, train_key = jax.random.split(ctx.keys["policy"])
    evaluate = _evaluate_fn(ctx)
    curve = iql.train(
        train_chunk,
        state,
        lambda c: args(jax.random.fold_in(train_key, c)),
        ctx.cfg.iql,
        ctx.cfg.eval.every,
        lambda params, step: evaluate(params, step)["score_mean"],
        log=lambda metrics, step: ctx.log(metrics, step=step),
    )
    return Policy(curve.state, curve.steps, curve.scores, curve.eval_s)


def policy_transitions(cfg: ExperimentConfig, ds: Any, reward: np.ndarray) -> Any:
    """The transitions the policy trains on (``ds.transitions(reward)``), actions clipped to
    ``±iql.clip_action`` when it is > 0 (IQL's ``D4RLDataset``: ``1 - 1e-5``)."""
    data = ds.transitions(reward)
    clip = cfg.iql.clip_action
    return data._replace(act=np.clip(data.act, -clip, clip)) if clip > 0 else data


def iql_policy(ctx: Context, shaped: Shaped, labelled: Labelled | None) -> Policy:
    """IQL on the (shaped) reward."""
    import jax

    from spot.policy import iql

    # padded to a bucket of rows: one compiled chunk for every dataset of the env (spot.padding)
    data = jax.device_put(padding.padded(policy_transitions(ctx.cfg, ctx.ds, shaped.reward)))
    init_key, _ = jax.random.split(ctx.keys["policy"])
    state = iql.init_state(init_key, ctx.ds.obs_dim, ctx.ds.act_dim, ctx.cfg.iql)
    return _train_policy(ctx, state, iql.make_train_chunk(ctx.cfg.iql), lambda key: (data, key))


def ipl_policy(ctx: Context, shaped: Shaped, labelled: Labelled) -> Policy:
    """IPL: the critic's implied reward is trained on the preferences (no reward model)."""
    import jax

    from spot.policy import ipl

    cfg = ctx.cfg
    data = jax.device_put(padding.padded(policy_transitions(cfg, ctx.ds, shaped.reward)))  # spot.padding
    init_key, _ = jax.random.split(ctx.keys["policy"])
    from spot.reward.train import clip_actions

    feedback = ipl.feedback_from(clip_actions(labelled.train_batch, cfg.iql.clip_action))
    state = ipl.init_state(init_key, ctx.ds.obs_dim, ctx.ds.act_dim, cfg.iql)
    chunk = ipl.make_train_chunk(cfg.iql, cfg.ipl)
    replay = data if cfg.ipl.use_replay else None
    policy = _train_policy(ctx, state, chunk, lambda key: (replay, feedback, key))
    # IPL's implied reward Q(s,a) - γV(s') summed over segments: how often it ranks the preferred
    # segment higher, on the training and held-out queries (reward/*, like the reward models').
    for name, batch in (("train", labelled.train_batch), ("eval", labelled.eval_batch)):
        if batch is not None:
            res = ipl.evaluate_preferences(policy.state, ipl.feedback_from(batch), cfg.iql, cfg.ipl)
            ctx.log({f"reward/{name}_acc": res["ipl/eval_pref_acc"], f"reward/{name}_loss": res["ipl/eval_pref_loss"]})
    return policy
