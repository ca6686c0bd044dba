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

Episodes are run and scored by :mod:`spot.evaluation`.
"""

from __future__ import annotations

import re
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


# ---------------------------------------------------------------- datasets against their env
ACTION_SLACK = 0.05
"""How far beyond its env's action bounds a dataset action may lie, as a fraction of the bounds'
width (evaluation clips to the bounds; real data recorded through a tanh or a clip lies inside)."""


_SIZES: dict[tuple, tuple[str, int, int, tuple[float, ...], tuple[float, ...]]] = {}


def _env_sizes(env_name: str) -> tuple[str, int, int, tuple[float, ...], tuple[float, ...]]:
    """``(env id, observation size, action size, action low, action high)`` of the evaluation env
    of ``env_name``, built once per env in a process: the datasets of one env (lift-ph and lift-mh,
    hopper-medium-replay and hopper-medium-expert) share it."""
    spec = env_spec(env_name)
    key = (spec.family, spec.env_id, spec.make_kwargs)
    if key not in _SIZES:
        _SIZES[key] = _built_sizes(env_name)
    return _SIZES[key]


def _built_sizes(env_name: str) -> tuple[str, int, int, tuple[float, ...], tuple[float, ...]]:
    """:func:`_env_sizes` read from a newly built env of ``env_name``."""
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
