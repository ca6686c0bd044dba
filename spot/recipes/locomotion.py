"""D4RL locomotion datasets (Fu et al., 2020, arXiv:2004.07219) rebuilt locally in gymnasium MuJoCo,
for Hopper-v5 and Walker2d-v5 (1000-step episodes).

D4RL's recipe, which this module follows:

1. Train SAC online (:mod:`spot.recipes.sac`, :mod:`spot.recipes.sac_train`), saving the actor at
   every evaluation. At size ``paper`` it trains until the deterministic evaluation return (mean of
   10 episodes) reaches D4RL's expert level (:data:`spot.recipes.locomotion_sac.PAPER_STOP`: Hopper
   3000, Walker2d 4000; D4RL's expert references are 3234.3 and 4592.3), with a step cap. One
   training per ``(env, size, seed)`` serves all five datasets (:mod:`spot.recipes.locomotion_sac`):
   its snapshots and replay buffer are cached under ``cache_dir/sac/`` (msgpack, written
   atomically, under a file lock). While it trains, a checkpoint (learner, optimisers, replay
   buffer, snapshots, generators, simulator state) is written every ``checkpoint_every`` steps
   beside the cache file, and a killed build resumes from it bit for bit.
2. ``expert``: rollouts of the final policy. ``medium``: rollouts of the first snapshot whose
   deterministic evaluation return reaches ``medium_fraction`` (1/3) of the final one's.
   ``medium-replay``: the replay buffer, in order, up to the medium snapshot (random start-up
   actions included; an episode still running at that step is dropped). ``medium-expert``: the
   medium rows followed by the expert rows (exactly the two datasets of that seed).
   ``full-replay`` (D4RL's ``*-full-replay-v2``): the whole replay buffer, in order, up to the
   final (expert) snapshot; ``medium-replay`` is its first part. Where SAC reaches the medium
   level early (local Hopper at size paper: 150k of 420k steps), medium-replay is short and
   mostly early failures, and full-replay is the replay data with room above it.
3. Rollouts sample from the stochastic policy, as D4RL did, and fill exactly ``transitions`` rows:
   the last episode is cut there and that cut counts as a timeout.

Each episode ends in exactly one flag: ``terminals[-1]`` when the environment terminated (the
hopper fell), otherwise ``timeouts[-1]`` (the 1000-step limit, or a cut).

Walker2d runs in the v2-v4 model D4RL recorded in (:func:`spot.envs.locomotion_make_kwargs`), the
same model the policies are evaluated in.

Sizes (per env; :data:`SIZES`): ``tiny`` for tests (3k SAC steps with 32x32 nets, 2k-row datasets; seconds),
``small`` (80k SAC steps with 128x128 nets, 100k-row datasets; minutes on 2 CPU cores),
``paper`` (D4RL: SAC with the paper's settings until the expert level, 1M-row datasets),
``paper-fast`` (``paper``'s rows and stop rule; ``small``'s SAC networks, batch and learning rates,
about 4x cheaper per step here: the size that builds Walker2d on 2 CPU cores). The same seed gives the same
arrays on the same
machine: environments are reset with derived seeds, and every random draw comes from a jax key
or a numpy generator made from the seed.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from spot import SpotError, envs
from spot.data.dataset import RawDataset, raw_from_episodes
from spot.recipes import sac, sac_train
from spot.recipes.locomotion_sac import ENV_IDS, RECIPE_VERSION, SIZES, make_kwargs, train_or_load_sac, versions

RECIPE = "d4rl-sac-locomotion"
KINDS = ("medium", "medium-replay", "expert", "medium-expert", "full-replay")
_ROLLOUT_TAGS = {"medium": 2, "expert": 3}  # seed streams; SAC's evaluations use tags 1 and 4 (spot.recipes.sac_train)
COMPOSITES: dict[str, tuple[str, ...]] = {"medium-expert": ("medium", "expert")}
"""Kinds whose rows are exactly other kinds' rows of the same size and seed, in order: the
registry joins the built parts (:func:`join`) instead of rolling them out again."""


def recipe_version(name: str, size: str) -> int | str:
    """The version a card of ``name`` at ``size`` records (the registry rebuilds a file whose card
    holds another): :data:`RECIPE_VERSION`, with the stop rule's policy and count appended where
    they are not the first rule's (one deterministic evaluation), so data built under one
    (policy, count) never pass for another's. A change of a target or cap changes the SAC run's cache
    name (:func:`spot.recipes.locomotion_sac.sac_cache_path`) but not this: bump :data:`RECIPE_VERSION` with it."""
    env, _ = parse_name(name)
    rule = SIZES[size].stop.get(env) if size in SIZES else None
    if rule is None or (rule.policy, rule.evals) == ("deterministic", 1):
        return RECIPE_VERSION
    return f"{RECIPE_VERSION}+stop-{rule.policy}-{rule.evals}"


def parse_name(name: str) -> tuple[str, str]:
    """``"hopper-medium-replay"`` -> ``("hopper", "medium-replay")``; raises :class:`SpotError`."""
    env, _, kind = name.partition("-")
    if env not in ENV_IDS or kind not in KINDS:
        names = [f"{e}-{k}" for e in ENV_IDS for k in KINDS]
        raise SpotError(f"unknown locomotion dataset '{name}'; expected one of {', '.join(names)}")
    return env, kind


# ------------------------------------------------------------------------------------- datasets
def pick_medium(snapshots: list[sac_train.Snapshot], fraction: float) -> sac_train.Snapshot:
    """First snapshot whose eval return reaches ``fraction`` of the last (expert) snapshot's."""
    threshold = fraction * snapshots[-1].eval_return
    return next(s for s in snapshots if s.eval_return >= threshold)


def _rollouts(
    env_name: str, params: Any, cfg: sac.SACConfig, transitions: int, seed: int, tag: int, desc: str, progress: bool
) -> list[dict[str, np.ndarray]]:
    """Stochastic-policy episodes until exactly ``transitions`` rows (the last cut, as a timeout)."""
    env = sac_train.make_env(ENV_IDS[env_name], cfg, **make_kwargs(env_name))
    key = jax.random.fold_in(jax.random.key(seed), tag)
    env_seed = int(np.random.SeedSequence([seed, tag]).generate_state(1)[0])
    episodes: list[dict[str, np.ndarray]] = []
    total = 0
    with tqdm(total=transitions, desc=desc, unit="step", disable=not progress) as bar:
        while total < transitions:
            ep = sac_train.run_episode(
                env, params, jax.random.fold_in(key, len(episodes)), False, cfg, seed=env_seed if not episodes else None
            )
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


def build(name: str, size: str, seed: int, cache_dir: Path, progress: bool = True) -> tuple[RawDataset, dict[str, Any]]:
    """Build a D4RL-style locomotion dataset in the real simulator.

    Args:
      name: ``{hopper,walker2d}-{medium,medium-replay,expert,medium-expert,full-replay}``.
      size: ``"tiny"``, ``"small"``, ``"paper"`` or ``"paper-fast"`` (see :data:`SIZES`).
      seed: seeds SAC and the rollouts; the five datasets of one seed share one SAC run.
      cache_dir: where the SAC run is cached (``cache_dir/sac/``).
      progress: show tqdm bars for SAC training and rollouts, and each evaluation's return.
    Returns:
      The raw dataset (with ``next_observations``; ``metadata["episode_kind"]`` names each
      episode's source) and its card (:func:`make_card`).
    """
    env, kind = parse_name(name)
    if size not in SIZES:
        raise SpotError(f"unknown size '{size}' for dataset '{name}'; expected one of {', '.join(SIZES)}")
    start = time.perf_counter()
    spec = SIZES[size]
    result, cache_hit = train_or_load_sac(env, size, seed, cache_dir, progress)
    expert = result.snapshots[-1]
    medium = pick_medium(result.snapshots, spec.medium_fraction)
    if progress and result.target_reached is False:
        print(
            f"spot: warning: SAC {ENV_IDS[env]} stopped at its cap of {result.config.total_steps} "
            f"steps without meeting its stop rule ({result.config.stop_evals} evaluation(s) in a row of the "
            f"{result.config.stop_policy} policy at {result.config.target_return:.0f} or more; the last: "
            f"{sac_train.stop_value(expert, result.config):.0f})",
            file=sys.stderr,
        )

    episodes: list[dict[str, np.ndarray]] = []
    episode_kind: list[str] = []
    if kind in ("medium-replay", "full-replay"):
        end = medium.step if kind == "medium-replay" else expert.step
        episodes = _replay_episodes(result.replay, end)
        episode_kind = ["replay"] * len(episodes)
    for part, snap in (("medium", medium), ("expert", expert)):
        if kind in (part, "medium-expert"):
            eps = _rollouts(
                env,
                snap.actor_params,
                result.config,
                spec.transitions,
                seed,
                _ROLLOUT_TAGS[part],
                f"{name} ({size}): {part} rollouts",
                progress,
            )
            episodes += eps
            episode_kind += [part] * len(eps)

    return _finish(name, size, seed, episodes, episode_kind, result, cache_hit, start)


def _finish(
    name: str,
    size: str,
    seed: int,
    episodes: list[dict[str, np.ndarray]],
    episode_kind: list[str],
    result: sac_train.SACResult,
    cache_hit: bool,
    start: float,
) -> tuple[RawDataset, dict[str, Any]]:
    """The raw dataset of ``episodes`` and its card, with the build's time and peak memory."""
    spec = SIZES[size]
    medium = pick_medium(result.snapshots, spec.medium_fraction)
    raw = raw_from_episodes(episodes, name=f"{name}-{size}", metadata={"episode_kind": episode_kind})
    card = make_card(name, size, seed, raw, episodes, result, medium, spec.medium_fraction)
    card["sac_cache_hit"] = cache_hit
    card["build_time_s"] = round(time.perf_counter() - start, 2)
    card["peak_rss_mb"] = round(sac_train.peak_rss_mb(), 1)
    return raw, card


def composite_parts(name: str) -> list[str]:
    """The datasets whose rows make up ``name``, in order (``hopper-medium-expert`` ->
    ``[hopper-medium, hopper-expert]``); ``[]`` for a dataset that is not a composite."""
    env, kind = parse_name(name)
    return [f"{env}-{part}" for part in COMPOSITES.get(kind, ())]


def _stochastic_evals(result: sac_train.SACResult, medium: sac_train.Snapshot) -> dict[str, Any]:
    """The stochastic policy's evaluation returns, where the stop rule measured them (else nothing)."""
    expert = result.snapshots[-1]
    if expert.stochastic_return is None:
        return {}
    measured = [s for s in result.snapshots if s.stochastic_return is not None]
    curve = [[int(s.step), round(float(s.stochastic_return), 1)] for s in measured]
    return {
        "medium_stochastic_return": medium.stochastic_return,
        "expert_stochastic_return": expert.stochastic_return,
        "stochastic_curve": curve,
    }


def _eval_curve(result: sac_train.SACResult) -> list[list[float]]:
    return [[int(s.step), round(float(s.eval_return), 1)] for s in result.snapshots]


def _split(raw: RawDataset, where: str) -> list[dict[str, np.ndarray]]:
    """A built dataset's rows back into its episodes (each ends in a terminal or a timeout)."""
    ends = np.flatnonzero(raw.terminals | raw.timeouts)
    if ends.size == 0 or ends[-1] != len(raw) - 1:
        raise SpotError(f"{where}: its last row ends no episode (neither terminal nor timeout); rebuild it")
    bounds = np.concatenate([[0], ends + 1])
    keys = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")
    return [{k: getattr(raw, k)[a:b] for k in keys} for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def join(
    name: str,
    size: str,
    seed: int,
    cache_dir: Path,
    parts: list[tuple[RawDataset, dict[str, Any]]],
    progress: bool = True,
) -> tuple[RawDataset, dict[str, Any]] | None:
    """A :data:`COMPOSITES` dataset from its built parts (``(raw, card)`` in :func:`composite_parts`
    order): their rows concatenated, the card as :func:`build` makes it, with ``joined_from``.
    The same rows as :func:`build` rolls out, in seconds instead of one rollout per part. None when
    a part's card does not record this seed's SAC run (another run's evaluation curve) or these
    package versions (rollouts under other simulator or JAX versions may differ): the caller then
    builds the dataset whole."""
    env, kind = parse_name(name)
    wanted = composite_parts(name)
    if len(parts) != len(wanted):
        raise SpotError(f"join('{name}'): got {len(parts)} parts; expected {len(wanted)} ({', '.join(wanted)})")
    cards = [card for _, card in parts]
    if any(card.get("versions") != versions() or not isinstance(card.get("behaviour"), dict) for card in cards):
        return None  # checked before the SAC run is loaded
    start = time.perf_counter()
    result, cache_hit = train_or_load_sac(env, size, seed, cache_dir, progress)
    if any(card["behaviour"].get("eval_curve") != _eval_curve(result) for card in cards):
        return None
    episodes: list[dict[str, np.ndarray]] = []
    episode_kind: list[str] = []
    for part, (raw, _) in zip(COMPOSITES[kind], parts, strict=True):
        eps = _split(raw, f"{env}-{part} ({size}, seed {seed})")
        episodes += eps
        episode_kind += [part] * len(eps)
    raw, card = _finish(name, size, seed, episodes, episode_kind, result, cache_hit, start)
    card["joined_from"] = wanted
    return raw, card


def normalized(env: str, returns: Any) -> Any:
    """D4RL normalised score ``100 (R - R_random) / (R_expert - R_random)`` (d4rl/infos.py refs)."""
    lo, hi = envs.D4RL_REF_SCORES[env]
    return 100.0 * (np.asarray(returns, np.float64) - lo) / (hi - lo)


def make_card(
    name: str,
    size: str,
    seed: int,
    raw: RawDataset,
    episodes: list[dict[str, np.ndarray]],
    result: sac_train.SACResult,
    medium: sac_train.Snapshot,
    medium_fraction: float,
) -> dict[str, Any]:
    """The data card: layout, episode returns (raw and D4RL-normalised), the behaviour policies'
    evaluation returns and normalised scores beside D4RL's references, and SAC's length, time and
    memory. ``build`` adds ``sac_cache_hit``, ``build_time_s`` and ``peak_rss_mb`` (the build
    process's peak resident memory, MiB)."""
    env, _ = parse_name(name)
    cfg, expert = result.config, result.snapshots[-1]
    returns = np.array([ep["rewards"].sum(dtype=np.float64) for ep in episodes])
    lengths = np.array([len(ep["rewards"]) for ep in episodes])
    lo, hi = envs.D4RL_REF_SCORES[env]
    return {
        "recipe": RECIPE,
        "recipe_version": recipe_version(name, size),
        "name": name,
        "env": ENV_IDS[env],
        "model": envs.LOCOMOTION_MODELS.get(env, "default"),
        "size": size,
        "seed": seed,
        "transitions": len(raw),
        "episodes": len(episodes),
        "obs_dim": int(raw.observations.shape[1]),
        "act_dim": int(raw.actions.shape[1]),
        "terminal_episodes": int(raw.terminals.sum()),
        "return": {
            "mean": float(returns.mean()),
            "std": float(returns.std()),
            "min": float(returns.min()),
            "max": float(returns.max()),
            "normalized_mean": round(float(normalized(env, returns).mean()), 2),
        },
        "episode_length_mean": float(lengths.mean()),
        "behaviour": {
            "rollout_policy": "stochastic",
            "medium_fraction": medium_fraction,
            "medium_snapshot_step": medium.step,
            "medium_eval_return": medium.eval_return,
            "medium_normalized": round(float(normalized(env, medium.eval_return)), 2),
            "expert_snapshot_step": expert.step,
            "expert_eval_return": expert.eval_return,
            "expert_normalized": round(float(normalized(env, expert.eval_return)), 2),
            "target_return": cfg.target_return,
            "target_reached": result.target_reached,
            "stop_policy": cfg.stop_policy,
            "stop_evals": cfg.stop_evals,
            **_stochastic_evals(result, medium),
            "d4rl_reference": {
                "random_return": lo,
                "expert_return": hi,
                "source": "d4rl/infos.py REF_MIN_SCORE / REF_MAX_SCORE",
            },
            "eval_episodes": cfg.eval_episodes,
            "eval_curve": _eval_curve(result),
        },
        "sac": {
            "steps": expert.step,
            "step_cap": cfg.total_steps,
            "hidden_dims": list(cfg.hidden_dims),
            "batch_size": cfg.batch_size,
            "train_time_s": round(result.timing["total"], 1),
            "peak_rss_mb": round(result.timing.get("peak_rss_mb", 0.0), 1),
            "resumed_from": list(result.resumed_from),
        },
        "versions": versions(),
    }
