"""The stages of one run, their typed outputs, and the table that picks them per method.

A run is ``labels -> reward -> relabel -> [subgoals -> cvae -> shaping -> diagnostics] -> policy``
(docs/design.md draws it). Each stage is a function ``stage(ctx, *inputs) -> output`` over a
:class:`Context` (config, dataset, keys, tracker, stage cache) and the typed outputs of earlier
stages (:class:`Labelled`, :class:`RewardModel`, :class:`Rewards`, :class:`Subgoals`,
:class:`Policy`). :meth:`Context.stage` wraps every stage the same way: it times it
(``time/<stage>_s``) and the stage's expensive part goes through :meth:`Context.cached`, which
tags the run ``cache.<stage> = hit | miss``. The trained models are saved as run artifacts
(:func:`save_model`: ``models/reward_model``, ``models/cvae``, ``models/policy``, data only, with a
JSON header), so a run can be evaluated again (``spot eval``) without the stage cache. Which
functions fill the reward, relabel and policy slots is read from
:data:`REWARD_KINDS` by ``reward.kind`` (set by the method preset); adding a method is one
:func:`register` call plus the module with its stage functions.

Where normalisation sits: the reward model's per-step output is relabelled over the whole dataset,
normalised (``relabel.normalize``), and only then is the shaping term added,
``r = norm(r_model) + λ r_shape`` (eq. 13), so that λ = 1 adds a bonus in [0, 1] beside a reward of
the scale IQL's hyperparameters expect.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from spot import SpotError, cache, phases
from spot import config as config_lib
from spot.config import ExperimentConfig
from spot.tracking import Tracker, record


# --------------------------------------------------------------------------- typed outputs
@dataclass(frozen=True)
class Labelled:
    """Preference queries: all of them, the training split, and their segment batches."""

    prefs: Any  # spot.data.labels.Preferences, all queries
    train_prefs: Any
    train_batch: dict[str, np.ndarray]
    eval_batch: dict[str, np.ndarray] | None
    deps: dict[str, Any]  # what identifies them in stage-cache keys


@dataclass(frozen=True)
class RewardModel:
    """A trained reward model: its parameters and the stage-cache key that identifies it; ``cvae``:
    the CVAE trained with it (``cvae.schedule=online``: ``{"params", "history"}``), else None."""

    kind: str
    params: Any
    cache_key: str
    cvae: Any = None


@dataclass(frozen=True)
class Rewards:
    """Per-transition rewards ``[N]``: the model's raw output and the normalised training reward."""

    model: np.ndarray
    normalised: np.ndarray
    source: RewardModel | None = None


@dataclass(frozen=True)
class Subgoals:
    """Attention subgoals of the preferred segments and the CVAE trained to propose them."""

    triplets: Any  # spot.subgoal.extract.Triplets (s, a, g)
    states: np.ndarray
    cvae_params: Any


@dataclass(frozen=True)
class Shaped:
    """The reward the policy trains on, and the cosine to the subgoal (Fig. 2's proximity axis)."""

    reward: np.ndarray
    cos_to_subgoal: np.ndarray | None = None


@dataclass(frozen=True)
class Policy:
    """The trained policy's state and its evaluation curve."""

    state: Any
    steps: list[int]
    scores: list[float]
    eval_s: float


# --------------------------------------------------------------------------- context
@dataclass
class Context:
    """Everything a stage may read besides earlier stages' outputs."""

    cfg: ExperimentConfig
    ds: Any  # spot.data.dataset.Dataset (qlearning view)
    card: dict[str, Any]
    env_name: str
    tracker: Tracker
    keys: dict[str, Any]  # PRNG keys per stage: reward, cvae, shaping, policy
    progress: bool = True
    on_eval: Callable[[dict[str, float]], None] | None = None
    artifacts: Path = field(default_factory=lambda: record.run_temp_dir())  # $SPOT_CACHE_DIR/tmp
    times: dict[str, float] = field(default_factory=dict)
    cache_hits: list[str] = field(default_factory=list)  # stage-cache keys read (hits), in order
    # stage -> (key, value) computed for this run outside its stage (seed_mode vmap: the seeds'
    # reward models as one program); the stage stores and logs it as computed (:meth:`cached`)
    precomputed: dict[str, tuple[str, Any]] = field(default_factory=dict)
    # added to every stage's deps: ``{"seed_mode": "vmap"}`` in a vmap trial, whose reward models
    # and CVAEs differ from one-seed training in the last bits (more after Adam): kept apart, so a
    # one-seed run never depends on whether a vmap trial filled the cache first
    key_extra: dict[str, Any] = field(default_factory=dict)

    def log(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        self.tracker.log_metrics(metrics, step=step)

    @contextmanager
    def timed(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            k = f"time/{name}_s"
            self.times[k] = self.times.get(k, 0.0) + time.perf_counter() - t0

    def stage(self, name: str, fn: Callable[..., Any], *inputs: Any) -> Any:
        """Run one stage, timed as ``time/<name>_s`` (stages marked :func:`untimed` are not)."""
        if getattr(fn, "untimed", False):
            return self._run_evicting(name, fn, inputs)
        with self.timed(name):
            return self._run_evicting(name, fn, inputs)

    def _run_evicting(self, name: str, fn: Callable[..., Any], inputs: tuple) -> Any:
        """``fn(self, *inputs)``; when it fails on a value its stage-cache hits returned (an entry
        that decodes, digest and all, to a value of the wrong structure: KeyError, TypeError...),
        those entries are deleted and the stage runs once more, computing them again."""
        before = len(self.cache_hits)
        try:
            return fn(self, *inputs)
        except SpotError:
            raise
        except (KeyError, TypeError, AttributeError, IndexError, ValueError) as e:
            hits = self.cache_hits[before:]
            if not hits:
                raise
            del self.cache_hits[before:]
            import warnings

            warnings.warn(
                f"stage '{name}': cached entries {hits} do not fit it ({type(e).__name__}: {e}); "
                "deleting and recomputing them",
                stacklevel=2,
            )
            for k in hits:
                cache._store().delete(f"{k}.npz")  # the entry's store (local folder or spot.store URI)
            return fn(self, *inputs)

    def _precomputed(self, name: str, key: str, compute: Callable[[], Any]) -> Callable[[], Any]:
        """What computes stage ``name``'s entry ``key`` on a miss: the value computed for it outside
        the stage when its key is this one, else ``compute`` (with a warning: the two computed the
        key differently, so the value was not used)."""
        pre_key, value = self.precomputed.pop(name)
        if pre_key == key:
            return lambda: value
        import warnings

        warnings.warn(
            f"stage '{name}': a value computed for key {pre_key} does not fit key {key}; computing it here",
            stacklevel=3,
        )
        return compute

    def cached(
        self, name: str, deps: dict[str, Any], compute: Callable[[], Any], code: str | None = None
    ) -> tuple[Any, str]:
        """``(value, key)`` of stage ``name`` from the stage cache (computed and stored on a miss);
        tags the run ``cache.<name>`` = ``hit`` or ``miss`` (a tag, not a metric: it is a fact
        about the run, not a measurement) and ``stage.<name>.source`` = ``computed`` or ``reused`` and
        ``stage.<name>.key`` = the entry's key (the run that computed an entry others reused: the one
        with the same key and ``computed``). ``code``: the stage's code version (default: that of
        ``compute``'s stage function, :func:`spot.cache.code_version`); ``deps`` get :attr:`key_extra`."""
        deps = {**deps, **self.key_extra}
        if name in self.precomputed:
            code = code if code is not None else cache.code_version(compute)
            compute = self._precomputed(name, cache.key(name, deps, code), compute)
        value, hit, key = cache.cached(name, deps, compute, code)
        if hit:
            self.cache_hits.append(key)
        self.tracker.set_tags(
            {
                f"cache.{name}": "hit" if hit else "miss",
                f"stage.{name}.source": "reused" if hit else "computed",
                f"stage.{name}.key": key,
            }
        )
        return value, key


def save_model(ctx: Context, name: str, what: str, value: Any, sections: tuple[str, ...], **extra: Any) -> None:
    """Save a trained model as the run's ``models/<name>`` artifacts (:mod:`spot.tracking.models`),
    its header naming the config ``sections`` it was built with."""
    from spot import tracking

    cfg = config_lib.to_flat(ctx.cfg)
    section_cfg = {s: {k.split(".", 1)[1]: v for k, v in cfg.items() if k.startswith(f"{s}.")} for s in sections}
    tracking.save_model(
        ctx.tracker,
        ctx.artifacts / "models",
        name,
        what,
        value,
        {"method": ctx.cfg.method, **section_cfg},
        dataset=ctx.card.get("name", ctx.cfg.data.name),
        **extra,
    )


def eval_seed(cfg: ExperimentConfig) -> int:
    """The base seed of a run's evaluation episodes (episode ``i`` is seeded ``eval_seed + i``; the
    same episodes at every evaluation, and in ``spot eval``)."""
    return 10_000 * (cfg.seed + 1)


def untimed(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Mark a stage that computes nothing worth timing (e.g. the Oracle's "reward model"), so that
    Table 8 charges no reward-model time to methods without one."""
    fn.untimed = True  # type: ignore[attr-defined]
    return fn


def dataset_deps(ds: Any) -> dict[str, Any]:
    """What identifies the dataset in stage-cache keys: the fingerprint of all its arrays
    (:meth:`spot.data.dataset.Dataset.fingerprint`: episode ends, next observations and infos too)."""
    return {"dataset": ds.fingerprint()}


# --------------------------------------------------------------------------- labels
PT_HUMAN_LABELS = Path(__file__).resolve().parent / "data" / "pt_human_labels"
"""The PT repo's human label files (csmile-1006/PreferenceTransformer f71647b ``human_label/``,
MIT), shipped unchanged with spot; ``PROVENANCE.md`` there says where they come from."""


def human_label_folder(card: Mapping[str, Any]) -> Path | None:
    """The shipped PT human label folder that indexes this dataset, or None.

    Only a real D4RL/robomimic file qualifies: a dataset read from a file (``card["source"] ==
    "file"``) whose card names no spot recipe (a locally built dataset's card says which recipe
    built it, and PT's indices point into the real file's rows). The file is matched by name:
    D4RL ``hopper_medium_replay-v2.hdf5`` (or with hyphens) -> ``hopper-medium-replay-v2``;
    robomimic ``lift/ph/low_dim*.hdf5`` -> ``Lift_ph``.
    """
    if card.get("source") != "file" or "recipe" in card:
        return None
    from spot.data.labels import pt_label_folder

    by_name = pt_label_folder(str(card.get("name") or ""), PT_HUMAN_LABELS)  # a resolved real name (registry)
    if by_name is not None:
        return by_name
    path = Path(str(card.get("path") or card.get("name") or ""))
    names = [path.stem.replace("_", "-")]
    if path.stem.startswith("low_dim") and len(path.parts) >= 3:
        names.append(f"{path.parts[-3].lower().capitalize()}_{path.parts[-2].lower()}")
    for name in names:
        if name and (PT_HUMAN_LABELS / name / "label_human").is_file():
            return PT_HUMAN_LABELS / name
    return None


def label_source(cfg: ExperimentConfig, card: Mapping[str, Any] | None) -> tuple[str, str]:
    """``(source, path)`` the run's labels come from: ``labels.source=auto`` resolves to the shipped
    PT human files when :func:`human_label_folder` finds them, to the scripted teacher otherwise."""
    lc = cfg.labels
    if lc.source == "auto":
        folder = human_label_folder(card or {})
        return ("human", str(folder)) if folder is not None else ("script", "")
    return lc.source, lc.path


def make_preferences(cfg: ExperimentConfig, ds: Any, card: Mapping[str, Any] | None = None) -> Any:
    """The run's preference queries (scripted teacher or PT human label files), checked against
    ``ds``; ``card`` (the dataset's) decides ``labels.source=auto`` (:func:`label_source`)."""
    from spot.data import labels

    lc = cfg.labels
    source, path = label_source(cfg, card)
    if source == "human":
        if not path:
            raise SpotError("labels.source=human needs labels.path (a folder of PT label files)")
        prefs = labels.read_pt_labels(path, num_queries=lc.num_queries)
        labels.check_against(prefs, ds, allow_cross_episode=True)
        return prefs
    return labels.scripted_teacher(
        ds,
        lc.num_queries,
        lc.segment_length,
        teacher=lc.teacher,
        discount=lc.discount,
        tie_threshold=lc.tie_threshold,
        mistake_rate=lc.mistake_rate,
        allow_cross_episode=lc.allow_cross_episode,
        seed=lc.seed,
        score=lc.score,
    )


def pt_eval_subset(prefs: Any, fraction: float) -> Any:
    """The PT repo's reward-model evaluation queries: the last ``int(fraction * Q)`` of them (at
    least one when ``fraction > 0``), which the model also trains on (``labels.eval_split=pt_subset``)."""
    n_eval = max(1, int(fraction * len(prefs))) if fraction > 0 else 0
    return prefs.subset(np.arange(len(prefs) - n_eval, len(prefs)))


def split_queries(prefs: Any, cfg: ExperimentConfig) -> tuple[Any, Any]:
    """``(train, eval)`` queries by ``labels.eval_split``: ``holdout`` = a random disjoint split;
    ``pt_subset`` = all queries for training and :func:`pt_eval_subset` for evaluation."""
    from spot.data import labels

    lc = cfg.labels
    if lc.eval_split == "pt_subset":
        return prefs, pt_eval_subset(prefs, lc.eval_fraction)
    return labels.split_eval(prefs, lc.eval_fraction, lc.seed)


def labels_stage(ctx: Context) -> Labelled:
    """Queries, their train/evaluation split (``labels.eval_split``) and segment batches."""
    from spot.data import labels

    cfg, ds = ctx.cfg, ctx.ds
    source, path = label_source(cfg, ctx.card)
    ctx.tracker.set_tags({"labels.resolved_source": source, **({"labels.resolved_path": path} if path else {})})
    prefs = make_preferences(cfg, ds, ctx.card)
    train_prefs, eval_prefs = split_queries(prefs, cfg)
    train_batch = labels.segment_batch(ds, train_prefs)
    eval_batch = labels.segment_batch(ds, eval_prefs) if len(eval_prefs) else None
    ctx.log(
        {
            "labels/queries": len(prefs),
            "labels/ties": float(np.sum(prefs.labels == 0.5)),
            "labels/segment_length": prefs.segment_length,
        }
    )
    deps = {
        "s1": prefs.starts_1,
        "s2": prefs.starts_2,
        "y": prefs.labels,
        "length": prefs.segment_length,
        "split": (cfg.labels.eval_fraction, cfg.labels.seed),
        **({"eval_split": cfg.labels.eval_split} if cfg.labels.eval_split != "holdout" else {}),
    }
    return Labelled(prefs, train_prefs, train_batch, eval_batch, deps)


def _reward_deps(ctx: Context, labelled: Labelled, **extra: Any) -> dict[str, Any]:
    return {"data": dataset_deps(ctx.ds), "labels": labelled.deps, "seed": ctx.cfg.seed, **extra}


def _corr_true(r_model: np.ndarray, r_true: np.ndarray) -> float:
    return float(np.corrcoef(r_model, r_true)[0, 1]) if r_model.std() > 0 else 0.0


# --------------------------------------------------------------------------- reward stages
@untimed
def true_reward(ctx: Context, labelled: Labelled | None) -> None:
    """Oracle: no reward model."""
    return None


def learned_reward(ctx: Context, labelled: Labelled) -> RewardModel:
    """MR or PT trained on the preferences (eq. 1-2), best held-out checkpoint; cached."""
    return _learned_reward(ctx, labelled, None, cache.code_version(learned_reward))


def learned_reward_online(ctx: Context, labelled: Labelled) -> RewardModel:
    """PT as :func:`learned_reward`, with the CVAE trained alongside it (``cvae.schedule=online``:
    one CVAE step per reward-model step, :mod:`spot.subgoal.online`), both in one cache entry whose
    code version covers the CVAE's code too (:func:`stages_of` picks this stage)."""
    return _learned_reward(ctx, labelled, lambda: _online_companion(ctx), cache.code_version(learned_reward_online))


def _learned_reward(ctx: Context, labelled: Labelled, companion: Callable[[], Any] | None, code: str) -> RewardModel:
    """The reward stage of MR/PT; ``companion()`` builds the online CVAE (None: no CVAE here);
    ``code``: the stage's code version in its cache key."""
    from spot.reward import models
    from spot.reward import train as reward_train

    cfg = ctx.cfg
    model = models.from_config(cfg)
    online = companion is not None
    deps = _reward_deps(ctx, labelled, reward=model.kind, reward_cfg=cfg.reward, model_cfg=model.cfg)
    if online:  # the CVAE trained with the reward model is part of its entry
        deps["cvae_online"] = {"subgoal": cfg.subgoal, "cvae": cfg.cvae, "state_action": cfg.shaping.state_action}

    def compute() -> dict[str, Any]:
        clip = cfg.reward.clip_action
        params, history = reward_train.train_reward_model(
            model,
            ctx.keys["reward"],
            reward_train.clip_actions(labelled.train_batch, clip),
            reward_train.clip_actions(labelled.eval_batch, clip),
            cfg.reward,
            progress=ctx.progress,
            companion=companion() if online else None,
        )
        if not online:
            return {"params": params, "history": history}
        cvae_history = [
            {"step": step, **{k: history["companion"][k][i] for k in history["companion"]}}
            for i, step in enumerate(history["step"])
        ]
        state = history.pop("companion_state")
        cvae = {"params": state.params, "history": cvae_history, "steps": int(state.step)}
        history.pop("companion")
        return {"params": params, "history": history, "cvae": cvae}

    out, key = ctx.cached("reward", deps, compute, code=code)
    h = out["history"]
    names = ("train_loss", "train_acc", "eval_loss", "eval_acc")
    for name in names:
        ctx.tracker.log_series(f"reward/{name}", h["step"], h[name])
    ctx.log({f"reward/{k}": h[k] for k in ("best_step", "best_eval_loss", "best_eval_acc", "steps_per_s")})
    if "steps" in h:
        ctx.log({"reward/steps": h["steps"]})
    save_model(
        ctx,
        "reward_model",
        f"{model.kind.upper()} reward model (best held-out checkpoint)",
        out["params"],
        ("reward", model.kind),
        kind=model.kind,
        cache_key=key,
    )
    return RewardModel(model.kind, out["params"], key, out.get("cvae"))


def hpl_reward(ctx: Context, labelled: Labelled) -> RewardModel:
    """HPL: hindsight VAE + reward r(s, a, z) trained on the preferences; cached."""
    import jax

    from spot.reward import hpl

    cfg = ctx.cfg
    train_key, _ = jax.random.split(ctx.keys["reward"])
    deps = _reward_deps(ctx, labelled, reward="hpl", hpl=cfg.hpl, reward_cfg=cfg.reward)

    def compute() -> dict[str, Any]:
        params, history = hpl.train_hpl(
            train_key, ctx.ds, labelled.train_batch, labelled.eval_batch, cfg.hpl, progress=ctx.progress
        )
        return {"params": params, "history": history}

    out, key = ctx.cached("reward", deps, compute)
    h = out["history"]
    ctx.log({f"reward/{k}": h[k] for k in ("best_step", "best_eval_loss", "best_eval_acc", "steps_per_s") if k in h})
    for k in ("vae_loss", "vae_recon", "vae_kl"):
        if k in h:
            ctx.tracker.log_series(f"hpl/{k}", h["vae_step"], h[k])
    for k in ("train_loss", "train_acc", "eval_loss", "eval_acc"):
        if k in h:
            n = min(len(h["reward_step"]), len(h[k]))
            ctx.tracker.log_series(f"reward/{k}", h["reward_step"][:n], h[k][:n])
    # Table 8: HPL's two pretraining phases, as measured when it was trained
    ctx.log({f"time/hpl_{name}": h[name] for name in ("vae_s", "reward_s") if name in h})
    save_model(
        ctx,
        "reward_model",
        "HPL hindsight VAE, prior and reward r(s, a, z)",
        out["params"],
        ("reward", "hpl"),
        kind="hpl",
        cache_key=key,
    )
    return RewardModel("hpl", out["params"], key)


# --------------------------------------------------------------------------- relabel stages
def normalisation_scale(cfg: ExperimentConfig, env_name: str) -> float:
    """``relabel.scale``, or the evaluation env's max episode steps where it is 0 (PT repo)."""
    from spot import envs

    return cfg.relabel.scale or float(envs.env_spec(env_name).max_episode_steps)


def _normalised(ctx: Context, r_model: np.ndarray, model: RewardModel | None) -> Rewards:
    from spot.reward import relabel

    if model is not None:
        ctx.log({"reward/corr_true": _corr_true(r_model, ctx.ds.rewards.astype(np.float32))})
    scale = normalisation_scale(ctx.cfg, ctx.env_name)
    return Rewards(r_model, relabel.normalize_rewards(r_model, ctx.ds, ctx.cfg.relabel.normalize, scale), model)


@untimed
def true_rewards(ctx: Context, model: None) -> Rewards:
    """The dataset's reward, normalised."""
    return _normalised(ctx, ctx.ds.rewards.astype(np.float32), None)


def model_rewards(ctx: Context, model: RewardModel) -> Rewards:
    """MR/PT: every transition relabelled by the reward model (chunked or sliding windows); cached."""
    from spot.reward import models, relabel

    cfg = ctx.cfg
    rel, _ = ctx.cached(
        "relabel",
        {"reward": model.cache_key, "relabel": cfg.relabel, "data": dataset_deps(ctx.ds)},
        lambda: relabel.relabel_rewards(
            models.from_config(cfg), model.params, ctx.ds, cfg.relabel, progress=ctx.progress
        )._asdict(),
    )
    return _normalised(ctx, np.asarray(rel["rewards"], np.float32), model)


def hpl_rewards(ctx: Context, model: RewardModel) -> Rewards:
    """HPL: the reward marginalised over the prior's latents; cached."""
    import jax

    from spot.reward import relabel

    _, relabel_key = jax.random.split(ctx.keys["reward"])
    rel, _ = ctx.cached(
        "relabel",
        {"hpl": model.cache_key, "seed": ctx.cfg.seed, "data": dataset_deps(ctx.ds)},
        lambda: {"rewards": relabel.relabel_hpl(model.params, ctx.ds, ctx.cfg.hpl, relabel_key)},
    )
    return _normalised(ctx, np.asarray(rel["rewards"], np.float32), model)


@untimed
def zero_rewards(ctx: Context, model: None) -> Rewards:
    """IPL learns no reward: the replay transitions carry zeros so no true reward leaks in."""
    zeros = np.zeros(len(ctx.ds), np.float32)
    return Rewards(zeros, zeros, None)


# --------------------------------------------------------------------------- subgoals, CVAE, shaping
def needs_subgoals(cfg: ExperimentConfig) -> bool:
    """SPOT shapes with subgoals; PT runs also extract them for the Fig. 2 diagnostics."""
    return cfg.reward.kind == "pt" and (cfg.shaping.kind != "none" or cfg.subgoal.diagnostics)


def online_cvae(cfg: ExperimentConfig) -> bool:
    """The CVAE trains during reward learning (``cvae.schedule=online``) in runs that need one."""
    return cfg.cvae.schedule == "online" and needs_subgoals(cfg)


def _online_companion(ctx: Context) -> Any:
    """The online CVAE as the reward trainer's companion (:mod:`spot.subgoal.online`), initialised
    with the ``cvae`` key."""
    from spot.reward.train import Companion
    from spot.subgoal import online

    cfg = ctx.cfg
    state = online.init_state(ctx.keys["cvae"], ctx.ds.observations, ctx.ds.act_dim, cfg.cvae, cfg.shaping.state_action)
    step = online.OnlineCVAE(cfg.subgoal, cfg.cvae, cfg.shaping.state_action)
    return Companion(step, state, {"cvae/loss": "cvae/loss"})


def subgoals_stage(ctx: Context, labelled: Labelled, rewards: Rewards) -> Any:
    """Eq. 5-6: attention subgoals on the preferred training segments of the best checkpoint ->
    (s, a, g) triplets (g a state and an action with ``shaping.state_action``); the offline CVAE
    trains on them, the online one (``cvae.schedule=online``) trained in the reward stage and these
    feed only the diagnostics."""
    import jax

    from spot.reward import pt
    from spot.subgoal import extract

    model = rewards.source
    attention = jax.jit(pt.attention, static_argnums=1)
    batch = labelled.train_batch
    sides = []
    for side in ("1", "2"):
        mask = np.ones(batch[f"obs_{side}"].shape[:2], np.float32)
        r_hat, attn = attention(
            model.params, ctx.cfg.pt, batch[f"obs_{side}"], batch[f"act_{side}"], batch[f"timesteps_{side}"], mask
        )
        sides.append(
            extract.segments(
                batch[f"obs_{side}"], batch[f"act_{side}"], np.asarray(r_hat), np.asarray(attn), ctx.cfg.subgoal
            )
        )
    goal_actions = ctx.cfg.shaping.state_action  # subgoals are states and actions
    triplets, segments, states, info = extract.extract_with_segments(
        sides[0],
        sides[1],
        batch["label"],
        ctx.cfg.subgoal,
        rng=np.random.default_rng(ctx.cfg.seed),
        goal_actions=goal_actions,
    )
    if ctx.cfg.subgoal.source == "random":  # the control: same count, random dataset states
        rng = np.random.default_rng([ctx.cfg.seed, 1])
        triplets = extract.random_subgoals(triplets, ctx.ds.observations, rng, ctx.ds.actions if goal_actions else None)
        states = triplets.g[:, : ctx.ds.obs_dim]
    ctx.log(info)
    return triplets, states, segments


def cvae_deps(ctx: Context, rewards: Rewards) -> dict[str, Any]:
    """What the offline CVAE's stage-cache entry depends on (its reward entry, configs, seed)."""
    cfg = ctx.cfg
    return {
        "reward": rewards.source.cache_key,
        "subgoal": cfg.subgoal,
        "cvae": cfg.cvae,
        "seed": cfg.seed,
        "split": "segment",
        **({"goal": "state_action"} if cfg.shaping.state_action else {}),
    }


def _offline_cvae(ctx: Context, triplets: Any, segments: np.ndarray, rewards: Rewards) -> tuple[dict[str, Any], str]:
    """``cvae.schedule=offline``: the CVAE trained on the extracted triplets, cached under its own key."""
    from spot.subgoal import cvae

    cfg = ctx.cfg
    out, key = ctx.cached(
        "cvae",
        cvae_deps(ctx, rewards),
        lambda: dict(
            zip(
                ("params", "history"),
                cvae.train_cvae(
                    ctx.keys["cvae"],
                    triplets.s,
                    triplets.a,
                    triplets.g,
                    cfg.cvae,
                    cvae.obs_stats(ctx.ds.observations),
                    progress=ctx.progress,
                    groups=segments,
                    goal_actions=cfg.shaping.state_action,
                ),
                strict=False,
            )
        ),
    )
    ctx.tracker.set_tags({"cache.cvae_key": key})
    return out, key


def cvae_stage(ctx: Context, extracted: Any, rewards: Rewards) -> Subgoals:
    """Eq. 7: the CVAE G(s, a) -> g. ``cvae.schedule=offline``: trained here on the triplets of the
    best checkpoint, cached; its held-out triplets (``cvae/heldout_*``) are whole preferred segments
    (no segment has triplets on both sides). ``online``: the CVAE the reward stage trained alongside
    the reward model (``RewardModel.cvae``, in the reward stage's cache entry; ``cvae/steps`` = its
    steps); the triplets here only feed the diagnostics."""
    triplets, states, segments = extracted
    if online_cvae(ctx.cfg):
        if rewards.source.cvae is None:
            raise SpotError("cvae.schedule=online, but the reward stage trained no CVAE (stages_of picks its stage)")
        out, key = rewards.source.cvae, rewards.source.cache_key
        ctx.log({"cvae/steps": out["steps"]})
    else:
        out, key = _offline_cvae(ctx, triplets, segments, rewards)
    ctx.tracker.set_tags({"cache.reward_key": rewards.source.cache_key})
    for row in out["history"]:
        ctx.log({k: v for k, v in row.items() if k != "step"}, step=int(row["step"]))
    save_model(
        ctx,
        "cvae",
        "CVAE G(s, a) -> subgoal (spot.subgoal.cvae.CVAEParams)",
        out["params"],
        ("subgoal", "cvae"),
        cache_key=key,
    )
    return Subgoals(triplets, states, out["params"])


def shaping_stage(ctx: Context, rewards: Rewards, subgoals: Subgoals | None) -> Shaped:
    """Eq. 13: ``norm(r_model) + λ r_shape(s', G(s, a))`` (no subgoals: the normalised reward)."""
    if subgoals is None:
        return Shaped(rewards.normalised)
    from spot.subgoal import shaping

    ds, cfg = ctx.ds, ctx.cfg
    shaped, info = shaping.shaped_rewards(
        subgoals.cvae_params,
        ds.observations,
        ds.actions,
        ds.next_observations,
        rewards.normalised,
        cfg.shaping,
        ctx.keys["shaping"],
        gamma=cfg.iql.discount,
        terminals=ds.terminals,
    )
    ctx.log(info)
    return Shaped(shaped.reward, shaped.cos_to_subgoal)


def in_segments_mask(n: int, prefs: Any) -> np.ndarray:
    """``[n]`` bool: transitions inside any segment of ``prefs``."""
    inside = np.zeros(n, bool)
    length = prefs.segment_length
    for starts in (prefs.starts_1, prefs.starts_2):
        idx = (np.asarray(starts)[:, None] + np.arange(length)[None, :]).ravel()
        inside[idx[idx < n]] = True
    return inside


def in_distribution(n: int, labelled: Labelled) -> np.ndarray:
    """Fig. 2's in-distribution transitions: inside the reward model's *training* segments (§5.3:
    "only on the reward model training data"); held-out queries count as out of distribution."""
    return in_segments_mask(n, labelled.train_prefs)


def diagnostics_stage(ctx: Context, labelled: Labelled, subgoals: Subgoals, shaped: Shaped) -> None:
    """Fig. 2 extrapolation error by proximity to the subgoal; subgoal precision/recall; Fig. 4."""
    from spot.subgoal import cvae, diagnostics

    ds, art = ctx.ds, ctx.artifacts
    in_dist = in_distribution(len(ds), labelled)
    table = diagnostics.extrapolation_error_bins(
        shaped.reward, ds.rewards.astype(np.float32), shaped.cos_to_subgoal, in_dist, bins=np.linspace(-1.0, 1.0, 21)
    )
    ctx.log(table.metrics())
    bins = range(table.mean_error.shape[1])
    ctx.tracker.log_series("diag/extrap_bin_in", bins, table.mean_error[0])
    ctx.tracker.log_series("diag/extrap_bin_ood", bins, table.mean_error[1])
    ctx.tracker.log_artifact(diagnostics.plot_extrapolation({ctx.cfg.method: table}, art / "extrapolation_error.png"))
    generated = cvae.generate(subgoals.cvae_params, subgoals.triplets.s, subgoals.triplets.a)
    ctx.log(diagnostics.precision_recall(subgoals.states, generated))
    ctx.tracker.log_artifact(diagnostics.plot_projection(ds.observations, generated, art / "subgoal_projection.png"))
    ctx.tracker.log_dict(
        {
            "edges": table.edges.tolist(),
            "mean_error": table.mean_error.tolist(),
            "count": table.count.tolist(),
            "groups": list(diagnostics.GROUP_NAMES),
        },
        "extrapolation_error.json",
    )


# --------------------------------------------------------------------------- policy stages
def eval_episodes(cfg: ExperimentConfig, step: int) -> int:
    """Episodes of the evaluation after ``step`` updates: ``eval.final_episodes`` after the last
    update when it is set, else ``eval.episodes``."""
    final = cfg.eval.final_episodes
    return final if final > 0 and step >= cfg.iql.steps else cfg.eval.episodes


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
    """The ``policy_fn`` of :func:`spot.envs.evaluate` for an IQL actor (the policy's mean action,
    one jitted call per step, each row computed alone); ``runs=True``: that of
    :func:`spot.envs.evaluate_runs` for actor params stacked over runs (a vmapped trial's seeds)."""
    import jax

    act = _act_each(iql_cfg)
    if runs:
        return lambda obs: np.asarray(act(actor_params, obs))
    stacked = jax.tree.map(lambda a: a[None], actor_params)
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


def _evaluate_fn(ctx: Context) -> Callable[[Any, int], dict[str, float]]:
    """``evaluate(actor_params, step)``: the policy's mean action in the evaluation env, its
    episodes stepped together (:func:`eval_policy`)."""
    from spot import envs

    cfg = ctx.cfg

    def evaluate(actor_params: Any, step: int) -> dict[str, float]:
        with phases.phase("evaluate"):  # a sweep trial's time breakdown (spot.phases)
            res = envs.evaluate(
                eval_policy(actor_params, cfg.iql),
                ctx.env_name,
                eval_episodes(cfg, step),
                seed=eval_seed(cfg),
                max_steps=cfg.eval.max_steps,
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

    data = jax.device_put(policy_transitions(ctx.cfg, ctx.ds, shaped.reward))
    init_key, _ = jax.random.split(ctx.keys["policy"])
    state = iql.init_state(init_key, ctx.ds.obs_dim, ctx.ds.act_dim, ctx.cfg.iql)
    return _train_policy(ctx, state, iql.make_train_chunk(ctx.cfg.iql), lambda key: (data, key))


def ipl_policy(ctx: Context, shaped: Shaped, labelled: Labelled) -> Policy:
    """IPL: the critic's implied reward is trained on the preferences (no reward model)."""
    import jax

    from spot.policy import ipl

    cfg = ctx.cfg
    data = jax.device_put(policy_transitions(cfg, ctx.ds, shaped.reward))
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


# --------------------------------------------------------------------------- the method table
@dataclass(frozen=True)
class RewardKind:
    """The stages that fill the reward, relabel and policy slots for one ``reward.kind``."""

    reward: Callable[[Context, Labelled | None], RewardModel | None]
    relabel: Callable[[Context, Any], Rewards]
    policy: Callable[[Context, Shaped, Labelled | None], Policy] = iql_policy
    uses_labels: bool = True


REWARD_KINDS: dict[str, RewardKind] = {
    "none": RewardKind(true_reward, true_rewards, uses_labels=False),  # Oracle
    "mr": RewardKind(learned_reward, model_rewards),  # MR
    "pt": RewardKind(learned_reward, model_rewards),  # PT, SPOT
    "hpl": RewardKind(hpl_reward, hpl_rewards),  # HPL
    "ipl": RewardKind(true_reward, zero_rewards, policy=ipl_policy),  # IPL
}


def register(method: str, kind: RewardKind, preset: dict[str, Any] | None = None) -> None:
    """Add a method: its stages (under ``reward.kind = method``) and its config preset.

    ``spot run method=<method>`` then runs ``kind``'s stages; see docs/design.md, "Adding a method".
    """
    if method in REWARD_KINDS or method in config_lib.METHOD_PRESETS:
        raise SpotError(f"method {method!r} is already registered")
    config_lib.register_method(method, {"shaping.kind": "none", **(preset or {}), "reward.kind": method})
    REWARD_KINDS[method] = kind


PLUGIN_GROUP = "spot.methods"


def load_plugins() -> list[str]:
    """Call every ``spot.methods`` entry point (a function that calls :func:`register`), once per
    process, so that a method shipped in another package works with ``spot run`` and ``spot sweep``.
    Returns the entry points' names."""
    from importlib.metadata import entry_points

    names = []
    for ep in entry_points(group=PLUGIN_GROUP):
        if ep.name not in _LOADED_PLUGINS:
            ep.load()()
            _LOADED_PLUGINS.add(ep.name)
        names.append(ep.name)
    return names


_LOADED_PLUGINS: set[str] = set()


def stages_of(cfg: ExperimentConfig) -> RewardKind:
    """The stages of ``cfg``'s ``reward.kind``; with ``cvae.schedule=online`` (PT runs that need a
    CVAE) the reward slot is :func:`learned_reward_online`."""
    try:
        kind = REWARD_KINDS[cfg.reward.kind]
    except KeyError:
        raise SpotError(
            f"reward.kind={cfg.reward.kind!r} has no stages; registered: {', '.join(REWARD_KINDS)}"
        ) from None
    return replace(kind, reward=learned_reward_online) if online_cvae(cfg) else kind


def plot_curve(steps: list[int], scores: list[float], path: Path, title: str) -> Path:
    """The evaluation curve as a PNG (the run's ``learning_curve.png``)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3.2))
    ax = fig.subplots()
    ax.plot(steps, scores, marker="o")
    ax.set_xlabel("IQL updates")
    ax.set_ylabel("normalised score")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def finish(ctx: Context, policy: Policy, t_start: float) -> dict[str, Any]:
    """Learning curve artifact and the run's final metrics (``eval/score_final``, ``_best``, times)."""
    png = plot_curve(
        policy.steps,
        policy.scores,
        ctx.artifacts / "learning_curve.png",
        f"{ctx.cfg.method} on {ctx.env_name} (seed {ctx.cfg.seed})",
    )
    ctx.tracker.log_artifact(png)
    st = policy.state
    save_model(
        ctx,
        "policy",
        "IQL actor (Gaussian, mean tanh(MLP(s)); spot.policy.iql.act), critics, value "
        "and target critics after the last update",
        {
            "actor": st.actor.params,
            "critic": st.critic.params,
            "value": st.value.params,
            "target_critic": st.target_critic_params,
        },
        ("iql", "eval", *(("ipl",) if ctx.cfg.reward.kind == "ipl" else ())),
        env=ctx.env_name,
        eval_seed=eval_seed(ctx.cfg),
        steps=int(policy.steps[-1]),
        score_final=policy.scores[-1],
        obs_dim=int(ctx.ds.obs_dim),
        act_dim=int(ctx.ds.act_dim),
    )
    ctx.times["time/eval_s"] = policy.eval_s
    ctx.times["time/iql_s"] = ctx.times.get("time/iql_s", 0.0) - policy.eval_s
    ctx.times["time/total_s"] = time.perf_counter() - t_start
    # best over the trained policies: the evaluation at step 0 (the untrained policy) is the baseline
    trained = [score for step, score in zip(policy.steps, policy.scores, strict=True) if step > 0]
    final = {"eval/score_final": policy.scores[-1], "eval/score_best": max(trained), **ctx.times}
    ctx.log(final)
    return {"run_id": ctx.tracker.run_id, **final}
