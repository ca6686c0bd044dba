"""D4RL locomotion datasets (Fu et al., 2020, arXiv:2004.07219) rebuilt locally in gymnasium MuJoCo,
for Hopper-v5 and Walker2d-v5 (1000-step episodes).

D4RL's recipe, which this module follows:

1. Train SAC online (:mod:`spot.policy.sac`), saving the actor at every evaluation. One training
   per ``(env, size, seed)`` serves all four datasets: its snapshots and replay buffer are cached
   under ``cache_dir/sac/`` (msgpack, written atomically, under a file lock).
2. ``expert``: rollouts of the final policy. ``medium``: rollouts of the first snapshot whose
   deterministic evaluation return reaches ``medium_fraction`` (1/3) of the final one's.
   ``medium-replay``: the replay buffer, in order, up to the medium snapshot (random start-up
   actions included; an episode still running at that step is dropped). ``medium-expert``: the
   medium rows followed by the expert rows (exactly the two datasets of that seed).
3. Rollouts sample from the stochastic policy, as D4RL did, and fill exactly ``transitions`` rows:
   the last episode is cut there and that cut counts as a timeout.

Each episode ends in exactly one flag: ``terminals[-1]`` when the environment terminated (the
hopper fell), otherwise ``timeouts[-1]`` (the 1000-step limit, or a cut).

Sizes (per env): ``tiny`` for tests (3k SAC steps with 32x32 nets, 2k-row datasets; seconds),
``small`` (80k SAC steps with 128x128 nets, 100k-row datasets; minutes on 2 CPU cores),
``paper`` (D4RL: 1M SAC steps, 1M-row datasets). The same seed gives the same arrays on the same
machine: environments are reset with derived seeds, and every random draw comes from a jax key
or a numpy generator made from the seed.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import os
import time
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization
from tqdm.auto import tqdm

import spot
from spot import SpotError
from spot.data.dataset import RawDataset, raw_from_episodes
from spot.policy import sac

RECIPE = "d4rl-sac-locomotion"
RECIPE_VERSION = 1  # bump when a change here alters the SAC cache or the datasets
ENV_IDS = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5"}
KINDS = ("medium", "medium-replay", "expert", "medium-expert")
_ROLLOUT_TAGS = {"medium": 2, "expert": 3}  # seed streams; tag 1 is SAC's evaluation env


@dataclass(frozen=True)
class SizeSpec:
    """How big one size is."""

    sac: sac.SACConfig
    """The SAC run whose snapshots and buffer make the data."""
    transitions: int
    """Rows of ``medium`` and of ``expert`` each (``medium-expert`` has twice as many)."""
    medium_fraction: float = 1.0 / 3.0
    """``medium`` is the first snapshot whose eval return reaches this fraction of the final one's."""


SIZES: dict[str, SizeSpec] = {
    "tiny": SizeSpec(
        sac.SACConfig(hidden_dims=(32, 32), batch_size=64, total_steps=3000, start_steps=1000,
                      update_every=500, eval_every=500, eval_episodes=2),
        transitions=2000,
    ),
    # 128x128 nets, batch 128 and lr 1e-3 learn Hopper faster per CPU second than the paper's
    # 256x256 / 256 / 3e-4: on 2 busy shared cores, 80k steps took ~7 min and reached an eval
    # return of ~820, where the paper's settings reached ~700 after 60k steps in 10 min.
    "small": SizeSpec(
        sac.SACConfig(hidden_dims=(128, 128), batch_size=128, actor_lr=1e-3, critic_lr=1e-3,
                      temperature_lr=1e-3, total_steps=80_000, start_steps=5000, update_every=1000,
                      eval_every=2000, eval_episodes=5),
        transitions=100_000,
    ),
    "paper": SizeSpec(sac.SACConfig(), transitions=1_000_000),
}


def parse_name(name: str) -> tuple[str, str]:
    """``"hopper-medium-replay"`` -> ``("hopper", "medium-replay")``; raises :class:`SpotError`."""
    env, _, kind = name.partition("-")
    if env not in ENV_IDS or kind not in KINDS:
        names = [f"{e}-{k}" for e in ENV_IDS for k in KINDS]
        raise SpotError(f"unknown locomotion dataset '{name}'; expected one of {', '.join(names)}")
    return env, kind


def _versions() -> dict[str, str]:
    return {"spot": spot.__version__, **{p: version(p) for p in ("gymnasium", "mujoco", "jax", "flax")}}


# ------------------------------------------------------------------------------------ SAC cache
def sac_cache_path(cache_dir: Path, env_id: str, size: str, seed: int) -> Path:
    """Cache file of one SAC training; its name hashes everything the training depends on."""
    deps = {"recipe_version": RECIPE_VERSION, "env_id": env_id, "seed": seed,
            "sac": dataclasses.asdict(SIZES[size].sac), "versions": _versions()}
    digest = hashlib.sha256(json.dumps(deps, sort_keys=True).encode()).hexdigest()[:12]
    return Path(cache_dir) / "sac" / f"{env_id}__{size}__seed{seed}__{digest}.msgpack"


def _save(result: sac.SACResult, path: Path) -> None:
    payload = {
        "snapshots": {str(i): {"step": s.step, "eval_return": s.eval_return,
                               "eval_return_std": s.eval_return_std, "actor_params": s.actor_params}
                      for i, s in enumerate(result.snapshots)},
        "replay": result.replay,
        "timing": result.timing,
    }
    tmp = path.with_suffix(f".tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(serialization.msgpack_serialize(payload))
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _load(path: Path, env_id: str, seed: int, cfg: sac.SACConfig) -> sac.SACResult:
    payload = serialization.msgpack_restore(path.read_bytes())
    snaps = [payload["snapshots"][str(i)] for i in range(len(payload["snapshots"]))]
    snapshots = [sac.Snapshot(int(s["step"]), float(s["eval_return"]), float(s["eval_return_std"]),
                              s["actor_params"]) for s in snaps]
    return sac.SACResult(env_id, seed, cfg, snapshots, dict(payload["replay"]),
                         {k: float(v) for k, v in payload["timing"].items()})


def train_or_load_sac(env: str, size: str, seed: int, cache_dir: Path,
                      progress: bool = True) -> tuple[sac.SACResult, bool]:
    """The SAC run of ``(env, size, seed)``: from the cache if there, else trained and cached.

    Returns the result and whether it came from the cache. A file lock makes concurrent builds
    of the same run train it once.
    """
    env_id = ENV_IDS[env]
    cfg = SIZES[size].sac
    path = sac_cache_path(cache_dir, env_id, size, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if path.exists():
                return _load(path, env_id, seed, cfg), True
            result = sac.train_sac(env_id, cfg, seed, progress=progress)
            _save(result, path)
            return result, False
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


# ------------------------------------------------------------------------------------- datasets
def pick_medium(snapshots: list[sac.Snapshot], fraction: float) -> sac.Snapshot:
    """First snapshot whose eval return reaches ``fraction`` of the last (expert) snapshot's."""
    threshold = fraction * snapshots[-1].eval_return
    return next(s for s in snapshots if s.eval_return >= threshold)


def _rollouts(env_id: str, params: Any, cfg: sac.SACConfig, transitions: int, seed: int, tag: int,
              desc: str, progress: bool) -> list[dict[str, np.ndarray]]:
    """Stochastic-policy episodes until exactly ``transitions`` rows (the last cut, as a timeout)."""
    env = sac.make_env(env_id, cfg)
    key = jax.random.fold_in(jax.random.key(seed), tag)
    env_seed = int(np.random.SeedSequence([seed, tag]).generate_state(1)[0])
    episodes: list[dict[str, np.ndarray]] = []
    total = 0
    with tqdm(total=transitions, desc=desc, unit="step", disable=not progress) as bar:
        while total < transitions:
            ep = sac.run_episode(env, params, jax.random.fold_in(key, len(episodes)), False, cfg,
                                 seed=env_seed if not episodes else None)
            keep = min(len(ep["rewards"]), transitions - total)
            if keep < len(ep["rewards"]):
                ep = {k: v[:keep] for k, v in ep.items()}
                ep["terminals"][-1], ep["timeouts"][-1] = False, True
            episodes.append(ep)
            total += keep
            bar.update(keep)
    env.close()
    return episodes


def _replay_episodes(replay: dict[str, np.ndarray], end: int) -> list[dict[str, np.ndarray]]:
    """Complete episodes among buffer rows ``[0, end)``, in order."""
    done = np.flatnonzero(replay["terminals"][:end] | replay["timeouts"][:end])
    if done.size == 0:
        raise SpotError(f"the SAC replay buffer has no complete episode in its first {end} rows")
    bounds = np.concatenate([[0], done + 1])
    keys = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
    return [{k: replay[k][a:b] for k in keys} for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def build(name: str, size: str, seed: int, cache_dir: Path,
          progress: bool = True) -> tuple[RawDataset, dict[str, Any]]:
    """Build a D4RL-style locomotion dataset in the real simulator.

    Args:
      name: ``{hopper,walker2d}-{medium,medium-replay,expert,medium-expert}``.
      size: ``"tiny"``, ``"small"`` or ``"paper"`` (see :data:`SIZES`).
      seed: seeds SAC and the rollouts; the four datasets of one seed share one SAC run.
      cache_dir: where the SAC run is cached (``cache_dir/sac/``).
      progress: show tqdm bars for SAC training and rollouts.
    Returns:
      The raw dataset (with ``next_observations``; ``metadata["episode_kind"]`` names each
      episode's source) and its card: recipe, env, sizes, episode-return statistics, the
      behaviour snapshots' eval returns, SAC facts, ``sac_cache_hit``, build time and versions.
    """
    env, kind = parse_name(name)
    if size not in SIZES:
        raise SpotError(f"unknown size '{size}' for dataset '{name}'; expected one of {', '.join(SIZES)}")
    start = time.perf_counter()
    spec = SIZES[size]
    env_id = ENV_IDS[env]
    result, cache_hit = train_or_load_sac(env, size, seed, cache_dir, progress)
    expert = result.snapshots[-1]
    medium = pick_medium(result.snapshots, spec.medium_fraction)

    episodes: list[dict[str, np.ndarray]] = []
    episode_kind: list[str] = []
    if kind == "medium-replay":
        episodes = _replay_episodes(result.replay, medium.step)
        episode_kind = ["replay"] * len(episodes)
    for part, snap in (("medium", medium), ("expert", expert)):
        if kind in (part, "medium-expert"):
            eps = _rollouts(env_id, snap.actor_params, spec.sac, spec.transitions, seed,
                            _ROLLOUT_TAGS[part], f"{name} ({size}): {part} rollouts", progress)
            episodes += eps
            episode_kind += [part] * len(eps)

    returns = np.array([ep["rewards"].sum(dtype=np.float64) for ep in episodes])
    lengths = np.array([len(ep["rewards"]) for ep in episodes])
    raw = raw_from_episodes(episodes, name=f"{name}-{size}", metadata={"episode_kind": episode_kind})
    card = {
        "recipe": RECIPE,
        "recipe_version": RECIPE_VERSION,
        "name": name,
        "env": env_id,
        "size": size,
        "seed": seed,
        "transitions": len(raw),
        "episodes": len(episodes),
        "obs_dim": int(raw.observations.shape[1]),
        "act_dim": int(raw.actions.shape[1]),
        "terminal_episodes": int(raw.terminals.sum()),
        "return": {"mean": float(returns.mean()), "std": float(returns.std()),
                   "min": float(returns.min()), "max": float(returns.max())},
        "episode_length_mean": float(lengths.mean()),
        "behaviour": {
            "rollout_policy": "stochastic",
            "medium_fraction": spec.medium_fraction,
            "medium_snapshot_step": medium.step,
            "medium_eval_return": medium.eval_return,
            "expert_snapshot_step": expert.step,
            "expert_eval_return": expert.eval_return,
            "eval_episodes": spec.sac.eval_episodes,
            "eval_curve": [[s.step, round(s.eval_return, 1)] for s in result.snapshots],
        },
        "sac": {"steps": spec.sac.total_steps, "hidden_dims": list(spec.sac.hidden_dims),
                "batch_size": spec.sac.batch_size, "train_time_s": round(result.timing["total"], 1)},
        "sac_cache_hit": cache_hit,
        "build_time_s": round(time.perf_counter() - start, 2),
        "versions": _versions(),
    }
    return raw, card
