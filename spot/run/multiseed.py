"""Several seeds of one config in one process, IQL trained for all of them as one vmapped program.

:func:`run` is :func:`spot.run.pipeline.run` for seeds ``s_1 .. s_S`` of a config (``seed_mode: vmap``
in a sweep file). Each seed gets its own run (its own MLflow run, or the tracker given), and
the stages before the policy (labels, reward model, relabelling, subgoals, CVAE, shaping,
diagnostics) run per seed, one seed after another, through the stage cache as in a one-seed run,
with two exceptions: the MR/PT reward models of the seeds that miss the stage cache are trained
as one vmapped program first (:func:`vmapped_rewards`, :mod:`spot.reward.vmapped`), and so are
their offline CVAEs once every seed's subgoals are extracted (:func:`vmapped_cvaes`,
:mod:`spot.subgoal.vmapped`); each is stored by its seed's stage. A vmap trial's stage-cache
entries are kept apart from one-seed runs' (:data:`KEY_EXTRA`). IQL then trains all seeds as
**one** ``jit(vmap(chunk))`` over a leading seed axis
(:func:`spot.policy.iql.make_vmapped_train_chunk`): the observations, actions and masks are
shared, each seed has its own reward (its reward model's, shaped by its CVAE), initial networks
and minibatch keys, derived from its seed exactly as in a one-seed run. After each stretch of
updates every seed's policy is evaluated in the env with that seed's episodes and logged to its
own run, and each run gets its own learning curve, ``models/policy`` and final metrics
(:func:`spot.run.finish.finish`). The per-seed results equal one-seed runs' to float tolerance
(batched matmuls round differently): ``tests/test_multiseed.py``. The evaluations run on the CPU
device; on an accelerator, in a thread beside the training (the GPU goes on with the next
updates), and IQL's whole chunks as loops of static length (:func:`train_iql`); either way the
numbers are those of the evaluations in line (``tests/test_paper_row_multiseed.py``).

Per-seed timings: ``time/iql_s`` of every seed is the wall time of the shared vmapped training
(the evaluations excluded), ``time/eval_s`` an equal share of the evaluations (all seeds'
episodes step together; beside the training they overlap it), ``time/total_s`` the whole
multi-seed call. The times of the stages before IQL are logged when IQL starts too, so a run
stopped during IQL keeps them. The runs are tagged ``seed_mode = vmap`` and ``vmap.seeds`` (all
seeds); the stage-cache keys of a vmap trial carry :data:`KEY_EXTRA` and :func:`vmap_code`.

Members of several configs (``spot run --methods oracle,pt,spot --seeds 0,1,2``) share one
IQL program too, when they agree on :data:`SHARED_SECTIONS`: the stages before the policy run
config by config (a later config reuses an earlier one's stage-cache entries: SPOT takes PT's
reward models), and such runs are tagged ``vmap.members`` (``method:seed`` of every member).
On a GPU this width is nearly free, where a second process sharing the GPU is not.

Only methods whose policy stage is IQL (:func:`spot.policy_stages.iql_policy`) can be vmapped; IPL
trains its own critic on the preferences and is refused (run its seeds with ``seed_mode:
sequential`` or ``trials``). If one seed fails before or during training, every seed's run ends
FAILED with the reason: the seeds share one program.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from spot import SpotError, cache
from spot.config import ExperimentConfig
from spot.run import finish, label_stages, methods, pipeline, policy_stages, reward_stages, subgoal_stages
from spot.run.context import Context, Policy, Shaped
from spot.tracking import Tracker

KEY_EXTRA = {"seed_mode": "vmap"}
"""Added to the deps of every stage-cache entry a vmap trial makes or reads (``Context.key_extra``):
its reward models and CVAEs differ from one-seed training in the last bits, so the two kinds of
entries are kept apart and a one-seed run's numbers never depend on which filled the cache first."""


@functools.cache
def vmap_code() -> str:
    """The code version of the vmapped reward-model and CVAE training (:mod:`spot.reward.vmapped`,
    :mod:`spot.subgoal.vmapped`), added to a vmap trial's stage-cache keys beside :data:`KEY_EXTRA`:
    the one-seed stages' code versions do not cover those modules, so an edit to them retires the
    vmap entries they made."""
    from spot.reward import vmapped as reward_vmapped
    from spot.subgoal import vmapped as cvae_vmapped

    code = cache.code_version(reward_vmapped.train_reward_models) + cache.code_version(cvae_vmapped.train_cvaes)
    return cache.key("vmap", {}, code)


SHARED_SECTIONS = ("data", "iql", "eval")
"""The config sections every member of one vmapped IQL program must share (the transitions, the
IQL program and the evaluation schedule); members may differ in the seed and in everything that
only makes their reward (method, labels, reward model, subgoals, CVAE, shaping)."""


def _identity(cfg: ExperimentConfig) -> ExperimentConfig:
    """``cfg`` without its seed and tracking: the cell it belongs to."""
    return dataclasses.replace(cfg, seed=0, tracking=dataclasses.replace(cfg.tracking, experiment=""))


def check(cfgs: Sequence[ExperimentConfig]) -> list[methods.RewardKind]:
    """Each member's stages, after checking that ``cfgs`` are distinct members (no config twice with
    one seed) that share :data:`SHARED_SECTIONS` and whose policy stage is IQL (SpotError otherwise)."""
    if not cfgs:
        raise SpotError("seed_mode vmap: no seeds to run")
    members = [(c.seed, _identity(c)) for c in cfgs]
    for i, member in enumerate(members):
        if member in members[:i]:
            seeds = [c.seed for c, (_, cell) in zip(cfgs, members, strict=True) if cell == member[1]]
            raise SpotError(f"seed_mode vmap: seeds {seeds} repeat")
    kinds = [methods.stages_of(c) for c in cfgs]
    for cfg, kind in zip(cfgs, kinds, strict=True):
        if kind.policy is not policy_stages.iql_policy:
            raise SpotError(
                f"seed_mode vmap trains IQL over seeds; method {cfg.method!r} trains its own policy "
                f"({kind.policy.__name__}): use seed_mode: sequential or trials"
            )
    for cfg in cfgs[1:]:
        for section in SHARED_SECTIONS:
            if getattr(cfg, section) != getattr(cfgs[0], section):
                who = f"seed {cfg.seed}'s" if cfg.method == cfgs[0].method else f"{cfg.method} seed {cfg.seed}'s"
                raise SpotError(
                    f"seed_mode vmap: {who} config differs from seed {cfgs[0].seed}'s in {section}.*: the members "
                    f"of one vmapped IQL program share {', '.join(s + '.*' for s in SHARED_SECTIONS)}"
                )
    return kinds


def run(
    cfgs: Sequence[ExperimentConfig],
    *,
    progress: bool = True,
    parent_run_id: str | None = None,
    extra_tags: Sequence[dict[str, str] | None] | None = None,
    on_eval: Sequence[Callable[[dict[str, float]], None] | None] | None = None,
    trackers: Sequence[Tracker | None] | None = None,
) -> list[dict[str, Any]]:
    """Run the members ``cfgs`` (seeds of one config, or of several configs that share
    :data:`SHARED_SECTIONS`), IQL vmapped over all of them (module docstring).

    ``extra_tags``, ``on_eval`` and ``trackers`` are per member (as :func:`spot.run.pipeline.run`'s).
    The stages before the policy run config by config, in the order the configs first appear, so
    a later config reuses an earlier one's stage-cache entries (SPOT after PT: the same reward
    models). Returns each member's final metrics and ``run_id``, in the order of ``cfgs``.
    """
    t_start = time.perf_counter()
    kinds = check(cfgs)
    n = len(cfgs)
    extra_tags, on_eval, trackers = extra_tags or [None] * n, on_eval or [None] * n, trackers or [None] * n
    ds, card, env_name, data_s = pipeline._load(cfgs[0], progress)
    groups: dict[ExperimentConfig, list[int]] = {}  # the members of each config, in order
    for i, cfg in enumerate(cfgs):
        groups.setdefault(_identity(cfg), []).append(i)
    mode_tags = {"seed_mode": "vmap", "vmap.seeds": ",".join(str(c.seed) for c in cfgs)}
    if len(groups) > 1:
        mode_tags["vmap.members"] = ",".join(f"{c.method}:{c.seed}" for c in cfgs)
    with contextlib.ExitStack() as stack:
        ctxs, labelled = [], []
        for cfg, tags, callback, tracker, kind in zip(cfgs, extra_tags, on_eval, trackers, kinds, strict=True):
            tr = stack.enter_context(
                pipeline._tracking(cfg, card, tracker, parent_run_id, {**(tags or {}), **mode_tags}, ds)
            )
            if tracker is not None:
                tr.set_tags(mode_tags)
            ctx = Context(cfg, ds, card, env_name, tr, pipeline._keys(cfg.seed), progress, callback)
            ctx.key_extra = {**KEY_EXTRA, "vmap_code": vmap_code()}
            ctx.times["time/data_s"] = data_s
            labelled.append(ctx.stage("labels", label_stages.labels_stage) if kind.uses_labels else None)
            ctxs.append(ctx)
        shaped: list[Any] = [None] * n
        for members in groups.values():
            kind = kinds[members[0]]
            vmapped_rewards([ctxs[i] for i in members], [labelled[i] for i in members], kind)
            parts = {i: pipeline.up_to_subgoals(ctxs[i], kind, labelled[i]) for i in members}
            vmapped_cvaes([ctxs[i] for i in members], [parts[i][1] for i in members], [parts[i][2] for i in members])
            for i in members:
                shaped[i] = pipeline.from_cvae(ctxs[i], *parts[i])
        for ctx in ctxs:  # the stages' times so far: a run stopped during IQL (a time limit) keeps them
            ctx.log(dict(ctx.times))
        policies = train_iql(ctxs, shaped)
        return [finish.finish(ctx, policy, t_start) for ctx, policy in zip(ctxs, policies, strict=True)]


def vmapped_rewards(ctxs: Sequence[Context], labelled: Sequence[Any], kind: methods.RewardKind) -> list[int]:
    """Train the reward models (MR or PT, :func:`spot.reward_stages.learned_reward`) of the seeds that miss
    the stage cache as one vmapped program (:func:`spot.reward.vmapped.train_reward_models`), when
    at least two miss and their preference pairs have one shape. Each model waits in its run's
    ``ctx.precomputed``; the seed's reward stage then stores it under its own key and logs it as
    computed, exactly as if it had trained it. Each seed's ``time/reward_s`` gets the shared
    training's wall time. Returns the indices of the seeds trained here."""
    if kind.reward is not reward_stages.learned_reward or len(ctxs) < 2:
        return []
    from spot.reward import models, vmapped
    from spot.reward import train as reward_train

    cfg = ctxs[0].cfg
    model = models.from_config(cfg)
    extra = {"reward": model.kind, "reward_cfg": cfg.reward, "model_cfg": model.cfg}  # as the reward stage's
    deps_of = lambda i: reward_stages._reward_deps(ctxs[i], labelled[i], **extra)  # noqa: E731
    todo = _misses(ctxs, "reward", deps_of, cache.code_version(reward_stages.learned_reward))
    if len(todo) < 2:
        return []
    clip = cfg.reward.clip_action
    batches = [
        [reward_train.clip_actions(getattr(labelled[i], name), clip) for i, _ in todo]
        for name in ("train_batch", "eval_batch")
    ]
    t0 = time.perf_counter()
    try:
        keys = [ctxs[i].keys["reward"] for i, _ in todo]
        trained = vmapped.train_reward_models(model, keys, *batches, cfg.reward, progress=ctxs[0].progress)
    except SpotError:  # the pairs do not fit one program: one seed at a time, in the reward stage
        return []
    return _hand_over(ctxs, todo, trained, "reward", time.perf_counter() - t0)


def vmapped_cvaes(ctxs: Sequence[Context], rewards: Sequence[Any], extracted: Sequence[Any]) -> list[int]:
    """Train the offline CVAEs (``cvae.schedule=offline``) of the seeds that miss the stage cache as
    one vmapped program (:func:`spot.subgoal.vmapped.train_cvaes`), when at least two miss and their
    triplets fit one program; as :func:`vmapped_rewards`, each waits in ``ctx.precomputed`` for
    its seed's CVAE stage, and each seed's ``time/cvae_s`` gets the shared wall time. Returns the
    indices of the seeds trained here."""
    if len(ctxs) < 2 or extracted[0] is None or subgoal_stages.online_cvae(ctxs[0].cfg):
        return []
    from spot.subgoal import cvae, vmapped

    cfg = ctxs[0].cfg
    deps_of = lambda i: subgoal_stages.cvae_deps(ctxs[i], rewards[i])  # noqa: E731
    todo = _misses(ctxs, "cvae", deps_of, cache.code_version(subgoal_stages._offline_cvae))
    if len(todo) < 2:
        return []
    t0 = time.perf_counter()
    try:
        trained = vmapped.train_cvaes(
            [ctxs[i].keys["cvae"] for i, _ in todo],
            [(extracted[i][0].s, extracted[i][0].a, extracted[i][0].g) for i, _ in todo],
            cfg.cvae,
            cvae.obs_stats(ctxs[0].ds.observations),
            progress=ctxs[0].progress,
            groups=[extracted[i][2] for i, _ in todo],
            goal_actions=cfg.shaping.state_action,
        )
    except SpotError:  # the triplets do not fit one program: one seed at a time, in the CVAE stage
        return []
    return _hand_over(ctxs, todo, trained, "cvae", time.perf_counter() - t0)


def _misses(
    ctxs: Sequence[Context], stage: str, deps_of: Callable[[int], dict[str, Any]], code: str
) -> list[tuple[int, str]]:
    """``(index, key)`` of the seeds whose entry of ``stage`` is not in the stage cache."""
    keys = [(i, cache.key(stage, {**deps_of(i), **ctx.key_extra}, code)) for i, ctx in enumerate(ctxs)]  # as ctx.cached
    return [(i, k) for i, k in keys if not cache.load(k)[0]]


def _hand_over(
    ctxs: Sequence[Context], todo: list[tuple[int, str]], trained: Sequence[tuple[Any, Any]], stage: str, elapsed: float
) -> list[int]:
    """Leave each trained seed's ``{params, history}`` in its ``ctx.precomputed`` under its key, add
    the shared wall time to its ``time/<stage>_s`` and tag it ``vmap.<stage>``; the seeds' indices."""
    seeds = ",".join(str(ctxs[i].cfg.seed) for i, _ in todo)
    for (i, k), (params, history) in zip(todo, trained, strict=True):
        ctxs[i].precomputed[stage] = (k, {"params": params, "history": history})
        ctxs[i].times[f"time/{stage}_s"] = ctxs[i].times.get(f"time/{stage}_s", 0.0) + elapsed
        ctxs[i].tracker.set_tags({f"vmap.{stage}": seeds})
    return [i for i, _ in todo]


def _seed(tree: Any, s: int) -> Any:
    import jax

    return jax.tree.map(lambda a: a[s], tree)


def train_iql(
    ctxs: Sequence[Context], shaped: Sequence[Shaped], overlap: bool | None = None, static: bool | None = None
) -> list[Policy]:
    """IQL for every seed of ``ctxs`` as one vmapped program; each seed evaluated and logged to its
    own context, as :func:`spot.policy_stages.iql_policy` does for one seed (same keys, same schedule).

    The evaluations run on the CPU device (:class:`_Evaluations`); with ``overlap`` (default: when
    JAX's default backend is an accelerator) in a thread beside the training, which goes on with
    the next updates meanwhile; each is logged in order at the next chunk boundary. With ``static``
    (the same default) whole chunks run as a loop of static length (:class:`_StaticChunks`)."""
    import jax
    import jax.numpy as jnp

    from spot.policy import iql

    cfg, ds = ctxs[0].cfg, ctxs[0].ds
    rewards = np.stack([np.asarray(s.reward, np.float32) for s in shaped])
    data = jax.device_put(policy_stages.policy_transitions(cfg, ds, rewards[0])._replace(rew=rewards))
    init_keys, train_keys = (
        jnp.stack(k) for k in zip(*(jax.random.split(c.keys["policy"]) for c in ctxs), strict=True)
    )
    state = iql.init_state(init_keys, ds.obs_dim, ds.act_dim, cfg.iql)
    chunk = iql.make_vmapped_train_chunk(cfg.iql, per_seed_rewards=True)
    on_accelerator = jax.default_backend() != "cpu"
    if on_accelerator if static is None else static:
        chunk = _StaticChunks(cfg.iql, chunk)
    fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
    evals = _Evaluations(ctxs, on_accelerator if overlap is None else overlap)

    def evaluate(actor_params: Any, step: int) -> float:
        evals.submit(actor_params, step)
        return math.nan  # iql.train's curve; unused (each seed's scores are in evals.scores)

    def log(metrics: dict[str, Any], step: int) -> None:
        evals.drain()
        for s, ctx in enumerate(ctxs):
            ctx.log({k: float(np.asarray(v)[s]) for k, v in metrics.items()}, step=step)

    t0 = time.perf_counter()
    try:
        curve = iql.train(chunk, state, lambda c: (data, fold(train_keys, c)), cfg.iql, cfg.eval.every, evaluate, log)
        train_s = time.perf_counter() - t0 - curve.eval_s
        evals.drain(wait=True)
    finally:
        evals.close()
    policies = []
    for s, ctx in enumerate(ctxs):
        ctx.times["time/iql_s"] = train_s + evals.eval_s[s]  # finish.finish subtracts this seed's evaluations
        policies.append(Policy(_seed(curve.state, s), curve.steps, evals.scores[s], evals.eval_s[s]))
    return policies


class _StaticChunks:
    """IQL's vmapped chunk (``chunk(state, n, data, keys)``), whose chunks of exactly ``iql.chunk``
    updates run as a loop of that static length instead. :mod:`spot.loop`'s ``"sum"`` chunk loops
    ``n`` times with ``n`` traced (one program for every chunk length); on a GPU, XLA's runtime
    reads the predicate of a loop whose trip count it does not know back to the host at every
    iteration (a device-to-host copy and a wait per update; as we read XLA, not measured here),
    and does not when the count is static. The updates,
    and the means of their metrics, are the same (``tests/test_paper_row_multiseed.py``); a shorter
    last chunk still runs the traced program."""

    def __init__(self, cfg: Any, traced: Callable) -> None:
        self.traced, self.length, self.full = traced, cfg.chunk, _static_chunk(cfg)

    def __call__(self, state: Any, n: int, *args: Any) -> tuple[Any, dict]:
        return self.full(state, *args) if n == self.length else self.traced(state, n, *args)


@functools.lru_cache(maxsize=8)
def _static_chunk(cfg: Any) -> Callable:
    """The jitted whole chunk of :class:`_StaticChunks` (``cfg.chunk`` updates), kept per IQL config
    as :func:`spot.policy.iql.make_vmapped_train_chunk` is: compiled once per shapes in a process."""
    import jax

    from spot import loop
    from spot.batches import Transitions
    from spot.policy import iql

    update, length = iql.sampled_update(cfg), cfg.chunk

    def one(state: Any, data: Any, key: Any) -> tuple[Any, dict]:
        def body(_: Any, carry: tuple) -> tuple:
            st, sums = carry
            st, metrics = update(st, data, key)
            return st, jax.tree.map(lambda a, b: a + b, sums, metrics)

        idle = loop._zeros_like_metrics(update, state, data, key)
        state, sums = jax.lax.fori_loop(0, length, body, (state, idle))
        return state, jax.tree.map(lambda m: m / length, sums)  # loop._mean of a whole chunk

    axes = (0, Transitions(None, None, 0, None, None), 0)
    return jax.jit(jax.vmap(one, in_axes=axes), donate_argnums=0)


class _Evaluations:
    """The evaluations of a vmapped IQL program: every seed's episodes stepped together (one jitted
    policy call per env step for all of them, :func:`spot.evaluation.evaluate_runs`), each seed's
    numbers those of its own evaluation, the time shared equally among the seeds.

    The actor parameters are copied to the CPU device first (the next chunk donates the state), so
    the policy runs on the CPU cores beside an accelerator (one small program per env step: no
    device round trip) and on the same device as a CPU run's. With ``overlap`` they are evaluated by
    one worker thread while the training goes on; :meth:`drain` logs the finished ones, in order,
    from the calling thread (trackers and ``on_eval`` callbacks are only ever called from it)."""

    def __init__(self, ctxs: Sequence[Context], overlap: bool) -> None:
        import jax

        self.ctxs, self.cfg, self.cpu = ctxs, ctxs[0].cfg, jax.devices("cpu")[0]
        self.scores: list[list[float]] = [[] for _ in ctxs]
        self.eval_s = [0.0] * len(ctxs)
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="spot-eval") if overlap else None
        self.pending: collections.deque = collections.deque()

    def _run(self, actor_params: Any, step: int) -> tuple[list[dict[str, Any]], float]:
        from spot import evaluation

        t0 = time.perf_counter()
        results = evaluation.evaluate_runs(
            policy_stages.eval_policy(actor_params, self.cfg.iql, runs=True),
            self.ctxs[0].env_name,
            policy_stages.eval_episodes(self.cfg, step),
            [policy_stages.eval_seed(ctx.cfg) for ctx in self.ctxs],
            max_steps=self.cfg.eval.max_steps,
            stepper=self.cfg.eval.stepper,
        )
        return results, time.perf_counter() - t0

    def submit(self, actor_params: Any, step: int) -> None:
        """Evaluate the stacked ``actor_params`` after ``step`` updates (now, or in the worker)."""
        import jax

        from spot import phases

        params = jax.device_put(jax.tree.map(lambda a: np.array(a, copy=True), actor_params), self.cpu)
        if self.pool is None:
            with phases.phase("evaluate"):
                self._log(step, *self._run(params, step))
        else:
            self.pending.append((step, self.pool.submit(self._run, params, step)))

    def drain(self, wait: bool = False) -> None:
        """Log the evaluations that finished (all of them with ``wait``), in the order submitted."""
        while self.pending and (wait or self.pending[0][1].done()):
            step, future = self.pending.popleft()
            self._log(step, *future.result())

    def _log(self, step: int, results: list[dict[str, Any]], seconds: float) -> None:
        for s, (ctx, res) in enumerate(zip(self.ctxs, results, strict=True)):
            policy_stages.log_evaluation(ctx, res, step)
            self.scores[s].append(float(res["score_mean"]))
            self.eval_s[s] += seconds / len(self.ctxs)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)
