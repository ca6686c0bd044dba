"""The reward and relabel slots: the reward model trained on the preferences (MR, PT, HPL; the
Oracle and IPL train none), and every transition's reward, the model's raw output and the
normalised training reward (``relabel.normalize``). The expensive parts go through the stage cache."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from spot import cache
from spot.config import ExperimentConfig
from spot.run.context import Context, Labelled, RewardModel, Rewards, dataset_deps, save_model, untimed


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
    code version covers the CVAE's code too (:func:`spot.run.methods.stages_of` picks this stage)."""
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
    if getattr(ctx.on_eval, "takes_reward_metrics", False):  # a sweep trial's: reported to Tune (spot.sweep.search)
        ctx.on_eval({f"reward/{k}": float(h[k]) for k in ("best_eval_loss", "best_eval_acc")})
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


def _online_companion(ctx: Context) -> Any:
    """The online CVAE as the reward trainer's companion (:mod:`spot.subgoal.online`), initialised
    with the ``cvae`` key."""
    from spot.reward.train import Companion
    from spot.subgoal import online

    cfg = ctx.cfg
    state = online.init_state(ctx.keys["cvae"], ctx.ds.observations, ctx.ds.act_dim, cfg.cvae, cfg.shaping.state_action)
    step = online.OnlineCVAE(cfg.subgoal, cfg.cvae, cfg.shaping.state_action)
    return Companion(step, state, {"cvae/loss": "cvae/loss"})


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
    if getattr(ctx.on_eval, "takes_reward_metrics", False):  # as learned_reward's
        ctx.on_eval({f"reward/{k}": float(h[k]) for k in ("best_eval_loss", "best_eval_acc") if k in h})
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
