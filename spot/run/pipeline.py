"""One run end to end: data -> labels -> reward -> relabel -> subgoals -> CVAE -> shaping -> policy.

:func:`run` is the paper's data flow; the stages, their typed outputs and the per-method table are
in the other modules of :mod:`spot.run`. The expensive stages (reward model, relabelling, CVAE) go
through the stage cache, keyed by everything they depend on, so a run that changes only
``shaping.weight`` or ``shaping.kind`` reuses the reward model and the CVAE of an earlier run (tag
``cache.<stage> = hit``).
The trained models are saved as the run's ``models/*`` artifacts; :func:`evaluate_run` evaluates a
logged run's policy again (``spot eval``).

Metrics: ``labels/*``, ``reward/*`` (reward-model training), ``hpl/*``, ``ipl/*``, ``subgoal/*``
(extraction, quality), ``cvae/*``, ``shaping/*``, ``iql/*``, ``eval/score`` over policy updates,
``eval/score_final``, ``eval/score_best``, ``diag/*`` (extrapolation error, Fig. 2),
``time/<stage>_s`` and MLflow's ``system/*``.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from spot import NonFiniteError, loop
from spot.config import ExperimentConfig
from spot.run import finish, label_stages, methods, policy_stages, subgoal_stages
from spot.run.context import Context, Labelled, Rewards, Shaped
from spot.tracking import Tracker, run_temp


def run(
    cfg: ExperimentConfig,
    *,
    progress: bool = True,
    parent_run_id: str | None = None,
    extra_tags: dict[str, str] | None = None,
    on_eval: Callable[[dict[str, float]], None] | None = None,
    tracker: Tracker | None = None,
) -> dict[str, Any]:
    """Run one seed of ``cfg``, recorded by ``tracker`` (default: a new MLflow run).

    Returns the final metrics (``eval/score_final``, ``eval/score_best``, ``time/*``) and ``run_id``.
    """
    t_start = time.perf_counter()
    kind = methods.stages_of(cfg)
    ds, card, env_name, data_s = _load(cfg, progress)
    with _tracking(cfg, card, tracker, parent_run_id, extra_tags, ds) as tr:
        ctx = Context(cfg, ds, card, env_name, tr, _keys(cfg.seed), progress, on_eval)
        ctx.times["time/data_s"] = data_s
        try:
            labelled, shaped = before_policy(ctx, kind)
            policy = ctx.stage("iql", kind.policy, shaped, labelled)
            return finish.finish(ctx, policy, t_start)
        except NonFiniteError as e:  # name the keys that scale the loss, in the message and failure_reason
            loop.name_keys(e, cfg)
            raise
        finally:
            run_temp.remove_run_temp(ctx.artifacts)  # its files were logged to the run


def before_policy(
    ctx: Context, kind: methods.RewardKind, labelled: Labelled | None = None
) -> tuple[Labelled | None, Shaped]:
    """The stages before the policy: labels (unless ``labelled`` is given: the labels stage's output
    for this run), reward model, relabelling, subgoals, CVAE, shaping and the diagnostics; returns
    the labelled queries (None without labels) and the policy's reward."""
    labelled, rewards, extracted = up_to_subgoals(ctx, kind, labelled)
    return labelled, from_cvae(ctx, labelled, rewards, extracted)


def up_to_subgoals(
    ctx: Context, kind: methods.RewardKind, labelled: Labelled | None = None
) -> tuple[Labelled | None, Rewards, Any]:
    """:func:`before_policy`'s first part: labels (unless given), reward model, relabelling and the
    subgoals (None when the method shapes nothing); returns ``(labelled, rewards, extracted)``."""
    if labelled is None and kind.uses_labels:
        labelled = ctx.stage("labels", label_stages.labels_stage)
    model = ctx.stage("reward", kind.reward, labelled)
    rewards = ctx.stage("relabel", kind.relabel, model)
    extracted = None
    if subgoal_stages.needs_subgoals(ctx.cfg):
        extracted = ctx.stage("subgoals", subgoal_stages.subgoals_stage, labelled, rewards)
    return labelled, rewards, extracted


def from_cvae(ctx: Context, labelled: Labelled | None, rewards: Rewards, extracted: Any) -> Shaped:
    """:func:`before_policy`'s second part: the CVAE (with subgoals), shaping and the diagnostics."""
    subgoals = ctx.stage("cvae", subgoal_stages.cvae_stage, extracted, rewards) if extracted is not None else None
    shaped = ctx.stage("shaping", subgoal_stages.shaping_stage, rewards, subgoals)
    if subgoals is not None:
        ctx.stage("diagnostics", subgoal_stages.diagnostics_stage, labelled, subgoals, shaped)
    return shaped


def _load(cfg: ExperimentConfig, progress: bool) -> tuple[Any, dict[str, Any], str, float]:
    """The dataset, its card, its evaluation env (checked to exist, before any training) and the load time."""
    from spot import envs

    t0 = time.perf_counter()
    ds, card = open_dataset(cfg, progress)
    env_name = card.get("name") or ds.name
    envs.env_spec(env_name)
    envs.check_fits_env(ds, card, env_name)  # observation and action sizes, before any training
    return ds, card, env_name, time.perf_counter() - t0


_OPENED: dict[tuple, tuple[Any, dict[str, Any]]] = {}  # this process's open datasets (at most _KEEP_OPEN)
_KEEP_OPEN = 2


def open_dataset(cfg: ExperimentConfig, progress: bool = False) -> tuple[Any, dict[str, Any]]:
    """``registry.load`` of ``cfg.data``, opened once per process: a later run of the same
    ``data.name``/``size``/``build_seed``/``source`` reuses the arrays (the seeds of a ``sequential``
    sweep trial, runs in a notebook) as long as the file's path, mtime and size are unchanged.
    Keeps the last :data:`_KEEP_OPEN` datasets. Returns ``(dataset, a copy of its card)``."""
    from spot.data import registry

    d = cfg.data
    as_path = Path(d.name).expanduser()
    if d.source == "file" or (d.source == "auto" and as_path.exists()):
        path = as_path
    else:
        path = registry.build(d.name, d.size, d.build_seed, progress=progress)  # once; then only a check
    try:
        st = path.stat()
    except OSError:  # registry.load says what is wrong with it
        return registry.load(d.name, d.size, d.build_seed, source=d.source, progress=progress)
    key = (d.name, d.size, d.build_seed, d.source, str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _OPENED:
        opened = registry.load(d.name, d.size, d.build_seed, source=d.source, progress=progress)
        while len(_OPENED) >= _KEEP_OPEN:
            _OPENED.pop(next(iter(_OPENED)))
        _OPENED[key] = opened
    ds, card = _OPENED[key]
    return ds, dict(card)


def _keys(seed: int) -> dict[str, Any]:
    import jax

    reward, cvae, shaping, policy = jax.random.split(jax.random.key(seed), 4)
    return {"reward": reward, "cvae": cvae, "shaping": shaping, "policy": policy}


@contextlib.contextmanager
def _tracking(
    cfg: ExperimentConfig,
    card: dict[str, Any],
    tracker: Tracker | None,
    parent_run_id: str | None,
    extra_tags: dict[str, str] | None,
    ds: Any,
):
    if tracker is not None:
        yield tracker
        return
    if cfg.tracking.record:  # files, imported into MLflow later (spot.tracking.recorded)
        from spot.tracking import recorded

        with recorded.start_record(cfg, card, parent_run_id=parent_run_id, extra_tags=extra_tags, dataset=ds) as tr:
            yield tr
        return
    from spot import tracking

    with tracking.start_run(cfg, card, parent_run_id=parent_run_id, extra_tags=extra_tags, dataset=ds) as tr:
        yield tr


def _logged_max_steps(run_id: str, tracking_uri: str | None, resolved: int) -> int:
    """``eval.max_steps`` as the run used it: runs logged before the key existed played whole
    episodes (0), where resolving their config would give today's budget default."""
    import yaml

    from spot import tracking

    logged = yaml.safe_load(tracking.load_artifact_text(run_id, "config.yaml", tracking_uri)) or {}
    return resolved if "max_steps" in (logged.get("eval") or {}) else 0


def evaluate_run(run_id: str, tracking_uri: str | None = None, episodes: int | None = None) -> dict[str, Any]:
    """Evaluate the policy a run saved (``models/policy``) again, in the env and with the episode
    seeds the run evaluated it with (``episodes`` defaults to the episodes of the run's last
    evaluation, ``eval.final_episodes`` or else ``eval.episodes``; the first ``episodes`` are the
    run's). Returns the scores and the run's logged
    ``eval/score_final``, ``logged_score_final``.
    """
    from spot import evaluation, tracking

    params, head = tracking.load_model(run_id, "policy", tracking_uri)
    cfg = tracking.run_config(run_id, tracking_uri)
    n = episodes or cfg.eval.final_episodes or cfg.eval.episodes
    actor = params["actor"]
    res = evaluation.evaluate(
        policy_stages.eval_policy(actor, cfg.iql),  # as the run evaluated it
        head["env"],
        n,
        seed=int(head["eval_seed"]),
        max_steps=_logged_max_steps(run_id, tracking_uri, cfg.eval.max_steps),  # as the run evaluated it
        stepper=cfg.eval.stepper,  # either gives the same numbers
    )
    logged = tracking.reader(tracking_uri).get_run(run_id).data.metrics.get("eval/score_final")
    return {
        "run_id": run_id,
        "method": cfg.method,
        "env": head["env"],
        "episodes": n,
        "eval_seed": int(head["eval_seed"]),
        "steps": head.get("steps"),
        "score_mean": float(res["score_mean"]),
        "score_std": float(res["score_std"]),
        "return_mean": float(res["return_mean"]),
        "length_mean": float(res["episode_length_mean"]),
        "logged_score_final": logged,
    }
