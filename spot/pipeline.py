"""One run end to end: data -> labels -> reward model -> relabel -> subgoals -> CVAE -> shaping -> IQL.

Each stage is a function of its inputs and its config section. The expensive ones (reward model,
relabelling, CVAE) go through :mod:`spot.cache`, keyed by a hash of everything they depend on, so
a run that changes only ``shaping.weight`` or ``shaping.kind`` reuses the reward model and the
CVAE of an earlier run (logged as ``cache/<stage>_hit = 1``).

Where normalisation sits: the reward model's per-step output is relabelled over the whole dataset,
normalised (``relabel.normalize``, PT repo: ``r * 1000 / (R_max - R_min) + 0.5`` over episode
returns), and only then is the shaping term added, ``r = norm(r_model) + λ r_shape`` (eq. 13), so
that λ = 1 adds a bonus in [0, 1] beside a reward of the scale IQL's hyperparameters expect.

Metrics: ``reward/*`` (reward-model training), ``subgoal/*`` (extraction, quality), ``cvae/*``,
``shaping/*``, ``iql/*``, ``eval/score`` over IQL steps, ``eval/score_final``, ``eval/score_best``,
``diag/*`` (extrapolation error, Fig. 2) and ``time/<stage>_s``.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

import spot  # noqa: F401  (sets XLA flags before jax is imported)
from spot import SpotError, cache
from spot import config as config_lib
from spot.config import ExperimentConfig


class _Timer:
    def __init__(self) -> None:
        self.times: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times[f"time/{stage}_s"] = self.times.get(f"time/{stage}_s", 0.0) + time.perf_counter() - t0


def _log(metrics: dict[str, Any], step: int | None = None) -> None:
    import mlflow

    clean = {k: float(v) for k, v in metrics.items() if v is not None and np.isfinite(float(v))}
    if clean:
        mlflow.log_metrics(clean, step=step)


def make_preferences(cfg: ExperimentConfig, ds):
    """The run's preference queries (scripted teacher or PT human label files), checked against ``ds``."""
    from spot.data import labels

    lc = cfg.labels
    if lc.source == "human":
        if not lc.path:
            raise SpotError("labels.source=human needs labels.path (a folder of PT label files)")
        prefs = labels.read_pt_labels(lc.path, num_queries=lc.num_queries)
        labels.check_against(prefs, ds, allow_cross_episode=True)
        return prefs
    return labels.scripted_teacher(
        ds, lc.num_queries, lc.segment_length, teacher=lc.teacher, discount=lc.discount,
        tie_threshold=lc.tie_threshold, mistake_rate=lc.mistake_rate,
        allow_cross_episode=lc.allow_cross_episode, seed=lc.seed, score=lc.score,
    )


def _fingerprint(ds) -> dict[str, Any]:
    return {"obs": ds.observations, "act": ds.actions, "rew": ds.rewards, "term": ds.terminals}


def _reward_model_stage(cfg, ds, train_batch, eval_batch, deps, key, progress):
    from spot.reward import train as reward_train

    rc = cfg.reward
    model_cfg = cfg.pt if rc.kind == "pt" else cfg.mr
    stage_deps = {**deps, "reward": config_lib.to_flat(cfg)["reward.kind"], "reward_cfg": rc,
                  "model_cfg": model_cfg, "seed": cfg.seed}

    def compute():
        params, history = reward_train.train_reward_model(
            rc.kind, key, train_batch, eval_batch, rc, pt_cfg=cfg.pt, mr_cfg=cfg.mr, progress=progress)
        return {"params": params, "history": history}

    return cache.cached("reward", stage_deps, compute)


def _hpl_stage(cfg, ds, train_batch, eval_batch, deps, key, timer, progress):
    """HPL: hindsight VAE + reward r(s,a,z) (cached), then relabel by marginalising the prior."""
    import jax

    from spot.reward import hpl

    stage_deps = {**deps, "reward": "hpl", "hpl": cfg.hpl, "reward_cfg": cfg.reward, "seed": cfg.seed}
    train_key, relabel_key = jax.random.split(key)
    with timer("reward"):
        out, hit, cache_key = cache.cached("hpl", stage_deps, lambda: dict(zip(
            ("params", "history"), hpl.train_hpl(train_key, ds, train_batch, eval_batch, cfg.hpl, progress=progress),
            strict=True)))
    history = out["history"]
    _log({"cache/reward_hit": float(hit)})
    _log({f"reward/{k}": history[k] for k in ("best_step", "best_eval_loss", "best_eval_acc", "steps_per_s")
          if k in history})
    for i, step in enumerate(history.get("vae_step", [])):
        _log({f"hpl/{k}": history[k][i] for k in ("vae_loss", "vae_recon", "vae_kl") if k in history}, step=int(step))
    for i, step in enumerate(history.get("reward_step", [])):
        _log({f"reward/{k}": history[k][i] for k in ("train_loss", "train_acc", "eval_loss", "eval_acc")
              if k in history and len(history[k]) > i}, step=int(step))
    for name in ("vae_s", "reward_s"):
        if name in history:  # Table 8: HPL's two pretraining phases, as measured when it was trained
            _log({f"time/hpl_{name}": history[name]})
    with timer("relabel"):
        rel, rel_hit, _ = cache.cached("hpl_relabel", {"hpl": cache_key, "seed": cfg.seed},
                                       lambda: {"rewards": hpl.relabel_hpl(out["params"], ds, cfg.hpl, relabel_key)})
    _log({"cache/relabel_hit": float(rel_hit)})
    return np.asarray(rel["rewards"], np.float32), cache_key


def _ipl_ranking(state, cfg, train_batch, eval_batch) -> dict[str, float]:
    """IPL's implied reward Q(s,a) - gamma V(s') summed over whole segments: how often it ranks
    the preferred segment higher, on the training and held-out queries (``reward/*``, like the
    reward models' metrics)."""
    from spot.policy import ipl

    out = {}
    for name, batch in (("train", train_batch), ("eval", eval_batch)):
        if batch is not None:
            res = ipl.evaluate_preferences(state, ipl.feedback_from(batch), cfg.iql, cfg.ipl)
            out[f"reward/{name}_acc"], out[f"reward/{name}_loss"] = res["ipl/eval_pref_acc"], res["ipl/eval_pref_loss"]
    return out


def _in_segments_mask(n: int, prefs) -> np.ndarray:
    inside = np.zeros(n, bool)
    length = prefs.segment_length
    for starts in (prefs.starts_1, prefs.starts_2):
        idx = (np.asarray(starts)[:, None] + np.arange(length)[None, :]).ravel()
        inside[idx[idx < n]] = True
    return inside


def _plot_curve(steps: list[int], scores: list[float], path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(steps, scores, marker="o")
    ax.set_xlabel("IQL updates")
    ax.set_ylabel("normalised score")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run(cfg: ExperimentConfig, *, progress: bool = True, parent_run_id: str | None = None,
        extra_tags: dict[str, str] | None = None,
        on_eval: Callable[[dict[str, float]], None] | None = None) -> dict[str, Any]:
    """Run one seed of ``cfg`` and log it to MLflow. Returns the final metrics and the run id."""
    import jax
    import mlflow

    from spot import envs, tracking
    from spot.data import labels, registry
    from spot.policy import iql
    from spot.reward import relabel as relabel_lib
    from spot.reward import train as reward_train

    timer = _Timer()
    t_start = time.perf_counter()
    with timer("data"):
        ds, card = registry.load(cfg.data.name, cfg.data.size, cfg.data.build_seed,
                                 source=cfg.data.source, progress=progress)
    env_name = card.get("name") or ds.name
    envs.env_spec(env_name)  # fail early if the dataset has no evaluation env

    root = jax.random.key(cfg.seed)
    reward_key, cvae_key, shaping_key, iql_key = jax.random.split(root, 4)
    del root
    final: dict[str, Any] = {}
    with tracking.start_run(cfg, card, parent_run_id=parent_run_id, extra_tags=extra_tags) as mlrun:
        final["run_id"] = mlrun.info.run_id
        artifacts = Path(tempfile.mkdtemp(prefix="spot-run-"))
        deps: dict[str, Any] = {"data": _fingerprint(ds)}
        r_true = ds.rewards.astype(np.float32)
        kind = cfg.reward.kind
        uses_labels = kind != "none"
        uses_model = kind in ("mr", "pt", "hpl")  # ipl has no reward model: its critic is the reward
        prefs = train_prefs = eval_batch = None

        # ---------------------------------------------------------------- labels
        if uses_labels:
            with timer("labels"):
                prefs = make_preferences(cfg, ds)
                train_prefs, eval_prefs = labels.split_eval(prefs, cfg.labels.eval_fraction, cfg.labels.seed)
                train_batch = labels.segment_batch(ds, train_prefs)
                eval_batch = labels.segment_batch(ds, eval_prefs) if len(eval_prefs) else None
            y = prefs.labels
            _log({"labels/queries": len(prefs), "labels/ties": float(np.sum(y == 0.5)),
                  "labels/segment_length": prefs.segment_length})
            deps["labels"] = {"s1": prefs.starts_1, "s2": prefs.starts_2, "y": prefs.labels,
                              "split": (cfg.labels.eval_fraction, cfg.labels.seed)}

        # ---------------------------------------------------------------- reward model
        if kind == "hpl":
            r_model, reward_cache_key = _hpl_stage(cfg, ds, train_batch, eval_batch, deps, reward_key, timer,
                                                   progress)
            _log({"reward/corr_true": float(np.corrcoef(r_model, r_true)[0, 1]) if r_model.std() > 0 else 0.0})
            r_norm = relabel_lib.normalize_rewards(r_model, ds, cfg.relabel.normalize)
        elif uses_model:
            with timer("reward"):
                out, hit, reward_cache_key = _reward_model_stage(cfg, ds, train_batch, eval_batch, deps,
                                                                 reward_key, progress)
            params, history = out["params"], out["history"]
            _log({"cache/reward_hit": float(hit)})
            for i, step in enumerate(history["step"]):
                _log({"reward/train_loss": history["train_loss"][i], "reward/train_acc": history["train_acc"][i],
                      "reward/eval_loss": history["eval_loss"][i], "reward/eval_acc": history["eval_acc"][i]},
                     step=int(step))
            _log({"reward/best_step": history["best_step"], "reward/best_eval_loss": history["best_eval_loss"],
                  "reward/best_eval_acc": history["best_eval_acc"], "reward/steps_per_s": history["steps_per_s"]})
            with timer("relabel"):
                rel, rel_hit, _ = cache.cached(
                    "relabel", {"reward": reward_cache_key, "relabel": cfg.relabel},
                    lambda: relabel_lib.relabel_rewards(cfg.reward.kind, params, ds, cfg.relabel, pt_cfg=cfg.pt,
                                                        mr_cfg=cfg.mr, progress=progress)._asdict())
            r_model = np.asarray(rel["rewards"], np.float32)
            _log({"cache/relabel_hit": float(rel_hit),
                  "reward/corr_true": float(np.corrcoef(r_model, r_true)[0, 1]) if r_model.std() > 0 else 0.0})
            r_norm = relabel_lib.normalize_rewards(r_model, ds, cfg.relabel.normalize)
        elif kind == "ipl":
            # IPL learns no reward: the replay transitions carry zeros so no true reward leaks in.
            r_model = r_norm = np.zeros_like(r_true)
        else:
            r_model = r_true
            r_norm = relabel_lib.normalize_rewards(r_true, ds, cfg.relabel.normalize)

        # ---------------------------------------------------------------- subgoals + CVAE
        cvae_params = None
        shaping_on = cfg.shaping.kind != "none"
        if shaping_on and cfg.reward.kind != "pt":
            raise SpotError(f"shaping.kind={cfg.shaping.kind!r} needs reward.kind=pt (subgoals come from PT "
                            f"attention); got reward.kind={cfg.reward.kind!r}")
        if cfg.reward.kind == "pt" and (shaping_on or cfg.subgoal.diagnostics):
            from spot.subgoal import cvae as cvae_lib
            from spot.subgoal import extract

            with timer("subgoals"):
                f = reward_train.model_fn("pt", params, pt_cfg=cfg.pt)
                sides = []
                for side in ("1", "2"):
                    mask = np.ones(train_batch[f"obs_{side}"].shape[:2], np.float32)
                    r_hat, w = f(train_batch[f"obs_{side}"], train_batch[f"act_{side}"],
                                 train_batch[f"timesteps_{side}"], mask)
                    sides.append(extract.Segments(train_batch[f"obs_{side}"], train_batch[f"act_{side}"],
                                                  np.asarray(r_hat), np.asarray(w)))
                triplets, subgoal_states, sg_info = extract.extract(sides[0], sides[1], train_batch["label"], cfg.subgoal)
            _log(sg_info)
            with timer("cvae"):
                cv, cvae_hit, cvae_cache_key = cache.cached(
                    "cvae", {"reward": reward_cache_key, "subgoal": cfg.subgoal, "cvae": cfg.cvae, "seed": cfg.seed},
                    lambda: dict(zip(("params", "history"), cvae_lib.train_cvae(
                        cvae_key, triplets.s, triplets.a, triplets.g, cfg.cvae,
                        cvae_lib.obs_stats(ds.observations), progress=progress), strict=False)))
            cvae_params = cv["params"]
            _log({"cache/cvae_hit": float(cvae_hit)})
            mlflow.set_tags({"cache.cvae_key": cvae_cache_key, "cache.reward_key": reward_cache_key})
            for row in cv["history"]:
                _log({k: v for k, v in row.items() if k != "step"}, step=int(row["step"]))

        # ---------------------------------------------------------------- shaping
        reward = r_norm
        if cvae_params is not None:
            from spot.subgoal import cvae as cvae_lib
            from spot.subgoal import diagnostics, shaping

            with timer("shaping"):
                shaped, sh_info = shaping.shaped_rewards(
                    cvae_params, ds.observations, ds.actions, ds.next_observations, r_norm, cfg.shaping,
                    shaping_key, gamma=cfg.iql.discount, terminals=ds.terminals)
            reward = shaped.reward
            _log(sh_info)
            with timer("diagnostics"):
                in_dist = _in_segments_mask(len(ds), prefs)
                table = diagnostics.extrapolation_error_bins(reward, r_true, shaped.cos_to_subgoal, in_dist,
                                                             bins=np.linspace(-1.0, 1.0, 21))
                _log(table.metrics())
                for b in range(table.mean_error.shape[1]):
                    _log({"diag/extrap_bin_in": table.mean_error[0, b], "diag/extrap_bin_ood": table.mean_error[1, b]},
                         step=b)
                png = diagnostics.plot_extrapolation({cfg.method: table}, artifacts / "extrapolation_error.png")
                mlflow.log_artifact(str(png))
                generated = cvae_lib.generate(cvae_params, triplets.s, triplets.a)
                pr = diagnostics.precision_recall(subgoal_states, generated)
                _log(pr)
                png = diagnostics.plot_projection(ds.observations, generated, artifacts / "subgoal_projection.png")
                mlflow.log_artifact(str(png))
                mlflow.log_dict({"edges": table.edges.tolist(), "mean_error": table.mean_error.tolist(),
                                 "count": table.count.tolist(), "groups": list(diagnostics.GROUP_NAMES)},
                                "extrapolation_error.json")

        # ---------------------------------------------------------------- IQL + evaluation
        with timer("iql"):
            data = iql.transitions_from(ds, reward)
            init_key, train_key = jax.random.split(iql_key)
            if kind == "ipl":
                from spot.policy import ipl

                feedback = ipl.feedback_from(train_batch)
                state = ipl.init_state(init_key, ds.obs_dim, ds.act_dim, cfg.iql)
                ipl_chunk = ipl.make_train_chunk(cfg.iql, cfg.ipl)
                replay = data if cfg.ipl.use_replay else None

                def train_chunk(state, _data, key):
                    return ipl_chunk(state, replay, feedback, key)
            else:
                state = iql.init_state(init_key, ds.obs_dim, ds.act_dim, cfg.iql)
                train_chunk = iql.make_train_chunk(cfg.iql)
            steps_done, curve_steps, curve_scores = 0, [], []
            n_chunks = -(-cfg.iql.steps // cfg.iql.chunk)
            next_eval = min(cfg.eval.every, cfg.iql.steps)
            eval_time = 0.0
            for c in range(n_chunks):
                state, metrics = train_chunk(state, data, jax.random.fold_in(train_key, c))
                steps_done += cfg.iql.chunk
                _log(iql.check_finite(metrics, steps_done), step=steps_done)
                if steps_done >= next_eval or c == n_chunks - 1:
                    t_eval = time.perf_counter()
                    actor = state.actor.params
                    res = envs.evaluate(lambda o, p=actor: np.asarray(iql.act(p, o, cfg.iql)), env_name,
                                        cfg.eval.episodes, seed=10_000 * (cfg.seed + 1))
                    eval_time += time.perf_counter() - t_eval
                    curve_steps.append(steps_done)
                    curve_scores.append(float(res["score_mean"]))
                    _log({"eval/score": res["score_mean"], "eval/score_std": res["score_std"],
                          "eval/return": res["return_mean"]}, step=steps_done)
                    if on_eval is not None:
                        on_eval({"step": steps_done, "score": float(res["score_mean"])})
                    next_eval += cfg.eval.every
        timer.times["time/eval_s"] = eval_time
        timer.times["time/iql_s"] -= eval_time
        if kind == "ipl":
            _log(_ipl_ranking(state, cfg, train_batch, eval_batch))
        png = _plot_curve(curve_steps, curve_scores, artifacts / "learning_curve.png",
                          f"{cfg.method} on {env_name} (seed {cfg.seed})")
        mlflow.log_artifact(str(png))
        final.update({"eval/score_final": curve_scores[-1], "eval/score_best": max(curve_scores)})
        timer.times["time/total_s"] = time.perf_counter() - t_start
        final.update(timer.times)
        _log({k: v for k, v in final.items() if k != "run_id"})
    return final
