"""Gymnasium's MuJoCo locomotion envs stepped directly, many episodes at once.

:class:`LocomotionBatch` runs ``n`` episodes of ``Hopper-v5``, ``Walker2d-v5`` or ``HalfCheetah-v5``
on one ``MjModel`` and one ``MjData`` per episode, and computes their observations, rewards and
terminations with numpy over all episodes at once, with the formulas of gymnasium 1.x's
``hopper_v5.py``, ``walker2d_v5.py`` and ``half_cheetah_v5.py``:

* **step**: ``ctrl = action``, ``mj_step(model, data, nstep=frame_skip)``; ``x_velocity = (x_after
  − x_before) / dt`` with ``dt = timestep · frame_skip``; reward ``forward_weight · x_velocity +
  healthy · healthy_reward − ctrl_weight · Σ action²`` (HalfCheetah: no healthy term), the healthy
  term judged on the state *after* the step (so none on a terminating step); ``terminated = not
  healthy`` (HalfCheetah never terminates). gymnasium also calls ``mj_rnePostConstraint`` after the
  step; it fills only ``cacc`` / ``cfrc_int`` / ``cfrc_ext``, which neither the formulas here nor the
  next ``mj_step`` read (these models have no sensors), so it is left out.
* **healthy**: Hopper ``z ∈ (0.7, ∞)``, ``angle ∈ (−0.2, 0.2)`` and every entry of ``(qpos[2:],
  qvel)`` in ``(−100, 100)``; Walker2d ``z ∈ (0.8, 2)``, ``angle ∈ (−1, 1)`` (open intervals).
* **observation**: ``(qpos[1:], clip(qvel, −10, 10))`` (HalfCheetah: ``qvel`` unclipped).
* **reset with seed s**: the env's RNG is ``gymnasium.utils.seeding.np_random(s)`` (what
  ``Env.reset(seed=s)`` makes), ``mj_resetData``, ``qpos = init_qpos + U(−scale, scale, nq)``, then
  ``qvel = init_qvel + U(−scale, scale, nv)`` (HalfCheetah ``+ scale · N(0, 1)``), ``mj_forward``.

The parameters (frame skip, weights, ranges, noise scale, initial state, model) are read from an
instance of gymnasium's own env class built as :func:`spot.envs.make_env` builds it (walker2d on
its v2-v4 model), so each episode is the gymnasium env's episode with the same seed and actions to
the last digit: every number goes through the same float64 operations in the same order
(tests/test_eval_mujoco_step.py compares returns and lengths exactly). The ``TimeLimit``
truncation is the caller's (:mod:`spot.evaluation` cuts at the horizon).
"""

from __future__ import annotations

import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.utils import seeding

from spot.envs import env_spec

_CLASSES = {  # env id -> (gymnasium module, class): the envs this module reproduces
    "Hopper-v5": ("gymnasium.envs.mujoco.hopper_v5", "HopperEnv"),
    "Walker2d-v5": ("gymnasium.envs.mujoco.walker2d_v5", "Walker2dEnv"),
    "HalfCheetah-v5": ("gymnasium.envs.mujoco.half_cheetah_v5", "HalfCheetahEnv"),
}


def supports(name: str) -> bool:
    """Whether dataset ``name``'s evaluation env has a direct stepper here (locomotion)."""
    spec = env_spec(name)
    return spec.family == "locomotion" and spec.env_id in _CLASSES


@dataclass(frozen=True)
class Task:
    """One locomotion env's model and the constants of its step, reset and health check.

    ``healthy_state``: Hopper's range for ``(qpos[2:], qvel)``, else None; ``healthy_z`` /
    ``healthy_angle``: None for HalfCheetah (never terminates); ``qvel_clip``: None = unclipped;
    ``qvel_noise``: ``"uniform"`` or ``"normal"``.
    """

    env_id: str
    model: Any  # mujoco.MjModel
    frame_skip: int
    dt: float
    init_qpos: np.ndarray
    init_qvel: np.ndarray
    noise_scale: float
    qvel_noise: str
    forward_weight: float
    ctrl_weight: float
    healthy_reward: float
    terminate_when_unhealthy: bool
    healthy_z: tuple[float, float] | None
    healthy_angle: tuple[float, float] | None
    healthy_state: tuple[float, float] | None
    qvel_clip: float | None
    action_space: gym.spaces.Box


def task(name: str) -> Task:
    """The :class:`Task` of dataset ``name``'s env, read from a gymnasium env built as
    :func:`spot.envs.make_env` builds it (once per env and process)."""
    spec = env_spec(name)
    return _task(spec.env_id, spec.make_kwargs)


@functools.lru_cache(maxsize=4)
def _task(env_id: str, make_kwargs: tuple[tuple[str, Any], ...]) -> Task:
    import importlib

    module, cls = _CLASSES[env_id]
    env = gym.make(env_id, **dict(make_kwargs))
    try:
        raw = env.unwrapped
        if type(raw) is not getattr(importlib.import_module(module), cls):
            raise TypeError(f"{env_id} is {type(raw)}, not {module}.{cls}: no direct stepper for it")
        if not raw._exclude_current_positions_from_observation:
            raise TypeError(f"{env_id}: the stepper drops qpos[0] from the observation, as gymnasium's default")
        legged = env_id != "HalfCheetah-v5"
        return Task(
            env_id=env_id,
            model=raw.model,
            frame_skip=int(raw.frame_skip),
            dt=raw.dt,
            init_qpos=raw.init_qpos.copy(),
            init_qvel=raw.init_qvel.copy(),
            noise_scale=raw._reset_noise_scale,
            qvel_noise="uniform" if legged else "normal",
            forward_weight=raw._forward_reward_weight,
            ctrl_weight=raw._ctrl_cost_weight,
            healthy_reward=raw._healthy_reward if legged else 0.0,
            terminate_when_unhealthy=bool(raw._terminate_when_unhealthy) if legged else False,
            healthy_z=tuple(raw._healthy_z_range) if legged else None,
            healthy_angle=tuple(raw._healthy_angle_range) if legged else None,
            healthy_state=tuple(raw._healthy_state_range) if env_id == "Hopper-v5" else None,
            qvel_clip=10.0 if legged else None,
            action_space=raw.action_space,
        )
    finally:
        env.close()


MIN_PER_THREAD = 3
"""Fewest episodes a thread steps: below that, handing the work over costs more than it saves."""


def default_threads() -> int:
    """Threads a batch steps its episodes' physics on by default: the CPUs this process may run on
    (``os.sched_getaffinity``; a trial pinned to one CPU steps in its own thread)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@functools.cache
def _pool(workers: int, pid: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads for :meth:`LocomotionBatch.step`, made once per process
    (``pid``: a forked child, whose copy of the parent's pool has no threads, makes its own)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="spot-mujoco")


_KEPT = threading.local()  # .datas: {"model": the last env's MjModel, "datas": its MjData}, per thread


def _datas(t: Task, n: int) -> list[Any]:
    """``n`` ``MjData`` of ``t``'s model, kept for this thread's next batch of the env (building
    one takes about 1.5 ms; :meth:`LocomotionBatch.reset` makes a kept one as new, ``mj_resetData``)."""
    kept = getattr(_KEPT, "datas", None)
    if kept is None:
        kept = _KEPT.datas = {}
    if kept.get("model") is not t.model:  # another env: let the last one's go
        kept.clear()
        kept["model"], kept["datas"] = t.model, []
    datas = kept["datas"]
    datas.extend(mujoco.MjData(t.model) for _ in range(n - len(datas)))
    return datas[:n]


class LocomotionBatch:
    """``n`` episodes of one locomotion env, each on its own ``MjData`` (:class:`Task`'s model;
    kept for the thread's next batch of this env).

    :meth:`reset` starts every episode from its seed; :meth:`step` advances the episodes ``idx``
    one env step with their actions. ``qpos`` / ``qvel`` ``[n, nq]`` / ``[n, nv]`` hold every
    episode's last state.
    """

    def __init__(self, name: str, n: int, threads: int = 0) -> None:
        self.task = task(name)
        m = self.task.model
        self.datas = _datas(self.task, n)
        self.qpos, self.qvel = np.zeros((n, m.nq)), np.zeros((n, m.nv))
        self.threads = threads or default_threads()

    @property
    def action_space(self) -> gym.spaces.Box:
        return self.task.action_space

    def reset(self, seeds: list[int]) -> np.ndarray:
        """Reset episode ``j`` as gymnasium's ``env.reset(seed=seeds[j])`` does; the observations
        ``[n, obs_dim]`` (float64)."""
        t, m = self.task, self.task.model
        if len(seeds) != len(self.datas):
            raise ValueError(f"reset: {len(seeds)} seeds for {len(self.datas)} episodes")
        for j, (seed, d) in enumerate(zip(seeds, self.datas, strict=True)):
            rng, _ = seeding.np_random(int(seed))
            mujoco.mj_resetData(m, d)
            qpos = t.init_qpos + rng.uniform(low=-t.noise_scale, high=t.noise_scale, size=m.nq)
            if t.qvel_noise == "uniform":
                qvel = t.init_qvel + rng.uniform(low=-t.noise_scale, high=t.noise_scale, size=m.nv)
            else:
                qvel = t.init_qvel + t.noise_scale * rng.standard_normal(m.nv)
            d.qpos[:], d.qvel[:] = qpos, qvel
            mujoco.mj_forward(m, d)
            self.qpos[j], self.qvel[j] = d.qpos, d.qvel
        return self.observations(np.arange(len(self.datas)))

    def observations(self, idx: np.ndarray) -> np.ndarray:
        """``(qpos[1:], qvel clipped)`` of episodes ``idx``, ``[len(idx), obs_dim]`` (float64)."""
        qvel = self.qvel[idx]
        if self.task.qvel_clip is not None:
            qvel = np.clip(qvel, -self.task.qvel_clip, self.task.qvel_clip)
        return np.concatenate([self.qpos[idx, 1:], qvel], axis=1)

    def healthy(self, idx: np.ndarray) -> np.ndarray:
        """Gymnasium's ``is_healthy`` of episodes ``idx`` (all True for HalfCheetah)."""
        t, qpos = self.task, self.qpos[idx]
        ok = np.ones(len(idx), dtype=bool)
        if t.healthy_z is not None and t.healthy_angle is not None:
            z, angle = qpos[:, 1], qpos[:, 2]
            ok &= (t.healthy_z[0] < z) & (z < t.healthy_z[1])
            ok &= (t.healthy_angle[0] < angle) & (angle < t.healthy_angle[1])
        if t.healthy_state is not None:
            state = np.concatenate([qpos[:, 2:], self.qvel[idx]], axis=1)
            lo, hi = t.healthy_state
            ok &= np.all((lo < state) & (state < hi), axis=1)
        return ok

    def _physics(self, idx: np.ndarray, actions: np.ndarray) -> None:
        """``ctrl = action`` and ``frame_skip`` MuJoCo steps of episodes ``idx``; their new state."""
        m, frame_skip = self.task.model, self.task.frame_skip
        for j, action in zip(idx, actions, strict=True):
            d = self.datas[j]
            d.ctrl[:] = action
            mujoco.mj_step(m, d, nstep=frame_skip)
            self.qpos[j], self.qvel[j] = d.qpos, d.qvel

    def step(self, idx: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One env step of episodes ``idx`` with ``actions [len(idx), act_dim]`` (float64, within
        the action space): ``(observations, rewards, terminated)``, each over ``idx``."""
        t = self.task
        x_before = self.qpos[idx, 0].copy()
        parts = min(self.threads, len(idx) // MIN_PER_THREAD) if self.threads > 1 else 1
        if parts > 1:  # mj_step lets go of the GIL: the parts' physics runs on several cores
            chunks = np.array_split(np.arange(len(idx)), parts)
            pool = _pool(parts - 1, os.getpid())
            futures = [pool.submit(self._physics, idx[c], actions[c]) for c in chunks[1:]]
            self._physics(idx[chunks[0]], actions[chunks[0]])
            for f in futures:
                f.result()
        else:
            self._physics(idx, actions)
        x_velocity = (self.qpos[idx, 0] - x_before) / t.dt
        ctrl_cost = t.ctrl_weight * np.sum(np.square(actions), axis=1)
        healthy = self.healthy(idx)
        if t.healthy_z is None:  # HalfCheetah: forward_reward - ctrl_cost
            rewards = t.forward_weight * x_velocity - ctrl_cost
        else:  # (forward_reward + healthy_reward) - ctrl_cost, gymnasium's order
            rewards = (t.forward_weight * x_velocity + healthy * t.healthy_reward) - ctrl_cost
        terminated = ~healthy & t.terminate_when_unhealthy
        return self.observations(idx), rewards, terminated
