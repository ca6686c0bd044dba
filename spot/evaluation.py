"""Evaluation: a policy's episodes in its dataset's env (:func:`spot.envs.make_env`), scored
(:func:`spot.envs.normalized_score`).

:func:`evaluate` runs its episodes together, and :func:`evaluate_runs` those of several runs (the
seeds of a vmapped trial): one policy call per step for all of them on one fixed-shape batch (an
ended episode's row holds its last observation), so a jitted policy is compiled once and called
``max_episode_steps`` times, not ``runs × episodes × max_episode_steps`` times. A policy that
computes each row alone (``spot.run.policy_stages.eval_policy``) gives every episode the numbers it gets
alone (:func:`evaluate_sequential`, tests/test_eval_batched.py); a matrix product's rows differ in
their last bits with the batch's size. Episode ``i`` gets its own env built and reset with
``seed + i``. The envs are kept for the next evaluation (:func:`pooled_env`): a run evaluates
with the same seeds every time, and building a robosuite env takes 1.5-3.5 s and about 140 MB that
closing it does not all give back, a Meta-World env about 0.5 s. A kept env is reset with the
episode's seed, which makes its episode that of a new env (tested per family). The envs of
several envs are kept (a reused sweep process moving between lift-mh, can-ph and drawer-open
builds each of their envs once, not once per trial), least recently used closed first, within two
bounds: at most :data:`MAX_LIVE` of a family alive at once, and the kept envs' estimated memory
(:data:`ENV_MB`) within :data:`POOL_MB`. An evaluation with more episodes than :data:`MAX_LIVE`
(robosuite's 30-episode final evaluations) runs them in waves of that many.

The locomotion envs skip gymnasium's ``step`` by default (``eval.stepper: mujoco``,
:func:`stepper_used`): :class:`spot.mujoco_step.LocomotionBatch` steps all of an evaluation's
episodes on their own ``MjData`` and computes their observations, rewards and terminations at once,
the same numbers to the last digit as their gymnasium envs (tests/test_eval_mujoco_step.py); no env
is kept for them. :func:`evaluate_sequential`, the reference, always runs the gymnasium envs.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from spot import SpotError
from spot.envs import env_spec, make_env, normalized_score

STEPPERS = ("mujoco", "gymnasium")
"""``eval.stepper``: MuJoCo stepped directly where :mod:`spot.mujoco_step` reproduces the env, or
always the gymnasium env's own ``step``."""
MAX_LIVE = {"robosuite": 10, "metaworld": 32, "locomotion": 32}
"""Most envs of a family alive at once: an evaluation with more episodes runs them in waves."""
ENV_MB = {"robosuite": 140, "metaworld": 32, "locomotion": 8}
"""About the memory one env of a family holds (resident set growth per env built: Lift ~130 MB,
Can ~100 MB, drawer-open ~32 MB)."""
POOL_MB = 1600
"""Most estimated memory (:data:`ENV_MB`) the kept envs may hold, those of the wave about to run
included: a full robosuite wave (10 envs) or a full Meta-World wave (32) fits, with room for a few
envs of other envs."""
_PoolKey = tuple[str, str, tuple, int, int]  # family, env id, make kwargs, seed, copy
_POOL: OrderedDict[_PoolKey, gym.Env] = OrderedDict()


def _pool_key(name: str, seed: int, copy: int = 0) -> _PoolKey:
    spec = env_spec(name)  # datasets of one env (hopper-medium-replay, hopper-medium-expert) share it
    return spec.family, spec.env_id, tuple(spec.make_kwargs), int(seed), copy


def _evict(victim: Callable[[_PoolKey], bool], keep: int) -> None:
    """Close kept envs, least recently used first, that ``victim`` selects, until ``keep`` remain
    among them."""
    chosen = [k for k in _POOL if victim(k)]
    for key in chosen[: max(0, len(chosen) - keep)]:
        _POOL.pop(key).close()


def _make_room(needed: set[_PoolKey]) -> None:
    """Close kept envs that ``needed`` (the envs of the wave about to run) does not name, least
    recently used first, until the family of ``needed`` has at most ``MAX_LIVE`` envs alive and
    the kept envs' :data:`ENV_MB` fit in :data:`POOL_MB` with those of ``needed``."""
    family = next(iter(needed))[0]
    _evict(lambda k: k[0] == family and k not in needed, MAX_LIVE[family] - len(needed))
    others = [k for k in _POOL if k not in needed]
    room = POOL_MB - sum(ENV_MB[k[0]] for k in needed)
    while others and sum(ENV_MB[k[0]] for k in others) > room:
        _POOL.pop(others.pop(0)).close()


def pooled_env(name: str, seed: int, copy: int = 0) -> gym.Env:
    """The evaluation env of ``name`` built with ``seed``: the one kept from an earlier evaluation of
    this process, else a new one (:func:`spot.envs.make_env`). Reset it with the episode's seed before use.
    ``copy`` numbers the envs of one seed that run at once (runs sharing a seed, evaluated together)."""
    key = _pool_key(name, seed, copy)
    env = _POOL.pop(key, None)
    _POOL[key] = env if env is not None else make_env(name, seed)  # most recently used last
    return _POOL[key]


def clear_env_pool() -> None:
    """Close every kept evaluation env."""
    _evict(lambda k: True, 0)


def _horizon(name: str, episodes: int, max_steps: int) -> int:
    """The steps an episode of an evaluation may take; its arguments checked."""
    if episodes < 1:
        raise SpotError(f"evaluate: episodes must be >= 1, got {episodes}")
    if max_steps < 0:
        raise SpotError(f"evaluate: max_steps must be >= 0 (0 = the env's horizon), got {max_steps}")
    spec = env_spec(name)
    return min(spec.max_episode_steps, max_steps) if max_steps else spec.max_episode_steps


def _summary(name: str, returns: np.ndarray, lengths: np.ndarray, successes: np.ndarray) -> dict[str, Any]:
    """The result of :func:`evaluate` from its per-episode returns, lengths and successes."""
    spec = env_spec(name)
    scores = normalized_score(name, returns if spec.score == "d4rl" else successes.astype(np.float64))
    return {
        "score_mean": float(scores.mean()),
        "score_std": float(scores.std()),
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "success_rate": float(successes.mean()) if spec.score == "success" else float("nan"),
        "episode_length_mean": float(lengths.mean()),
        "scores": scores,
        "returns": returns,
        "lengths": lengths,
    }


def _actions(policy_fn: Callable[[np.ndarray], Any], obs: np.ndarray, space: gym.spaces.Box, name: str) -> np.ndarray:
    """``policy_fn(obs)`` as float64 actions clipped to ``space``; its shape checked."""
    actions = np.asarray(policy_fn(obs), dtype=np.float64)
    want = (*obs.shape[:-1], space.low.shape[0])
    if actions.shape != want:
        raise SpotError(
            f"evaluate('{name}'): policy_fn returned actions of shape {actions.shape} for observations "
            f"of shape {obs.shape}; expected {want}"
        )
    return np.clip(actions, space.low, space.high)


def _wave_envs(name: str, env_seeds: list[int]) -> list[gym.Env]:
    """The envs of one wave's episodes (:func:`pooled_env`), reset by the caller; an episode seed
    that several runs of the wave share (members of one seed) gets one env per run."""
    copies = [env_seeds[:j].count(s) for j, s in enumerate(env_seeds)]
    _make_room({_pool_key(name, s, c) for s, c in zip(env_seeds, copies, strict=True)})
    return [pooled_env(name, s, c) for s, c in zip(env_seeds, copies, strict=True)]


def _run_wave(policy_fn: Callable[[np.ndarray], Any], name: str, env_seeds: np.ndarray, horizon: int) -> tuple:
    """Step the episodes seeded ``env_seeds [R, n]`` together in gymnasium envs, one ``policy_fn``
    call per step on all ``R·n`` observations ``[R, n, obs_dim]`` (an ended episode's row holds its
    last observation; its action is not used); ``(returns, lengths, successes)``, each ``[R, n]``."""
    flat = [int(s) for s in env_seeds.reshape(-1)]
    envs = _wave_envs(name, flat)
    returns, lengths = np.zeros(len(flat)), np.zeros(len(flat), dtype=np.int64)
    successes, running = np.zeros(len(flat), dtype=bool), np.ones(len(flat), dtype=bool)
    obs = np.stack([env.reset(seed=s)[0] for s, env in zip(flat, envs, strict=True)]).astype(np.float32)
    for _ in range(horizon):
        if not running.any():
            break
        actions = _actions(policy_fn, obs.reshape(*env_seeds.shape, -1), envs[0].action_space, name)
        actions = actions.reshape(len(flat), -1)
        for j in np.flatnonzero(running):
            o, r, terminated, truncated, info = envs[j].step(actions[j])
            obs[j] = o
            returns[j] += float(r)
            lengths[j] += 1
            successes[j] |= bool(info.get("success", False))
            running[j] = not (terminated or truncated)
    return tuple(a.reshape(env_seeds.shape) for a in (returns, lengths, successes))


def _run_wave_mujoco(policy_fn: Callable[[np.ndarray], Any], name: str, env_seeds: np.ndarray, horizon: int) -> tuple:
    """:func:`_run_wave` with MuJoCo stepped directly (:class:`spot.mujoco_step.LocomotionBatch`):
    the same episodes, each env step of all running episodes computed at once."""
    from spot.mujoco_step import LocomotionBatch

    flat = [int(s) for s in env_seeds.reshape(-1)]
    batch = LocomotionBatch(name, len(flat))
    returns, lengths = np.zeros(len(flat)), np.zeros(len(flat), dtype=np.int64)
    running = np.ones(len(flat), dtype=bool)
    obs = batch.reset(flat).astype(np.float32)
    for _ in range(horizon):
        if not running.any():
            break
        actions = _actions(policy_fn, obs.reshape(*env_seeds.shape, -1), batch.action_space, name)
        idx = np.flatnonzero(running)
        o, rewards, terminated = batch.step(idx, actions.reshape(len(flat), -1)[idx])
        obs[idx] = o
        returns[idx] += rewards
        lengths[idx] += 1
        running[idx] = ~terminated
    return tuple(a.reshape(env_seeds.shape) for a in (returns, lengths, np.zeros(len(flat), dtype=bool)))


def stepper_used(name: str, stepper: str) -> str:
    """The stepper an evaluation of ``name`` with ``eval.stepper = stepper`` runs on: ``"mujoco"``
    (MuJoCo stepped directly, :mod:`spot.mujoco_step`) for the locomotion envs when asked, else
    ``"gymnasium"`` (the env's own ``step``)."""
    from spot import mujoco_step

    if stepper not in STEPPERS:
        raise SpotError(f"eval.stepper: expected one of {', '.join(STEPPERS)}, got '{stepper}'")
    return "mujoco" if stepper == "mujoco" and mujoco_step.supports(name) else "gymnasium"


def evaluate_runs(
    policy_fn: Callable[[np.ndarray], Any],
    name: str,
    episodes: int,
    seeds: list[int],
    max_steps: int = 0,
    stepper: str = "mujoco",
) -> list[dict[str, Any]]:
    """Evaluate the policies of several runs (the seeds of a vmapped trial) in ``episodes`` episodes
    each, all episodes stepped together: one ``policy_fn`` call per env step.

    Args:
      policy_fn: maps observations ``[R, n, obs_dim]`` (float32 numpy; run ``r``'s ``n`` episodes
        in row ``r``) to actions ``[R, n, act_dim]``, clipped to the action space. Rows of episodes
        that have ended hold their last observation; their actions are not used. An episode's
        numbers are those it gets alone (:func:`evaluate_sequential`) when ``policy_fn`` computes
        each row's action from that row alone (``spot.run.policy_stages.eval_policy``).
      name: dataset name (see :func:`spot.envs.env_spec`).
      episodes: episodes per run; run ``r``'s episode ``i`` runs in the env built and reset with
        ``seeds[r] + i`` (kept between evaluations, :func:`pooled_env`); at most
        ``MAX_LIVE[family]`` envs at once (waves of ``MAX_LIVE // R`` episodes per run, at least 1).
      seeds: each run's base seed (``R`` runs).
      max_steps: cut every episode after this many steps (``eval.max_steps``: smoke checks); 0 =
        the env's horizon.
      stepper: ``eval.stepper`` (:func:`stepper_used`): ``"mujoco"`` steps the locomotion envs'
        MuJoCo directly (:mod:`spot.mujoco_step`; every episode in one wave, no env kept), the same
        numbers as their gymnasium envs; other envs, and ``"gymnasium"``, run the gymnasium envs.

    Returns:
      one result per run, as :func:`evaluate`'s.
    """
    horizon, runs = _horizon(name, episodes, max_steps), len(seeds)
    if not seeds:
        raise SpotError("evaluate: expected at least one run's seed")
    direct = stepper_used(name, stepper) == "mujoco"
    out = [np.zeros((runs, episodes)), np.zeros((runs, episodes), dtype=np.int64), np.zeros((runs, episodes), bool)]
    wave = episodes if direct else max(1, MAX_LIVE[env_spec(name).family] // runs)
    run_wave = _run_wave_mujoco if direct else _run_wave
    try:
        for start in range(0, episodes, wave):
            ids = np.arange(start, min(start + wave, episodes))
            for whole, part in zip(out, run_wave(policy_fn, name, np.add.outer(seeds, ids), horizon), strict=True):
                whole[:, ids] = part
    except BaseException:
        clear_env_pool()  # an env left mid-episode by an error is not kept
        raise
    return [_summary(name, *(a[r].copy() for a in out)) for r in range(runs)]


def evaluate(
    policy_fn: Callable[[np.ndarray], Any],
    name: str,
    episodes: int,
    seed: int,
    max_steps: int = 0,
    stepper: str = "mujoco",
) -> dict[str, Any]:
    """Run ``episodes`` episodes of ``policy_fn`` together and score them (:func:`evaluate_runs`
    for one run).

    Args:
      policy_fn: maps observations ``[n, obs_dim]`` (float32 numpy) of the ``n`` episodes of a wave
        to actions ``[n, act_dim]``, once per step; rows of ended episodes hold their last
        observation and their actions are not used.
      name: dataset name (see :func:`spot.envs.env_spec`).
      episodes: number of episodes; episode ``i`` runs in the env built and reset with ``seed + i``
        (kept between evaluations, :func:`pooled_env`); at most ``MAX_LIVE[family]`` at once.
      seed: base seed.
      max_steps: cut every episode after this many steps (``eval.max_steps``: smoke checks); 0 =
        the env's horizon.
      stepper: ``eval.stepper``, as in :func:`evaluate_runs`.

    Returns:
      ``score_mean``, ``score_std`` (normalised, see :func:`spot.envs.normalized_score`), ``return_mean``,
      ``return_std``, ``success_rate`` (NaN for locomotion), ``episode_length_mean``, and the
      per-episode arrays ``scores``, ``returns``, ``lengths``.
    """
    runs = evaluate_runs(lambda obs: np.asarray(policy_fn(obs[0]))[None], name, episodes, [seed], max_steps, stepper)
    return runs[0]


def evaluate_sequential(
    policy_fn: Callable[[np.ndarray], Any], name: str, episodes: int, seed: int, max_steps: int = 0
) -> dict[str, Any]:
    """:func:`evaluate`'s reference: the episodes one after another, ``policy_fn`` called on one
    observation ``[1, obs_dim]`` per step (the envs and seeds of :func:`evaluate`). Used by the
    tests and ``spot bench eval``."""
    horizon = _horizon(name, episodes, max_steps)
    returns, lengths = np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
    successes = np.zeros(episodes, dtype=bool)
    try:
        for i in range(episodes):
            _make_room({_pool_key(name, seed + i)})
            env = pooled_env(name, seed + i)
            obs = env.reset(seed=seed + i)[0]
            for _ in range(horizon):
                action = _actions(policy_fn, np.asarray(obs, np.float32)[None], env.action_space, name)[0]
                obs, r, terminated, truncated, info = env.step(action)
                returns[i] += float(r)
                lengths[i] += 1
                successes[i] |= bool(info.get("success", False))
                if terminated or truncated:
                    break
    except BaseException:
        clear_env_pool()
        raise
    return _summary(name, returns, lengths, successes)
