"""Evaluation environments, the dataset-name -> environment map, and score normalisation.

Three families, each evaluated the way its reference papers report it:

* **locomotion** (``hopper-*``, ``walker2d-*``, ``halfcheetah-*``; a trailing ``-v2`` is dropped):
  gymnasium's MuJoCo ``Hopper-v5`` / ``Walker2d-v5`` / ``HalfCheetah-v5`` in the *model D4RL's data
  were recorded in*. D4RL's ``-v2`` datasets come from the mujoco-py ``-v3`` envs, which cannot run
  here. ``Walker2d-v5``'s own model gives both feet friction 1.9, while the v2-v4 model has 0.9 on
  the right foot (gymnasium's v5 version notes), so walker2d runs in ``Walker2d-v5`` with
  gymnasium's bundled v2-v4 ``walker2d.xml`` (:data:`LOCOMOTION_MODELS`). ``Hopper-v5`` and
  ``HalfCheetah-v5`` load the same xml as their v2-v4 versions. Every v5 env differs from v2-v4 in
  one reward detail: no healthy reward on the terminating step (at most 1 of an episode's return,
  about 0.02 normalised points for Hopper). Score: the D4RL normalised return ``100 · (R − R_random) / (R_expert −
  R_random)``
  with the ``-random-v0`` / expert references of ``d4rl/infos.py`` that the ``-v2`` datasets
  inherit (reference/algorithms.md §2.4; PT's ``EpisodeMonitor`` multiplies by 100).
* **metaworld** (``drawer-open``, ``plate-slide``, ``button-press``): the goal-observable v3
  single-task env, 500 steps. Score: 100 × success rate, an episode counting as a success if
  ``info["success"]`` was ever true (IPL's ``EvalMetricTracker``). Episodes run the full 500 steps.
* **robosuite** (``lift-ph``, ``lift-mh``, ``can-ph``, ``can-mh``): robosuite 1.5.1 ``Lift`` /
  ``PickPlaceCan`` with a Panda under the default composite OSC_POSE controller, sparse reward,
  20 Hz, horizon 500 as in IPL's ``RoboMimicEnv``; the observation is the robomimic ``low_dim``
  concatenation IPL reads (:data:`spot.data.formats.ROBOMIMIC_OBS_KEYS`, robomimic's ``object``
  being robosuite's ``object-state``: Lift 49-D, Can 53-D). An episode ends at the
  first success (IPL). Score: 100 × success rate.

Meta-World environments are built from the goal-observable class directly rather than through
``gym.make("Meta-World/MT1")``: MT1 pre-samples 50 fixed tasks per env and then picks one per
reset, while here each reset draws the task (object and goal placement) from the same uniform
distribution with the env's own seeded RNG, which is also cheaper to build (docs/benchmarks.md). IPL's data and
evaluation env likewise re-draw the task at every reset.

:func:`evaluate` runs its episodes together, and :func:`evaluate_runs` those of several runs (the
seeds of a vmapped trial): one policy call per step for all of them on one fixed-shape batch (an
ended episode's row holds its last observation), so a jitted policy is compiled once and called
``max_episode_steps`` times, not ``runs × episodes × max_episode_steps`` times. A policy that
computes each row alone (``spot.stages.eval_policy``) gives every episode the numbers it gets
alone (:func:`evaluate_sequential`, tests/test_eval_batched.py); a matrix product's rows differ in
their last bits with the batch's size. Episode ``i`` gets its own env built and reset with
``seed + i``. The envs are kept for the next evaluation (:func:`pooled_env`): a run evaluates
with the same seeds every time, and building a robosuite env takes 1.5-3.5 s and about 140 MB that
closing it does not all give back, a Meta-World env about 0.5 s. A kept env is reset with the
episode's seed, which makes its episode that of a new env (tested per family). Only the envs of
the env last evaluated are kept, at most :data:`MAX_LIVE` of its family (least recently used go),
and at most that many are alive at once: more episodes than that (robosuite's 30-episode final
evaluations) run in waves of that many.
"""

from __future__ import annotations

import functools
import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np

from spot import SpotError
from spot.data.dataset import Dataset
from spot.data.formats import ROBOMIMIC_OBS_KEYS
from spot.data.registry import D4RL_FILE_STEMS

Family = Literal["locomotion", "metaworld", "robosuite"]
ScoreKind = Literal["d4rl", "success"]

# D4RL reference returns (random, expert) from d4rl/infos.py, reference/algorithms.md §2.4.
D4RL_REF_SCORES: dict[str, tuple[float, float]] = {
    "hopper": (-20.272305, 3234.3),
    "walker2d": (1.629008, 4592.3),
    "halfcheetah": (-280.178953, 12135.0),
}
_LOCOMOTION_ENV_IDS = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "halfcheetah": "HalfCheetah-v5"}
# Model files (in gymnasium's MuJoCo assets) for envs whose v5 default model is not the v2-v4 one
# D4RL recorded in: walker2d.xml keeps the feet frictions 0.9 / 1.9 (walker2d_v5.xml: 1.9 / 1.9).
LOCOMOTION_MODELS = {"walker2d": "walker2d.xml"}
_LOCOMOTION_DATASETS = ("random", "medium", "expert", "medium-replay", "medium-expert", "full-replay")

METAWORLD_TASKS = ("drawer-open", "plate-slide", "button-press")
METAWORLD_MAX_PATH_LENGTH = 500

_ROBOSUITE_ENV_IDS = {"lift": "Lift", "can": "PickPlaceCan"}
ROBOSUITE_HORIZON = 500


@dataclass(frozen=True)
class EnvSpec:
    """Where a dataset's policies are evaluated.

    Attributes:
      name: the canonical dataset name (``-v2`` dropped), e.g. ``"hopper-medium-replay"``.
      family: ``"locomotion"``, ``"metaworld"`` or ``"robosuite"``.
      env_id: ``"Hopper-v5"``, ``"drawer-open-v3"``, ``"Lift"``, ...
      max_episode_steps: evaluation episode length limit.
      score: ``"d4rl"`` (normalised return) or ``"success"`` (100 × success rate).
      make_kwargs: extra ``gym.make`` keyword arguments (locomotion: the model file), as pairs.
    """

    name: str
    family: Family
    env_id: str
    max_episode_steps: int
    score: ScoreKind
    make_kwargs: tuple[tuple[str, Any], ...] = ()


def locomotion_make_kwargs(env: str) -> tuple[tuple[str, Any], ...]:
    """``gym.make`` kwargs that select the v2-v4 model of locomotion env ``env`` (``"walker2d"``)."""
    if env not in LOCOMOTION_MODELS:
        return ()
    import gymnasium.envs.mujoco as mujoco_envs

    xml = Path(mujoco_envs.__file__).parent / "assets" / LOCOMOTION_MODELS[env]
    return (("xml_file", str(xml)),)


def valid_names() -> list[str]:
    """Every dataset name :func:`env_spec` accepts (without the optional ``-v2`` suffix)."""
    loco = [f"{env}-{kind}" for env in _LOCOMOTION_ENV_IDS for kind in _LOCOMOTION_DATASETS]
    robo = [f"{task}-{src}" for task in _ROBOSUITE_ENV_IDS for src in ("ph", "mh")]
    return loco + list(METAWORLD_TASKS) + robo


def env_spec(dataset_name: str) -> EnvSpec:
    """Map a dataset name to its evaluation environment; raise :class:`SpotError` if unknown.

    D4RL's file stems (``hopper_medium_replay-v2``) name their datasets too
    (:data:`spot.data.registry.D4RL_FILE_STEMS`).
    """
    name = dataset_name.strip()
    name = re.sub(r"-v2$", "", D4RL_FILE_STEMS.get(name, name))
    env, _, kind = name.partition("-")
    if env in _LOCOMOTION_ENV_IDS and kind in _LOCOMOTION_DATASETS:
        return EnvSpec(name, "locomotion", _LOCOMOTION_ENV_IDS[env], 1000, "d4rl", locomotion_make_kwargs(env))
    if name in METAWORLD_TASKS:
        return EnvSpec(name, "metaworld", f"{name}-v3", METAWORLD_MAX_PATH_LENGTH, "success")
    if env in _ROBOSUITE_ENV_IDS and kind in ("ph", "mh"):
        return EnvSpec(name, "robosuite", _ROBOSUITE_ENV_IDS[env], ROBOSUITE_HORIZON, "success")
    raise SpotError(
        f"unknown dataset name '{dataset_name}'; expected one of: {', '.join(valid_names())} "
        "(locomotion names may end in -v2; a dataset file is named by its real name: D4RL's "
        "<env>_<kind>-v2.hdf5, robomimic's <task>/<ph|mh>/low_dim.hdf5)"
    )


# --------------------------------------------------------------------------- environments
class _MetaWorldTaskPerReset(gym.Wrapper):
    """Re-seedable Meta-World env: ``reset(seed=k)`` reseeds the task RNG (SawyerXYZEnv ignores it)."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        if seed is not None:
            self.env.unwrapped.seed(seed)
        return self.env.reset(options=options)


def make_metaworld_env(env_id: str, seed: int) -> gym.Env:
    """Goal-observable Meta-World v3 env (e.g. ``"drawer-open-v3"``), a new task every reset.

    Each reset draws the object/goal placement uniformly from the task's reset space with the
    env's RNG, which ``seed`` (and any later ``reset(seed=...)``) seeds. Observation ``(39,)``,
    action ``(4,)`` in [-1, 1]; ``truncated`` is set at step 500.
    """
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    key = f"{env_id}-goal-observable"
    if key not in ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE:
        raise SpotError(f"unknown Meta-World v3 env '{env_id}'")
    raw = ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[key](seed=seed)
    raw._freeze_rand_vec = False  # draw a new task at each reset ...
    raw.seeded_rand_vec = True  # ... from raw.np_random, not the global numpy RNG
    env = _MetaWorldTaskPerReset(raw)
    env.reset(seed=seed)
    return env


class _RobosuiteEnv(gym.Env):
    """robosuite Lift / PickPlaceCan as a gymnasium env with the robomimic low_dim observation.

    ``terminated`` is set at the first success (IPL's ``RoboMimicEnv``), ``truncated`` at the
    horizon. robosuite 1.5.1 draws model parameters (Lift's cube size) when it builds the env and
    object placements at every reset from the global numpy RNG, so construction seeds it from
    ``seed`` and each reset from this env's RNG, and both restore it afterwards: envs built with
    the same seed are identical in any process.
    """

    def __init__(self, env_id: str, seed: int, horizon: int = ROBOSUITE_HORIZON) -> None:
        try:
            import robosuite
        except ImportError as e:
            raise SpotError("robosuite evaluation needs robosuite 1.5.1: pip install 'spot-pbrl[robosuite]'") from e
        global_state = np.random.get_state()
        np.random.seed(seed)
        try:
            self._env = robosuite.make(
                env_id,
                robots="Panda",
                controller_configs=robosuite.load_composite_controller_config(robot="Panda"),
                has_renderer=False,
                has_offscreen_renderer=False,
                use_camera_obs=False,
                use_object_obs=True,
                reward_shaping=False,
                control_freq=20,
                horizon=horizon,
                ignore_done=True,
                hard_reset=False,
            )
            obs = self._flatten(self._env.reset())
        finally:
            np.random.set_state(global_state)
        self._horizon = horizon
        self._t = 0
        low, high = self._env.action_spec
        self.action_space = gym.spaces.Box(low.astype(np.float32), high.astype(np.float32))
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, obs.shape, np.float64)
        self.reset(seed=seed)

    @staticmethod
    def _flatten(obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([obs["object-state" if k == "object" else k] for k in ROBOMIMIC_OBS_KEYS]).astype(
            np.float64
        )

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        global_state = np.random.get_state()
        np.random.seed(int(self.np_random.integers(2**31)))
        try:
            obs = self._env.reset()
        finally:
            np.random.set_state(global_state)
        self._t = 0
        return self._flatten(obs), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, reward, _, info = self._env.step(np.asarray(action, dtype=np.float64))
        self._t += 1
        success = bool(self._env._check_success())
        info = dict(info, success=success)
        return self._flatten(obs), float(reward), success, self._t >= self._horizon, info

    def staged_reward(self) -> float:
        """robosuite's dense staged reward of the current state, in [0, 1].

        The env's own ``reward()`` with ``reward_shaping=True`` (the env itself keeps the sparse
        reward): Lift (reach + grasp) / 2.25; PickPlaceCan max(reach, grasp, lift, hover); 1 at
        success in both.
        """
        self._env.reward_shaping = True
        try:
            return float(self._env.reward())
        finally:
            self._env.reward_shaping = False

    def close(self) -> None:
        self._env.close()


def make_env(name: str, seed: int) -> gym.Env:
    """A headless evaluation env for dataset ``name``, reset once with ``seed``.

    Later ``reset()`` calls continue the seeded stream; ``reset(seed=k)`` reseeds.
    """
    spec = env_spec(name)
    if spec.family == "locomotion":
        env = gym.make(spec.env_id, **dict(spec.make_kwargs))
        env.reset(seed=seed)
        env.action_space.seed(seed)
        return env
    if spec.family == "metaworld":
        return make_metaworld_env(spec.env_id, seed)
    return _RobosuiteEnv(spec.env_id, seed)


# --------------------------------------------------------------------------- scores
def normalized_score(name: str, returns_or_successes: Any) -> np.ndarray:
    """Per-episode normalised score, same shape as the input (float64).

    Locomotion: ``100 · (R − R_random) / (R_expert − R_random)`` (D4RL). Meta-World and
    robosuite: ``100 · success`` with success in {0, 1}, so the mean is 100 × success rate.
    """
    spec = env_spec(name)
    values = np.asarray(returns_or_successes, dtype=np.float64)
    if spec.score == "d4rl":
        lo, hi = D4RL_REF_SCORES[spec.name.split("-")[0]]
        return 100.0 * (values - lo) / (hi - lo)
    if not np.all((values == 0.0) | (values == 1.0)):
        raise SpotError(
            f"normalized_score('{name}'): expected per-episode successes in {{0, 1}}, got values "
            f"in [{values.min()}, {values.max()}]"
        )
    return 100.0 * values


MAX_LIVE = {"robosuite": 10, "metaworld": 32, "locomotion": 32}
"""Most envs of a family alive at once: an evaluation with more episodes runs them in waves."""
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


def pooled_env(name: str, seed: int, copy: int = 0) -> gym.Env:
    """The evaluation env of ``name`` built with ``seed``: the one kept from an earlier evaluation of
    this process, else a new one (:func:`make_env`). Reset it with the episode's seed before use.
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
    needed = {_pool_key(name, s, c) for s, c in zip(env_seeds, copies, strict=True)}
    _evict(lambda k: k not in needed, MAX_LIVE[env_spec(name).family] - len(needed))  # MAX_LIVE alive
    return [pooled_env(name, s, c) for s, c in zip(env_seeds, copies, strict=True)]


def _run_wave(policy_fn: Callable[[np.ndarray], Any], name: str, env_seeds: np.ndarray, horizon: int) -> tuple:
    """Step the episodes seeded ``env_seeds [R, n]`` together, one ``policy_fn`` call per step on
    all ``R·n`` observations ``[R, n, obs_dim]`` (an ended episode's row holds its last observation;
    its action is not used); ``(returns, lengths, successes)``, each ``[R, n]``."""
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


def evaluate_runs(
    policy_fn: Callable[[np.ndarray], Any], name: str, episodes: int, seeds: list[int], max_steps: int = 0
) -> list[dict[str, Any]]:
    """Evaluate the policies of several runs (the seeds of a vmapped trial) in ``episodes`` episodes
    each, all episodes stepped together: one ``policy_fn`` call per env step.

    Args:
      policy_fn: maps observations ``[R, n, obs_dim]`` (float32 numpy; run ``r``'s ``n`` episodes
        in row ``r``) to actions ``[R, n, act_dim]``, clipped to the action space. Rows of episodes
        that have ended hold their last observation; their actions are not used. An episode's
        numbers are those it gets alone (:func:`evaluate_sequential`) when ``policy_fn`` computes
        each row's action from that row alone (``spot.stages.eval_policy``).
      name: dataset name (see :func:`env_spec`).
      episodes: episodes per run; run ``r``'s episode ``i`` runs in the env built and reset with
        ``seeds[r] + i`` (kept between evaluations, :func:`pooled_env`); at most
        ``MAX_LIVE[family]`` envs at once (waves of ``MAX_LIVE // R`` episodes per run, at least 1).
      seeds: each run's base seed (``R`` runs).
      max_steps: cut every episode after this many steps (``eval.max_steps``: smoke checks); 0 =
        the env's horizon.

    Returns:
      one result per run, as :func:`evaluate`'s.
    """
    horizon, runs = _horizon(name, episodes, max_steps), len(seeds)
    if not seeds:
        raise SpotError("evaluate: expected at least one run's seed")
    out = [np.zeros((runs, episodes)), np.zeros((runs, episodes), dtype=np.int64), np.zeros((runs, episodes), bool)]
    wave = max(1, MAX_LIVE[env_spec(name).family] // runs)
    this_env = _pool_key(name, seeds[0])[:3]
    _evict(lambda k: k[:3] != this_env, 0)  # a reused process moving on to another env frees the last one's
    try:
        for start in range(0, episodes, wave):
            ids = np.arange(start, min(start + wave, episodes))
            for whole, part in zip(out, _run_wave(policy_fn, name, np.add.outer(seeds, ids), horizon), strict=True):
                whole[:, ids] = part
    except BaseException:
        clear_env_pool()  # an env left mid-episode by an error is not kept
        raise
    return [_summary(name, *(a[r].copy() for a in out)) for r in range(runs)]


def evaluate(
    policy_fn: Callable[[np.ndarray], Any], name: str, episodes: int, seed: int, max_steps: int = 0
) -> dict[str, Any]:
    """Run ``episodes`` episodes of ``policy_fn`` together and score them (:func:`evaluate_runs`
    for one run).

    Args:
      policy_fn: maps observations ``[n, obs_dim]`` (float32 numpy) of the ``n`` episodes of a wave
        to actions ``[n, act_dim]``, once per step; rows of ended episodes hold their last
        observation and their actions are not used.
      name: dataset name (see :func:`env_spec`).
      episodes: number of episodes; episode ``i`` runs in the env built and reset with ``seed + i``
        (kept between evaluations, :func:`pooled_env`); at most ``MAX_LIVE[family]`` at once.
      seed: base seed.
      max_steps: cut every episode after this many steps (``eval.max_steps``: smoke checks); 0 =
        the env's horizon.

    Returns:
      ``score_mean``, ``score_std`` (normalised, see :func:`normalized_score`), ``return_mean``,
      ``return_std``, ``success_rate`` (NaN for locomotion), ``episode_length_mean``, and the
      per-episode arrays ``scores``, ``returns``, ``lengths``.
    """
    return evaluate_runs(lambda obs: np.asarray(policy_fn(obs[0]))[None], name, episodes, [seed], max_steps)[0]


def evaluate_sequential(
    policy_fn: Callable[[np.ndarray], Any], name: str, episodes: int, seed: int, max_steps: int = 0
) -> dict[str, Any]:
    """:func:`evaluate`'s reference: the episodes one after another, ``policy_fn`` called on one
    observation ``[1, obs_dim]`` per step (the envs and seeds of :func:`evaluate`). Used by the
    tests and ``spot bench eval``."""
    horizon = _horizon(name, episodes, max_steps)
    returns, lengths = np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
    successes = np.zeros(episodes, dtype=bool)
    _evict(lambda k: k[:3] != _pool_key(name, seed)[:3], 0)
    try:
        for i in range(episodes):
            _evict(lambda k, i=i: k != _pool_key(name, seed + i), MAX_LIVE[env_spec(name).family] - 1)
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


# ---------------------------------------------------------------- datasets against their env
ACTION_SLACK = 0.05
"""How far beyond its env's action bounds a dataset action may lie, as a fraction of the bounds'
width (evaluation clips to the bounds; real data recorded through a tanh or a clip lies inside)."""


@functools.lru_cache(maxsize=8)
def _env_sizes(env_name: str) -> tuple[str, int, int, tuple[float, ...], tuple[float, ...]]:
    """``(env id, observation size, action size, action low, action high)`` of the evaluation env
    of ``env_name`` (built once)."""
    env = make_env(env_name, 0)
    try:
        obs, space = env.observation_space.shape, env.action_space
        low = tuple(np.broadcast_to(space.low, space.shape).reshape(-1).astype(float))
        high = tuple(np.broadcast_to(space.high, space.shape).reshape(-1).astype(float))
        return env_spec(env_name).env_id, int(np.prod(obs)), int(np.prod(space.shape)), low, high
    finally:
        env.close()


def check_against_env(ds: Dataset, env_name: str, where: str) -> None:
    """Raise :class:`SpotError` unless the dataset's observation and action sizes are those of the
    env its policy is evaluated in, and its actions lie in that env's action space (up to
    :data:`ACTION_SLACK` of the bounds' width beyond them). Checked before any training: a size
    mismatch would otherwise fail only at the first evaluation, after the reward model and much of
    IQL, and actions far outside the space train a policy on nothing the env accepts."""
    env_id, obs_dim, act_dim, low, high = _env_sizes(env_name)
    for what, got, want in (("observation", ds.obs_dim, obs_dim), ("action", ds.act_dim, act_dim)):
        if got != want:
            raise SpotError(
                f"{where}: {what}s have {got} dimensions, but the evaluation env of '{env_name}' ({env_id}) "
                f"has {want}; expected a dataset recorded in that env"
            )
    lo, hi = np.asarray(low), np.asarray(high)
    slack = ACTION_SLACK * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
    outside = (ds.actions < lo - slack) | (ds.actions > hi + slack)
    if outside.any():
        row, col = (int(i) for i in np.argwhere(outside)[0])
        raise SpotError(
            f"{where}: 'actions' has the value {float(ds.actions[row, col]):g} in column {col} at row "
            f"{int(ds.raw_index[row])} ({int(outside.sum())} values outside); expected the action space "
            f"of {env_id}, [{lo[col]:g}, {hi[col]:g}] (up to {ACTION_SLACK:.0%} of its width beyond)"
        )


def check_fits_env(ds: Dataset, card: dict[str, Any], env_name: str) -> None:
    """:func:`check_against_env` for a loaded dataset, the error naming its file."""
    where = f"dataset file '{card['path']}'" if card.get("path") else f"dataset '{card.get('name') or ds.name}'"
    check_against_env(ds, env_name, where)
