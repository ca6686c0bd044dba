"""The online SAC training loop of the locomotion recipes (:func:`train_sac`); the learner itself
(config, networks, updates) is :mod:`spot.recipes.sac`.

The environment loop is Python and numpy (gymnasium); the replay buffer is a fixed-capacity pytree
of device arrays; every ``update_every`` environment steps one jitted ``lax.scan``
(:func:`spot.recipes.sac.train_chunk`) runs ``update_every`` gradient updates, so Python costs
little. Actions must lie in ``[-1, 1]``, as in Hopper and Walker2d.

A run stops after ``total_steps`` or, with ``target_return`` set, once ``stop_evals`` evaluations
in a row have a mean return that reaches it (``total_steps`` is then a cap); ``stop_policy`` says
whose return: the deterministic (mean-action) policy's or the stochastic one's, which the datasets
are rolled out with. Without a stop rule (sizes ``tiny`` and ``small``) nothing in the training
depends on the evaluations, and each one's episodes run in a worker thread beside the next chunks
(the eval env and a copy of the actor are the worker's; the same snapshots and data). A run can write checkpoints
(learner and optimiser states, the replay buffer so far, the snapshots, the random generators and
the training env's simulator state); :func:`train_sac` resumes from one and continues bit for bit.
"""

from __future__ import annotations

import json
import math
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import serialization
from tqdm.auto import tqdm

from spot import SpotError, store
from spot.recipes.sac import Params, Replay, SACConfig, act, identity, init_state, insert, train_chunk


# ----------------------------------------------------------------------------- environment loop
@partial(jax.jit, static_argnames=("deterministic", "cfg"))
def _act_at(
    params: Params, obs: jax.Array, key: jax.Array, step: int, deterministic: bool, cfg: SACConfig
) -> jax.Array:
    # act with key fold_in(key, step) folded inside jit: an eager fold_in costs ~0.4 ms on CPU.
    return act(params, obs, jax.random.fold_in(key, step), deterministic, cfg)


def make_env(env_id: str, cfg: SACConfig, **make_kwargs: Any) -> gym.Env:
    """``gym.make`` with the config's time limit (and ``make_kwargs``, e.g. ``xml_file``); raises
    unless actions lie in ``[-1, 1]``."""
    env = gym.make(env_id, max_episode_steps=cfg.max_episode_steps, **make_kwargs)
    space = env.action_space
    if not (np.all(space.low == -1.0) and np.all(space.high == 1.0)):
        env.close()
        raise SpotError(f"{env_id}: SAC here needs actions in [-1, 1], got [{space.low}, {space.high}]")
    return env


def run_episode(
    env: gym.Env, params: Params, key: jax.Array, deterministic: bool, cfg: SACConfig, seed: int | None = None
) -> dict[str, np.ndarray]:
    """One episode of the actor ``params`` in ``env`` (reset with ``seed`` if given).

    Returns the D4RL-style rows: ``observations``, ``actions``, ``rewards``, ``next_observations``,
    ``terminals`` (``[-1]`` set if the environment terminated) and ``timeouts`` (``[-1]`` set if
    the time limit cut it instead). Step ``t`` samples with ``fold_in(key, t)``.
    """
    obs, _ = env.reset(seed=seed)
    rows: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations")}
    for t in range(cfg.max_episode_steps + 1):
        action = np.asarray(_act_at(params, obs, key, t, deterministic, cfg))
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for k, v in zip(rows, (obs, action, reward, next_obs), strict=True):
            rows[k].append(v)
        obs = next_obs
        if terminated or truncated:
            break
    n = len(rows["rewards"])
    ep = {k: np.asarray(v, np.float32) for k, v in rows.items()}
    ep["terminals"] = np.zeros(n, bool)
    ep["timeouts"] = np.zeros(n, bool)
    ep["terminals"][-1] = terminated
    ep["timeouts"][-1] = not terminated  # an episode that both terminates and times out is a terminal
    return ep


def evaluate(
    env: gym.Env, params: Params, episodes: int, seed: int, cfg: SACConfig, key: jax.Array | None = None
) -> np.ndarray:
    """Returns of ``episodes`` episodes; the first reset uses ``seed``. Deterministic (mean
    actions) without ``key``; with it, sampled actions, episode ``i`` with ``fold_in(key, i)``."""
    deterministic = key is None
    key = jax.random.key(0) if key is None else key  # unused when deterministic
    return np.array(
        [
            run_episode(env, params, jax.random.fold_in(key, i), deterministic, cfg, seed=seed if i == 0 else None)[
                "rewards"
            ].sum()
            for i in range(episodes)
        ]
    )


@dataclass(frozen=True)
class Snapshot:
    """The actor at one evaluation: host (numpy) params, its deterministic eval returns and, where
    the stop rule reads the stochastic policy, that policy's (else None)."""

    step: int
    eval_return: float
    eval_return_std: float
    actor_params: Params
    stochastic_return: float | None = None
    stochastic_return_std: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """msgpack-able fields (the stochastic returns only where measured)."""
        out = {"step": self.step, "eval_return": self.eval_return, "eval_return_std": self.eval_return_std}
        if self.stochastic_return is not None:
            out |= {"stochastic_return": self.stochastic_return, "stochastic_return_std": self.stochastic_return_std}
        return {**out, "actor_params": self.actor_params}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Snapshot:
        stoch = d.get("stochastic_return")
        return cls(
            int(d["step"]),
            float(d["eval_return"]),
            float(d["eval_return_std"]),
            d["actor_params"],
            None if stoch is None else float(stoch),
            None if stoch is None else float(d["stochastic_return_std"]),
        )


def stop_reached(snapshots: Sequence[Snapshot], cfg: SACConfig) -> bool:
    """Whether the last ``cfg.stop_evals`` evaluations all reach ``cfg.target_return`` with the
    return of ``cfg.stop_policy`` (False without a target)."""
    if cfg.target_return is None or len(snapshots) < cfg.stop_evals:
        return False
    last = snapshots[len(snapshots) - cfg.stop_evals :]
    values = [stop_value(s, cfg) for s in last]
    return all(v is not None and v >= cfg.target_return for v in values)


def stop_value(snapshot: Snapshot, cfg: SACConfig) -> float | None:
    """The return of ``snapshot`` that ``cfg``'s stop rule reads (None: not measured)."""
    return snapshot.stochastic_return if cfg.stop_policy == "stochastic" else snapshot.eval_return


@dataclass(frozen=True)
class SACResult:
    """What :func:`train_sac` returns.

    Attributes:
      snapshots: one per evaluation, in step order; the last is the final policy.
      replay: the replay buffer in collection order (numpy; as many rows as steps were run: fewer
        than ``total_steps`` when ``target_return`` stopped the run): the D4RL raw keys
        ``observations``, ``actions``, ``rewards``, ``next_observations``, ``terminals``,
        ``timeouts``. Row ``t`` is environment step ``t``.
      timing: seconds, summed over every session of the run: ``total``, ``env`` (stepping and
        acting), ``update`` (chunks, incl. compilation), ``eval`` (in a worker thread beside the
        training of a run without a stop rule: not part of ``total`` then), ``checkpoint``; and
        ``peak_rss_mb``, the largest peak resident memory of the sessions' processes.
      resumed_from: the steps at which the run was resumed from a checkpoint, in order.
    """

    env_id: str
    seed: int
    config: SACConfig
    snapshots: list[Snapshot]
    replay: dict[str, np.ndarray]
    timing: dict[str, float]
    resumed_from: tuple[int, ...] = ()

    @property
    def target_reached(self) -> bool | None:
        """Whether the run ended by its stop rule (:func:`stop_reached`; ``None`` without a target)."""
        if self.config.target_return is None:
            return None
        return stop_reached(self.snapshots, self.config)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (``getrusage``; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


_REPLAY_KEYS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
CHECKPOINT_FORMAT = 1
_MJ_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, act, warm start, time, controls...


class _Run:
    """The mutable state of one SAC training run: exactly what a checkpoint holds.

    Everything random is either stateless (jax keys folded with the step) or saved (the numpy
    generator of the random start actions, the training env's MuJoCo integration state, time-limit
    counter and reset generator), so a run resumed from a checkpoint continues bit for bit.
    """

    def __init__(self, env_id: str, cfg: SACConfig, seed: int, make_kwargs: dict[str, Any]):
        self.env_id, self.cfg, self.seed = env_id, cfg, seed
        self.env, self.eval_env = make_env(env_id, cfg, **make_kwargs), make_env(env_id, cfg, **make_kwargs)
        self.obs_dim = self.env.observation_space.shape[0]
        self.act_dim = self.env.action_space.shape[0]
        init_key, self.train_key, self.act_key = jax.random.split(jax.random.key(seed), 3)
        self.state = init_state(init_key, self.obs_dim, self.act_dim, cfg)
        n, dims = (
            cfg.total_steps,
            {"observations": self.obs_dim, "next_observations": self.obs_dim, "actions": self.act_dim},
        )
        self.host = {
            k: np.zeros((n, dims[k]) if k in dims else n, bool if k in ("terminals", "timeouts") else np.float32)
            for k in _REPLAY_KEYS
        }
        self.random_actions = np.random.default_rng(seed)
        self.eval_seed = int(np.random.SeedSequence([seed, 1]).generate_state(1)[0])
        # the stochastic evaluations (stop_policy stochastic): their own env seed and action keys
        self.stochastic_seed = int(np.random.SeedSequence([seed, 4]).generate_state(1)[0])
        self.stochastic_key = jax.random.fold_in(jax.random.key(seed), 4)
        self.snapshots: list[Snapshot] = []
        self.timing = {"total": 0.0, "env": 0.0, "update": 0.0, "eval": 0.0, "checkpoint": 0.0, "peak_rss_mb": 0.0}
        self.resumed_from: list[int] = []
        self.chunk_metrics: dict[str, Any] = {}
        self.t = 0
        self.obs, _ = self.env.reset(seed=seed)
        self.session_start, self.total_before = time.perf_counter(), 0.0
        self.replay: Replay | None = None

    # ---------------------------------------------------------------------------- one chunk
    def collect(self) -> None:
        """``update_every`` environment steps into the host buffer."""
        cfg, tic = self.cfg, time.perf_counter()
        for t in range(self.t, self.t + cfg.update_every):
            if t < cfg.start_steps:
                action = self.random_actions.uniform(-1.0, 1.0, self.act_dim).astype(np.float32)
            else:
                action = np.asarray(_act_at(self.state.actor.params, self.obs, self.act_key, t, False, cfg))
            next_obs, reward, terminated, truncated, _ = self.env.step(action)
            for k, v in zip(
                _REPLAY_KEYS,
                (self.obs, action, reward, next_obs, terminated, truncated and not terminated),
                strict=True,
            ):
                self.host[k][t] = v
            self.obs = self.env.reset()[0] if terminated or truncated else next_obs
        self.timing["env"] += time.perf_counter() - tic

    def learn(self) -> None:
        """Copy the chunk's rows to the device buffer; one update chunk once past ``start_steps``."""
        cfg, tic = self.cfg, time.perf_counter()
        start, end = self.t, self.t + cfg.update_every
        if self.replay is None:  # the whole buffer, once per session (zeros past row `start`)
            self.replay = Replay(*(jnp.asarray(self.host[k], jnp.float32) for k in Replay._fields))
        else:
            rows = Replay(*(jnp.asarray(self.host[k][start:end], jnp.float32) for k in Replay._fields))
            self.replay = insert(self.replay, rows, start)
        if end > cfg.start_steps:
            self.state, self.chunk_metrics = train_chunk(
                self.state, self.replay, jnp.int32(end), jax.random.fold_in(self.train_key, end), cfg, cfg.update_every
            )
            jax.block_until_ready(self.state)
        self.t = end
        self.timing["update"] += time.perf_counter() - tic

    def evaluate(self) -> tuple[int, dict[str, float], Params]:
        """The evaluation at this step, begun: the chunk's metrics and a host copy of the actor
        (before the next chunk donates the state); :meth:`returns` measures it, :meth:`snapshot`
        keeps it."""
        metrics = {}
        if self.t > self.cfg.start_steps:
            metrics = {k: float(v) for k, v in jax.device_get(self.chunk_metrics).items()}
            if not all(math.isfinite(v) for v in metrics.values()):
                raise FloatingPointError(
                    f"SAC {self.env_id} seed {self.seed}: non-finite metrics at step {self.t}: {metrics}"
                )
        return self.t, metrics, jax.tree.map(lambda x: np.array(x, copy=True), self.state.actor.params)

    def returns(self, step: int, params: Params) -> tuple[np.ndarray, np.ndarray | None]:
        """The deterministic evaluation returns of ``params`` (and with sampled actions where the
        stop rule reads those) in the eval env, which only this call uses: a function of ``params``
        and ``step`` alone (every evaluation resets the env with the same seed)."""
        tic = time.perf_counter()
        returns = evaluate(self.eval_env, params, self.cfg.eval_episodes, self.eval_seed, self.cfg)
        sampled = None
        if self.cfg.stop_policy == "stochastic":
            key = jax.random.fold_in(self.stochastic_key, step)
            sampled = evaluate(self.eval_env, params, self.cfg.eval_episodes, self.stochastic_seed, self.cfg, key)
        self.timing["eval"] += time.perf_counter() - tic
        return returns, sampled

    def snapshot(self, step: int, metrics: dict[str, float], params: Params, returns: Any) -> dict[str, float]:
        """Keep the evaluated actor as the next :class:`Snapshot`; the metrics for ``on_eval``."""
        det, sampled = returns
        metrics = {**metrics, "eval/return_mean": float(det.mean()), "eval/return_std": float(det.std())}
        stoch = (None, None) if sampled is None else (float(sampled.mean()), float(sampled.std()))
        if sampled is not None:
            metrics |= {"eval/stochastic_return_mean": stoch[0], "eval/stochastic_return_std": stoch[1]}
        self.snapshots.append(Snapshot(step, float(det.mean()), float(det.std()), params, *stoch))
        return metrics

    # ---------------------------------------------------------------------------- checkpoints
    def payload(self) -> dict[str, Any]:
        """Everything needed to continue the run (msgpack-able; big ints travel as JSON text)."""
        u = self.env.unwrapped
        mj_state = np.empty(mujoco.mj_stateSize(u.model, _MJ_STATE))
        mujoco.mj_getState(u.model, u.data, mj_state, _MJ_STATE)
        return {
            "format": CHECKPOINT_FORMAT,
            "run": json.dumps({"env_id": self.env_id, "seed": self.seed, "config": identity(self.cfg)}, sort_keys=True),
            "t": self.t,
            "learner": serialization.to_state_dict(self.state),
            "host": {k: v[: self.t] for k, v in self.host.items()},
            "snapshots": {str(i): s.to_dict() for i, s in enumerate(self.snapshots)},
            "timing": {
                **self.timing,
                "total": self.elapsed(),
                "peak_rss_mb": max(self.timing["peak_rss_mb"], peak_rss_mb()),
            },
            "resumed_from": np.asarray(self.resumed_from, np.int64),
            "random_actions": json.dumps(self.random_actions.bit_generator.state),
            "env": {
                "obs": self.obs,
                "mj_state": mj_state,
                "elapsed_steps": self.env._elapsed_steps,
                "np_random": json.dumps(u.np_random.bit_generator.state),
            },
        }

    def restore(self, payload: dict[str, Any], path: Path) -> None:
        """Continue from :meth:`payload`'s output; raises :class:`SpotError` if it is another run's."""
        mine = json.dumps({"env_id": self.env_id, "seed": self.seed, "config": identity(self.cfg)}, sort_keys=True)
        if payload.get("format") != CHECKPOINT_FORMAT or payload.get("run") != mine:
            raise SpotError(
                f"SAC checkpoint {path} belongs to another run or format (it holds "
                f"{payload.get('run')}, format {payload.get('format')}; expected {mine}, "
                f"format {CHECKPOINT_FORMAT}); delete it to start over"
            )
        self.t = int(payload["t"])
        self.state = serialization.from_state_dict(self.state, payload["learner"])
        for k in _REPLAY_KEYS:
            self.host[k][: self.t] = payload["host"][k]
        snaps = [payload["snapshots"][str(i)] for i in range(len(payload["snapshots"]))]
        self.snapshots = [Snapshot.from_dict(s) for s in snaps]
        self.timing.update({k: float(v) for k, v in payload["timing"].items()})
        self.total_before = self.timing["total"]
        self.resumed_from = [int(x) for x in payload["resumed_from"]] + [self.t]
        self.random_actions.bit_generator.state = json.loads(payload["random_actions"])
        env, u = payload["env"], self.env.unwrapped
        mujoco.mj_setState(u.model, u.data, np.array(env["mj_state"], np.float64), _MJ_STATE)
        self.env._elapsed_steps = int(env["elapsed_steps"])
        u.np_random.bit_generator.state = json.loads(env["np_random"])
        self.obs = np.asarray(env["obs"])

    def save(self, path: Path) -> None:
        """Write :meth:`payload` to ``path`` atomically (temporary file, fsync, rename)."""
        tic = time.perf_counter()
        store.write_atomic(path, serialization.msgpack_serialize(self.payload()), fsync=True)  # full disk: SpotError
        self.timing["checkpoint"] += time.perf_counter() - tic

    def elapsed(self) -> float:
        """Seconds of this run so far, over all its sessions."""
        return self.total_before + time.perf_counter() - self.session_start

    def close(self) -> None:
        self.env.close()
        self.eval_env.close()


class _Evaluations:
    """A run's evaluations, in step order. With ``overlap`` (a run whose length does not depend on
    them: no stop rule) each one's episodes run in a worker thread while training goes on (the
    actor is copied first; the eval env is the worker's alone), else at once; :meth:`drain` keeps
    the finished ones as snapshots and calls ``on_eval``, in order, in the caller's thread. The
    snapshots, and so the data, are those of the sequential loop (a test)."""

    def __init__(self, run: _Run, on_eval: Callable | None, bar: Any, overlap: bool) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.run, self.on_eval, self.bar = run, on_eval, bar
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="sac-eval") if overlap else None
        self.pending: list[tuple[int, dict[str, float], Params, Any]] = []

    def submit(self) -> None:
        step, metrics, params = self.run.evaluate()
        if self.pool is None:
            self.pending.append((step, metrics, params, self.run.returns(step, params)))
        else:
            self.pending.append((step, metrics, params, self.pool.submit(self.run.returns, step, params)))
        self.drain(wait=False)

    def drain(self, wait: bool = True) -> None:
        """Keep every finished evaluation (``wait``: every one, waiting for the rest)."""
        while self.pending:
            step, metrics, params, returns = self.pending[0]
            if self.pool is not None:
                if not (wait or returns.done()):
                    return
                returns = returns.result()
            self.pending.pop(0)
            metrics = self.run.snapshot(step, metrics, params, returns)
            if self.on_eval is not None:
                self.on_eval(step, metrics)
            self.bar.set_postfix(eval_return=f"{metrics['eval/return_mean']:.0f}")

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)


def train_sac(
    env_id: str,
    cfg: SACConfig,
    seed: int,
    on_eval: Callable[[int, dict[str, float]], None] | None = None,
    progress: bool = True,
    checkpoint: Path | None = None,
    checkpoint_every: int = 0,
    make_kwargs: dict[str, Any] | None = None,
) -> SACResult:
    """Train SAC in ``env_id`` for ``cfg.total_steps`` environment steps, or until its stop rule
    (:func:`stop_reached`: ``cfg.stop_evals`` evaluations in a row reach ``cfg.target_return``).

    Args:
      env_id: a gymnasium id with actions in ``[-1, 1]`` (``Hopper-v5``, ``Walker2d-v5``).
      cfg: hyperparameters, run length (a cap when ``target_return`` is set) and stop rule.
      seed: seeds the networks, the action noise, the random start actions and both environments;
        the same seed gives the same run on the same machine.
      on_eval: called after each evaluation with ``(step, metrics)``; metrics holds
        ``eval/return_mean``, ``eval/return_std``, under a stochastic stop rule
        ``eval/stochastic_return_mean`` and ``_std``, and the chunk's ``sac/...`` means.
      progress: show a tqdm bar over environment steps.
      checkpoint: a file to resume from if it exists, and to save to every ``checkpoint_every``
        steps (after that step's evaluation; a multiple of ``cfg.eval_every``; 0: never). A run
        resumed from it gives the same result as one that was never stopped. The caller deletes
        it once the result is stored.
      make_kwargs: extra ``gym.make`` arguments of both environments (e.g. ``xml_file``).
    Returns:
      A :class:`SACResult` with the snapshots, the replay buffer and timings.
    """
    if checkpoint_every < 0 or checkpoint_every % cfg.eval_every:
        raise SpotError(
            f"train_sac: checkpoint_every = {checkpoint_every}; expected 0 or a multiple "
            f"of eval_every ({cfg.eval_every})"
        )
    run = _Run(env_id, cfg, seed, dict(make_kwargs or {}))
    if checkpoint is not None and Path(checkpoint).exists():
        run.restore(serialization.msgpack_restore(Path(checkpoint).read_bytes()), Path(checkpoint))
    bar = tqdm(total=cfg.total_steps, initial=run.t, desc=f"SAC {env_id}", unit="step", disable=not progress)
    evals = _Evaluations(run, on_eval, bar, overlap=cfg.target_return is None)
    try:
        while run.t < cfg.total_steps:
            run.collect()
            run.learn()
            bar.update(cfg.update_every)
            if run.t % cfg.eval_every:
                continue
            evals.submit()  # (without overlap: evaluated and kept now, for the stop rule)
            if stop_reached(run.snapshots, cfg):
                break
            if (
                checkpoint is not None
                and checkpoint_every
                and run.t % checkpoint_every == 0
                and run.t < cfg.total_steps
            ):
                evals.drain()  # a checkpoint holds every snapshot so far
                run.save(Path(checkpoint))
        evals.drain()
    finally:
        evals.close()
    bar.close()
    run.close()
    run.timing["total"] = run.elapsed()
    run.timing["peak_rss_mb"] = max(run.timing["peak_rss_mb"], peak_rss_mb())
    replay = {k: v[: run.t] for k, v in run.host.items()}
    return SACResult(env_id, seed, cfg, run.snapshots, replay, run.timing, tuple(run.resumed_from))
