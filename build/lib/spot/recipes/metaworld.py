"""Meta-World offline datasets built with IPL's recipe (Hejna & Sadigh 2023, Inverse Preference Learning).

Restates ``scripts/create_metaworld_offline_dataset.py`` of jhejna/inverse-preference-learning
(reference/algorithms.md §3.4) for Meta-World v3. Per task, equal numbers of episodes of four kinds:

* ``expert``: the task's scripted policy ``Sawyer<Task>V3Policy`` acting on the data env, with
  Gaussian action noise ``a + ε·N(0, I)``;
* ``within``: the same policy acting on a second env of the same task whose task (object and goal
  placement) is drawn independently ("rand vec unfrozen"); its noisy actions are executed in
  the data env too, so it solves a *different* placement than the one it acts in;
* ``random``: uniform random actions in [-1, 1];
* ``cross``: the scripted policy of a random *other* Meta-World v3 task, observing its own env
  of that task, with its noisy actions executed in the data env (IPL's ``random.choice`` could
  also pick the task itself; we exclude it).

Actions are clipped to ±(1 − 1e-5). An episode ends after 500 steps (``max_path_length``) or at
its 25th step with ``info["success"]`` (IPL counts successful steps down from 25; with a
persistent success this is 25 steps after the first). Either end is a truncation: ``timeouts``
is set on the last step and ``terminals`` stay 0 (Meta-World never terminates). Rewards are the
env's v2 reward function. ``metadata`` holds, per episode in order, its kind
(``"episode_kind"``) and the index within the episode of its first successful step, or -1
(``"episode_first_success"``); both are plain lists, so they survive the JSON metadata of
:func:`spot.data.formats.write_d4rl_hdf5`. The card has the success rate per kind.

Differences from IPL: the data env is goal-observable (the same env :func:`spot.envs.make_env`
evaluates in) where IPL's recorded goal-hidden observations; v3 envs instead of v2.

Sizes (episodes per kind): ``tiny`` 2 (tests), ``small`` 25, ``paper`` 100 (IPL's defaults).
Deterministic for a seed: placements, noise and cross-task choices all come from one seeded
numpy generator, and MuJoCo is deterministic.
"""

from __future__ import annotations

import time
import warnings
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

import spot
from spot import SpotError
from spot.data.dataset import RawDataset, raw_from_episodes
from spot.envs import METAWORLD_MAX_PATH_LENGTH, METAWORLD_TASKS, make_metaworld_env

SIZES = {"tiny": 2, "small": 25, "paper": 100}
KINDS = ("expert", "within", "random", "cross")
SUCCESS_STEPS = 25  # an episode ends at its 25th successful step (IPL)
ACTION_BOUND = 1.0 - 1e-5


def _episode(
    env: Any, policy_env: Any | None, policy: Any | None, epsilon: float, rng: np.random.Generator
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """One episode in ``env``; ``policy`` observes ``policy_env`` (or ``env`` when it is None).

    ``policy=None`` takes uniform random actions. Returns the episode in the
    :func:`raw_from_episodes` layout and its per-step success flags.
    """
    obs, _ = env.reset(seed=int(rng.integers(2**31)))
    policy_obs = obs if policy_env is None else policy_env.reset(seed=int(rng.integers(2**31)))[0]
    steps: dict[str, list] = {"observations": [], "actions": [], "rewards": [], "next_observations": []}
    successes: list[bool] = []
    for _ in range(METAWORLD_MAX_PATH_LENGTH):
        if policy is None:
            action = rng.uniform(-1.0, 1.0, size=4)
        else:
            action = policy.get_action(policy_obs) + epsilon * rng.standard_normal(4)
        action = np.clip(action, -ACTION_BOUND, ACTION_BOUND)
        next_obs, reward, _, truncated, info = env.step(action)
        policy_obs = next_obs if policy_env is None else policy_env.step(action)[0]
        for key, value in zip(steps, (obs, action, reward, next_obs), strict=True):
            steps[key].append(value)
        successes.append(bool(info["success"]))
        obs = next_obs
        if truncated or sum(successes) == SUCCESS_STEPS:
            break
    n = len(successes)
    episode = {k: np.asarray(v) for k, v in steps.items()}
    episode["terminals"] = np.zeros(n, dtype=bool)
    episode["timeouts"] = np.arange(n) == n - 1
    return episode, np.asarray(successes)


def build(
    name: str, size: str, seed: int, cache_dir: Path, progress: bool = True, epsilon: float = 1.0
) -> tuple[RawDataset, dict[str, Any]]:
    """Build the IPL Meta-World dataset for task ``name`` (e.g. ``"drawer-open"``).

    Args:
      name: one of :data:`spot.envs.METAWORLD_TASKS`.
      size: ``"tiny"``, ``"small"`` or ``"paper"`` (2, 25, 100 episodes of each kind).
      seed: seed of everything random in the build.
      cache_dir: unused; this recipe keeps no intermediate artifacts (common recipe signature).
      progress: show a tqdm bar over episodes.
      epsilon: std of the Gaussian action noise (IPL's ``--epsilon``, default 1.0).

    Returns:
      The raw dataset (obs 39-D, actions 4-D; per-episode kind and first success in
      ``metadata``) and its card.
    """
    del cache_dir
    if name not in METAWORLD_TASKS:
        raise SpotError(f"unknown Meta-World dataset '{name}'; expected one of {', '.join(METAWORLD_TASKS)}")
    if size not in SIZES:
        raise SpotError(f"unknown size '{size}' for dataset '{name}'; expected one of {', '.join(SIZES)}")
    from metaworld.policies import ENV_POLICY_MAP

    start = time.perf_counter()
    env_id = f"{name}-v3"
    per_kind = SIZES[size]
    rng = np.random.default_rng(seed)
    env = make_metaworld_env(env_id, int(rng.integers(2**31)))
    within_env = make_metaworld_env(env_id, int(rng.integers(2**31)))
    expert = ENV_POLICY_MAP[env_id]()
    others = sorted(k for k in ENV_POLICY_MAP if k != env_id)
    cross_envs: dict[str, Any] = {}

    episodes: list[dict[str, np.ndarray]] = []
    successes: list[np.ndarray] = []
    kinds: list[str] = []
    cross_tasks: list[str] = []
    bar = tqdm(total=per_kind * len(KINDS), desc=f"metaworld {name} ({size})", disable=not progress)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")
        for kind in KINDS:
            for _ in range(per_kind):
                policy_env, policy = None, expert  # kind == "expert"
                if kind == "within":
                    policy_env = within_env
                elif kind == "random":
                    policy = None
                elif kind == "cross":
                    other = others[int(rng.integers(len(others)))]
                    if other not in cross_envs:
                        cross_envs[other] = make_metaworld_env(other, int(rng.integers(2**31)))
                    policy_env, policy = cross_envs[other], ENV_POLICY_MAP[other]()
                    cross_tasks.append(other)
                ep, succ = _episode(env, policy_env, policy, epsilon, rng)
                episodes.append(ep)
                successes.append(succ)
                kinds.append(kind)
                bar.update()
    bar.close()
    for e in [env, within_env, *cross_envs.values()]:
        e.close()

    first_success = [int(np.argmax(s)) if s.any() else -1 for s in successes]
    raw = raw_from_episodes(
        episodes, name=f"{name}-{size}", metadata={"episode_kind": kinds, "episode_first_success": first_success}
    )
    returns = np.array([ep["rewards"].sum() for ep in episodes])
    lengths = np.array([len(ep["rewards"]) for ep in episodes])
    ever = np.array([s.any() for s in successes])
    kind_arr = np.array(kinds)

    def stats(x: np.ndarray) -> dict[str, float]:
        return {"mean": float(x.mean()), "std": float(x.std()), "min": float(x.min()), "max": float(x.max())}

    card = {
        "recipe": "ipl-metaworld",
        "name": name,
        "env": env_id,
        "size": size,
        "seed": seed,
        "epsilon": epsilon,
        "max_path_length": METAWORLD_MAX_PATH_LENGTH,
        "success_steps": SUCCESS_STEPS,
        "episodes": len(episodes),
        "episodes_per_kind": {k: int((kind_arr == k).sum()) for k in KINDS},
        "transitions": len(raw),
        "obs_dim": int(raw.observations.shape[1]),
        "act_dim": int(raw.actions.shape[1]),
        "return": stats(returns),
        "return_per_kind": {k: stats(returns[kind_arr == k]) for k in KINDS},
        "episode_length_per_kind": {k: float(lengths[kind_arr == k].mean()) for k in KINDS},
        "success_rate": float(ever.mean()),
        "success_rate_per_kind": {k: float(ever[kind_arr == k].mean()) for k in KINDS},
        "cross_tasks": cross_tasks,
        "build_time_s": round(time.perf_counter() - start, 2),
        "versions": {
            "spot": spot.__version__,
            **{p: version(p) for p in ("metaworld", "mujoco", "gymnasium", "numpy")},
        },
    }
    return raw, card
