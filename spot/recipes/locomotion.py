"""D4RL locomotion datasets (Fu et al., 2020, arXiv:2004.07219) rebuilt locally in gymnasium MuJoCo,
for Hopper-v5 and Walker2d-v5 (1000-step episodes).

D4RL's recipe, which this module follows:

1. Train SAC online (:mod:`spot.recipes.sac`), saving the actor at every evaluation. At size
   ``paper`` it trains until the deterministic evaluation return (mean of 10 episodes) reaches
   D4RL's expert level (:data:`PAPER_STOP`: Hopper 3000, Walker2d 4000; D4RL's expert references
   are 3234.3 and 4592.3), with a step cap. One training per ``(env, size, seed)`` serves all
   five datasets: its snapshots and replay buffer are cached under ``cache_dir/sac/`` (msgpack,
   written atomically, under a file lock). While it trains, a checkpoint (learner, optimisers,
   replay buffer, snapshots, generators, simulator state) is written every ``checkpoint_every``
   steps beside the cache file, and a killed build resumes from it bit for bit.
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

Sizes (per env): ``tiny`` for tests (3k SAC steps with 32x32 nets, 2k-row datasets; seconds),
``small`` (80k SAC steps with 128x128 nets, 100k-row datasets; minutes on 2 CPU cores),
``paper`` (D4RL: SAC with the paper's settings until the expert level, 1M-row datasets),
``paper-fast`` (``paper``'s rows and stop rule; ``small``'s SAC networks, batch and learning rates,
about 4x cheaper per step here: the size that builds Walker2d on 2 CPU cores). The same seed gives the same
arrays on the same
machine: environments are reset with derived seeds, and every random draw comes from a jax key
or a numpy generator made from the seed.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import os
import sys
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
from spot import SpotError, envs, store
from spot.data.dataset import RawDataset, raw_from_episodes
from spot.recipes import sac

RECIPE = "d4rl-sac-locomotion"
RECIPE_VERSION = 2  # bump when a change here alters the SAC cache or the datasets
ENV_IDS = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5"}
KINDS = ("medium", "medium-replay", "expert", "medium-expert", "full-replay")
_ROLLOUT_TAGS = {"medium": 2, "expert": 3}  # seed streams; SAC's evaluations use tags 1 and 4 (spot.recipes.sac)
COMPOSITES: dict[str, tuple[str, ...]] = {"medium-expert": ("medium", "expert")}
"""Kinds whose rows are exactly other kinds' rows of the same size and seed, in order: the
registry joins the built parts (:func:`join`) instead of rolling them out again."""


@dataclass(frozen=True)
class StopRule:
    """When SAC stops: once ``evals`` evaluations in a row have a mean return of the ``policy``
    (``"deterministic"``: mean actions; ``"stochastic"``: sampled, as the rollouts) that reaches
    ``target``, or at ``cap`` steps (:class:`spot.recipes.sac.SACConfig`)."""

    target: float
    cap: int
    policy: str = "deterministic"
    evals: int = 1

    def __post_init__(self) -> None:
        if self.policy not in sac.STOP_POLICIES:
            raise SpotError(f"StopRule.policy = {self.policy!r}; expected one of {', '.join(sac.STOP_POLICIES)}")
        if self.evals < 1 or self.cap < 1 or not np.isfinite(self.target):
            raise SpotError(
                f"StopRule(target={self.target}, cap={self.cap}, evals={self.evals}): expected a finite "
                "target, a positive cap and at least one evaluation"
            )


@dataclass(frozen=True)
class SizeSpec:
    """How big one size is."""

    sac: sac.SACConfig
    """The SAC run whose snapshots and buffer make the data."""
    transitions: int
    """Rows of ``medium`` and of ``expert`` each (``medium-expert`` has twice as many)."""
    medium_fraction: float = 1.0 / 3.0
    """``medium`` is the first snapshot whose eval return reaches this fraction of the final one's."""
    stop: dict[str, StopRule] = dataclasses.field(default_factory=dict)
    """Per env: when SAC stops (:class:`StopRule`). Envs not listed run ``sac.total_steps``."""
    checkpoint_every: int = 0
    """SAC checkpoint interval in environment steps (0: none)."""

    def sac_config(self, env: str) -> sac.SACConfig:
        """The SAC config of ``env`` at this size (with its stop rule, if any)."""
        if env not in self.stop:
            return self.sac
        rule = self.stop[env]
        return dataclasses.replace(
            self.sac,
            target_return=rule.target,
            total_steps=rule.cap,
            stop_policy=rule.policy,
            stop_evals=rule.evals,
        )


# D4RL's expert level (its expert references are 3234.3 and 4592.3) and a step cap per env.
PAPER_STOP = {"hopper": StopRule(3000.0, 2_000_000), "walker2d": StopRule(4000.0, 3_000_000)}
# paper-fast: the same targets and caps. Hopper's rule reads the stochastic policy, which the data
# are rolled out with, twice in a row: at size paper one deterministic evaluation of 3053 +- 594
# stopped SAC while its stochastic rollouts scored 1,741 (normalised 54), so that `expert` is not
# D4RL-grade. Walker2d keeps paper's rule: its stochastic rollouts scored like its deterministic
# evaluation (4,063 against 4,034), and its paper-fast data were built under that rule.
PAPER_FAST_STOP = {**PAPER_STOP, "hopper": StopRule(3000.0, 2_000_000, policy="stochastic", evals=2)}


# small's SAC networks, batch and learning rates, shared by sizes small and paper-fast
_SMALL_SAC: dict[str, Any] = {
    "hidden_dims": (128, 128),
    "batch_size": 128,
    "actor_lr": 1e-3,
    "critic_lr": 1e-3,
    "temperature_lr": 1e-3,
}

SIZES: dict[str, SizeSpec] = {
    "tiny": SizeSpec(
        sac.SACConfig(
            hidden_dims=(32, 32),
            batch_size=64,
            total_steps=3000,
            start_steps=1000,
            update_every=500,
            eval_every=500,
            eval_episodes=2,
        ),
        transitions=2000,
        checkpoint_every=1000,
    ),
    # 128x128 nets, batch 128 and lr 1e-3 learn Hopper faster per CPU second than the paper's
    # 256x256 / 256 / 3e-4: on 2 busy shared cores, 80k steps took ~7 min and reached an eval
    # return of ~820, where the paper's settings reached ~700 after 60k steps in 10 min.
    "small": SizeSpec(
        sac.SACConfig(
            **_SMALL_SAC,
            total_steps=80_000,
            start_steps=5000,
            update_every=1000,
            eval_every=2000,
            eval_episodes=5,
        ),
        transitions=100_000,
        checkpoint_every=20_000,
    ),
    "paper": SizeSpec(sac.SACConfig(), transitions=1_000_000, stop=PAPER_STOP, checkpoint_every=50_000),
    # paper's rows and stop targets with small's SAC: `spot bench sac` on 2 CPU cores measured an
    # update of 2.0 ms against 8.8 ms, 411 against 107 steps/s. The paper SAC's Walker2d scored 300-500
    # over its first 90k steps; this one reached the 4000 target at 270k steps in 985 s.
    "paper-fast": SizeSpec(
        sac.SACConfig(**_SMALL_SAC),
        transitions=1_000_000,
        stop=PAPER_FAST_STOP,
        checkpoint_every=50_000,
    ),
}


def recipe_version(name: str, size: str) -> int | str:
    """The version a card of ``name`` at ``size`` records (the registry rebuilds a file whose card
    holds another): :data:`RECIPE_VERSION`, with the stop rule's policy and count appended where
    they are not the first rule's (one deterministic evaluation), so data built under one
    (policy, count) never pass for another's. A change of a target or cap changes the SAC run's cache
    name (:func:`sac_cache_path`) but not this: bump :data:`RECIPE_VERSION` with it."""
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


def _versions() -> dict[str, str]:
    return {"spot": spot.__version__, **{p: version(p) for p in ("gymnasium", "mujoco", "jax", "flax")}}


# ------------------------------------------------------------------------------------ SAC cache
def _make_kwargs(env: str) -> dict[str, Any]:
    return dict(envs.locomotion_make_kwargs(env))


def sac_cache_path(cache_dir: Path, env: str, size: str, seed: int) -> Path:
    """Cache file of one SAC training; its name hashes everything the training depends on.

    Its checkpoint, while it trains, is the same name with the suffix ``.ckpt``.
    """
    env_id = ENV_IDS[env]
    deps = {
        "recipe_version": RECIPE_VERSION,
        "env_id": env_id,
        "seed": seed,
        "model": envs.LOCOMOTION_MODELS.get(env),
        "sac": sac.identity(SIZES[size].sac_config(env)),
        "versions": _versions(),
    }
    digest = hashlib.sha256(json.dumps(deps, sort_keys=True).encode()).hexdigest()[:12]
    return Path(cache_dir) / "sac" / f"{env_id}__{size}__seed{seed}__{digest}.msgpack"


def _save(result: sac.SACResult, path: Path) -> None:
    payload = {
        "snapshots": {str(i): s.to_dict() for i, s in enumerate(result.snapshots)},
        "replay": result.replay,
        "timing": result.timing,
        "resumed_from": np.asarray(result.resumed_from, np.int64),
    }
    store.write_atomic(path, serialization.msgpack_serialize(payload), fsync=True)  # full disk: SpotError
    _write_checksum(path)


def checksum_path(path: Path) -> Path:
    """The sidecar ``<cache file>.sha256`` holding the cache file's sha256 (the file itself, its
    name and format are unchanged by it: a file cached before checksums still loads)."""
    return path.with_name(path.name + ".sha256")


def _write_checksum(path: Path) -> str:
    from spot.data.fetch import sha256_file

    digest = sha256_file(path)
    store.write_atomic(checksum_path(path), f"{digest}  {path.name}\n".encode())
    return digest


def _load_checked(path: Path, env_id: str, seed: int, cfg: sac.SACConfig, progress: bool) -> sac.SACResult | None:
    """The cached SAC run at ``path``, or None when it is damaged (then it is moved to
    ``<name>.damaged`` and trained again). With a ``.sha256`` sidecar the file's sum must match it;
    without one (cached before checksums) the file must load, and the sidecar is then written."""
    from spot.data.fetch import sha256_file

    side = checksum_path(path)
    want = None
    if side.exists():
        try:
            want = side.read_text().split()[0]
        except (OSError, UnicodeDecodeError, IndexError):
            want = ""
    why = None
    if want is not None and (got := sha256_file(path)) != want:
        why = f"sha256 {got}, but {side.name} records {want or 'nothing readable'}"
    else:
        try:
            result = _load(path, env_id, seed, cfg)
        except MemoryError:
            raise
        except Exception as err:  # noqa: BLE001 - a truncated or altered msgpack can raise anything
            why = f"it does not load ({type(err).__name__}: {err})"[:500]
        else:
            if want is None:
                digest = _write_checksum(path)
                if progress:
                    print(
                        f"spot: SAC cache {path.name} had no checksum; it loads, recorded sha256 {digest}",
                        file=sys.stderr,
                    )
            return result
    aside = path.with_suffix(".damaged")
    os.replace(path, aside)
    side.unlink(missing_ok=True)
    print(f"spot: SAC cache {path} is damaged ({why}); moved to {aside.name}, training it again", file=sys.stderr)
    return None


def _load(path: Path, env_id: str, seed: int, cfg: sac.SACConfig) -> sac.SACResult:
    payload = serialization.msgpack_restore(path.read_bytes())
    snaps = [payload["snapshots"][str(i)] for i in range(len(payload["snapshots"]))]
    snapshots = [sac.Snapshot.from_dict(s) for s in snaps]
    return sac.SACResult(
        env_id,
        seed,
        cfg,
        snapshots,
        dict(payload["replay"]),
        {k: float(v) for k, v in payload["timing"].items()},
        tuple(int(x) for x in payload["resumed_from"]),
    )


def train_or_load_sac(
    env: str, size: str, seed: int, cache_dir: Path, progress: bool = True
) -> tuple[sac.SACResult, bool]:
    """The SAC run of ``(env, size, seed)``: from the cache if there, else trained and cached.

    Returns the result and whether it came from the cache. A file lock makes concurrent builds
    of the same run train it once; a checkpoint left by a killed build is resumed.
    """
    env_id = ENV_IDS[env]
    cfg = SIZES[size].sac_config(env)
    path = sac_cache_path(cache_dir, env, size, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            from spot.data.registry import clean_stale_temp

            clean_stale_temp(path.parent)  # temp files of killed builds (dead pid, old)
            if path.exists():
                cached = _load_checked(path, env_id, seed, cfg, progress)
                if cached is not None:
                    return cached, True
            checkpoint = path.with_suffix(".ckpt")
            if progress and checkpoint.exists():
                print(f"spot: resuming SAC {env_id} ({size}, seed {seed}) from {checkpoint}", file=sys.stderr)
            result = sac.train_sac(
                env_id,
                cfg,
                seed,
                on_eval=_print_eval(env_id) if progress else None,
                progress=progress,
                checkpoint=checkpoint,
                checkpoint_every=SIZES[size].checkpoint_every,
                make_kwargs=_make_kwargs(env),
            )
            _save(result, path)
            checkpoint.unlink(missing_ok=True)
            return result, False
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _print_eval(env_id: str):
    start = time.perf_counter()

    def on_eval(step: int, metrics: dict[str, float]) -> None:
        stoch = metrics.get("eval/stochastic_return_mean")
        sampled = "" if stoch is None else f", stochastic {stoch:.1f} ± {metrics['eval/stochastic_return_std']:.1f}"
        print(
            f"spot: SAC {env_id} step {step}: eval return {metrics['eval/return_mean']:.1f} "
            f"± {metrics['eval/return_std']:.1f}{sampled} ({time.perf_counter() - start:.0f} s this session)",
            file=sys.stderr,
            flush=True,
        )

    return on_eval


# ------------------------------------------------------------------------------------- datasets
def pick_medium(snapshots: list[sac.Snapshot], fraction: float) -> sac.Snapshot:
    """First snapshot whose eval return reaches ``fraction`` of the last (expert) snapshot's."""
    threshold = fraction * snapshots[-1].eval_return
    return next(s for s in snapshots if s.eval_return >= threshold)


def _rollouts(
    env_name: str, params: Any, cfg: sac.SACConfig, transitions: int, seed: int, tag: int, desc: str, progress: bool
) -> list[dict[str, np.ndarray]]:
    """Stochastic-policy episodes until exactly ``transitions`` rows (the last cut, as a timeout)."""
    env = sac.make_env(ENV_IDS[env_name], cfg, **_make_kwargs(env_name))
    key = jax.random.fold_in(jax.random.key(seed), tag)
    env_seed = int(np.random.SeedSequence([seed, tag]).generate_state(1)[0])
    episodes: list[dict[str, np.ndarray]] = []
    total = 0
    with tqdm(total=transitions, desc=desc, unit="step", disable=not progress) as bar:
        while total < transitions:
            ep = sac.run_episode(
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
            f"{sac.stop_value(expert, result.config):.0f})",
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
    result: sac.SACResult,
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
    card["peak_rss_mb"] = round(sac.peak_rss_mb(), 1)
    return raw, card


def composite_parts(name: str) -> list[str]:
    """The datasets whose rows make up ``name``, in order (``hopper-medium-expert`` ->
    ``[hopper-medium, hopper-expert]``); ``[]`` for a dataset that is not a composite."""
    env, kind = parse_name(name)
    return [f"{env}-{part}" for part in COMPOSITES.get(kind, ())]


def _stochastic_evals(result: sac.SACResult, medium: sac.Snapshot) -> dict[str, Any]:
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


def _eval_curve(result: sac.SACResult) -> list[list[float]]:
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
    if any(card.get("versions") != _versions() or not isinstance(card.get("behaviour"), dict) for card in cards):
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
    result: sac.SACResult,
    medium: sac.Snapshot,
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
        "versions": _versions(),
    }
