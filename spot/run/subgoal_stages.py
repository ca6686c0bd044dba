"""The subgoals, CVAE, shaping and diagnostics slots (SPOT's part, eq. 5-13): attention subgoals of
the preferred segments, the CVAE trained on them (offline here, or online in the reward stage), the
shaped reward the policy trains on, and the Fig. 2 / Fig. 4 diagnostics."""

from __future__ import annotations

from typing import Any

import numpy as np

from spot import SpotError
from spot.config import ExperimentConfig
from spot.run.context import Context, Labelled, Rewards, Shaped, Subgoals, save_model


def needs_subgoals(cfg: ExperimentConfig) -> bool:
    """SPOT shapes with subgoals; PT runs also extract them for the Fig. 2 diagnostics."""
    return cfg.reward.kind == "pt" and (cfg.shaping.kind != "none" or cfg.subgoal.diagnostics)


def online_cvae(cfg: ExperimentConfig) -> bool:
    """The CVAE trains during reward learning (``cvae.schedule=online``) in runs that need one."""
    return cfg.cvae.schedule == "online" and needs_subgoals(cfg)


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
