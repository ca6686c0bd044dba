"""Finishing a run: its learning curve, the trained policy saved as ``models/policy`` and the final
metrics (``eval/score_final``, ``eval/score_best``, the times)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from spot.run.context import Context, Policy, save_model
from spot.run.policy_stages import eval_seed


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
