"""``spot bench``: throughput, compile time and peak memory of each stage, at the paper's sizes.

These are measurements, printed, never asserted in tests; each names the device JAX ran on.
``spot bench sweep FILE`` runs a whole sweep and prints where its trials' time went
(:func:`bench_sweep`). ``--small`` shrinks every size so a
check finishes in seconds. Peak memory is the process's ``ru_maxrss`` (it includes everything the
process did before, so run one benchmark per process for clean numbers: the CLI does).

Every benchmark times the real jitted program of its stage (the train chunk of :mod:`spot.loop`,
the relabelling program) on synthetic data, after compiling it ahead of time.
"""

from __future__ import annotations

import resource
import sys
import time
from typing import Any

import numpy as np

from spot.config import CVAEConfig, IQLConfig, PTConfig, RelabelConfig


# --------------------------------------------------------------------------- measurement helpers
def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_seconds() -> float:
    """User + system CPU time of this process (all threads); on a shared machine, CPU time per step
    is a steadier measure than wall time."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def synthetic_pairs(num_pairs: int, length: int, obs_dim: int, act_dim: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random ``segment_batch``-format pairs (timesteps 1..T, random labels)."""
    import jax

    k = jax.random.split(jax.random.key(seed), 5)
    ts = np.tile(np.arange(1, length + 1, dtype=np.int32), (num_pairs, 1))
    return {
        "obs_1": np.asarray(jax.random.normal(k[0], (num_pairs, length, obs_dim))),
        "act_1": np.asarray(jax.random.uniform(k[1], (num_pairs, length, act_dim), minval=-1, maxval=1)),
        "obs_2": np.asarray(jax.random.normal(k[2], (num_pairs, length, obs_dim))),
        "act_2": np.asarray(jax.random.uniform(k[3], (num_pairs, length, act_dim), minval=-1, maxval=1)),
        "timesteps_1": ts,
        "timesteps_2": ts.copy(),
        "label": np.asarray(jax.random.bernoulli(k[4], 0.5, (num_pairs,)), np.float32),
    }


def synthetic_dataset(n_transitions: int, episode_len: int, obs_dim: int, act_dim: int, seed: int = 0) -> Any:
    """Random transitions in episodes of ``episode_len`` steps (the last may be shorter)."""
    from spot.data.dataset import Dataset

    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n_transitions, obs_dim)).astype(np.float32)
    return Dataset(
        observations=obs,
        actions=rng.uniform(-1, 1, size=(n_transitions, act_dim)).astype(np.float32),
        rewards=rng.normal(size=n_transitions).astype(np.float32),
        next_observations=np.roll(obs, -1, axis=0),
        terminals=np.zeros(n_transitions, bool),
        episode_ids=np.arange(n_transitions) // episode_len,
        raw_index=np.arange(n_transitions),
        name="synthetic",
    )


def _time_chunks(chunk: Any, state: Any, n: int, args: tuple, repeats: int) -> dict[str, float]:
    """Compile ``chunk`` ahead of time, run it once to warm up (for ``repeats > 1``), then ``repeats``
    times: ``elapsed_s``, ``cpu_s`` (process CPU time, all threads) and ``compile_s``."""
    import jax

    from spot import loop

    compile_s = loop.compile_seconds(chunk, state, n, *args)
    if repeats > 1:
        state, metrics = chunk(state, n, *args)
        jax.block_until_ready(metrics)
    t0, c0 = time.perf_counter(), cpu_seconds()
    for _ in range(repeats):
        state, metrics = chunk(state, n, *args)
    jax.block_until_ready((state, metrics))
    loop.check_finite(metrics, n)
    return {"elapsed_s": time.perf_counter() - t0, "cpu_s": cpu_seconds() - c0, "compile_s": compile_s}


# --------------------------------------------------------------------------- stages
def iql_updates(
    obs_dim: int = 11,
    act_dim: int = 3,
    n: int = 1_000_000,
    steps: int = 3000,
    seeds: int = 1,
    cfg: IQLConfig | None = None,
) -> dict[str, float]:
    """Updates per second of IQL's train chunk on ``n`` random transitions: ``steps`` timed updates
    (rounded up to whole chunks) after one compile and one warm-up chunk; ``seeds > 1`` runs the
    vmapped chunk. ``updates_per_cpu_s`` is per second of process CPU time (all threads)."""
    import jax
    import jax.numpy as jnp

    from spot.batches import Transitions
    from spot.policy import iql

    cfg = cfg or IQLConfig(chunk=min(1000, steps))
    rng = np.random.default_rng(0)
    data = Transitions(
        obs=jnp.asarray(rng.standard_normal((n, obs_dim), np.float32)),
        act=jnp.asarray(rng.uniform(-1, 1, (n, act_dim)).astype(np.float32)),
        rew=jnp.asarray(rng.standard_normal(n, np.float32)),
        next_obs=jnp.asarray(rng.standard_normal((n, obs_dim), np.float32)),
        mask=jnp.asarray((rng.uniform(size=n) > 0.01).astype(np.float32)),
    )
    keys = jax.random.split(jax.random.key(0), seeds)
    if seeds == 1:
        state, key, fn = iql.init_state(keys[0], obs_dim, act_dim, cfg), keys[0], iql.make_train_chunk(cfg)
    else:
        state, key, fn = iql.init_state(keys, obs_dim, act_dim, cfg), keys, iql.make_vmapped_train_chunk(cfg)
    chunks = -(-steps // cfg.chunk)
    t = _time_chunks(fn, state, cfg.chunk, (data, key), chunks)
    updates = chunks * cfg.chunk * seeds
    return {
        "updates_per_s": updates / t["elapsed_s"],
        "updates_per_s_per_seed": updates / t["elapsed_s"] / seeds,
        "updates_per_cpu_s": updates / t["cpu_s"],
        "compile_s": t["compile_s"],
        "peak_rss_mb": peak_rss_mb(),
    }


def bench_iql(small: bool = False, seeds: int = 1, order: str = IQLConfig.order) -> dict[str, Any]:
    cfg = IQLConfig(hidden=(64, 64), chunk=100, order=order) if small else IQLConfig(chunk=1000, order=order)
    n = 10_000 if small else 1_000_000
    steps = 300 if small else 3000
    return {
        "what": f"IQL updates (batch {cfg.batch_size}, {cfg.hidden}, obs 11, act 3, {n} transitions, "
        f"{seeds} seed(s), order {order})",
        **iql_updates(obs_dim=11, act_dim=3, n=n, steps=steps, seeds=seeds, cfg=cfg),
    }


def reward_steps(
    model: Any,
    batch: int = 256,
    length: int = 100,
    steps: int = 3,
    obs_dim: int = 11,
    act_dim: int = 3,
    seed: int = 0,
    micro_batch: int = 64,
    seeds: int = 1,
) -> dict[str, float]:
    """Time ``steps`` training steps of ``batch`` pairs of length ``length`` (the real train chunk,
    one call): ``steps_per_s`` (compile excluded), ``cpu_s_per_step``, ``compile_s``, ``peak_rss_mb``.
    ``seeds > 1``: that many seeds (own keys and pairs) as one vmapped chunk
    (:mod:`spot.reward.vmapped`); ``steps_per_s`` then counts seed-steps."""
    import jax
    import jax.numpy as jnp

    from spot.reward import train, update, vmapped

    init_keys, train_keys = zip(*(jax.random.split(jax.random.key(seed + s)) for s in range(seeds)), strict=True)
    pairs = [train.pref_pairs(synthetic_pairs(batch, length, obs_dim, act_dim, seed + s)) for s in range(seeds)]
    states = [update.init_state(model, k, obs_dim, act_dim, steps) for k in init_keys]
    if seeds == 1:
        state, data, key = states[0], jax.device_put(pairs[0]), train_keys[0]
        chunk = update.make_train_chunk(model, batch, steps, steps, micro_batch)
    else:
        state, data = jax.device_put((vmapped._stack(states), vmapped._stack(pairs)))
        key, chunk = jnp.stack(train_keys), vmapped._vmapped_train_chunk(model, batch, steps, steps, micro_batch)
    t = _time_chunks(chunk, state, steps, (data, key), 1)
    return {
        "steps_per_s": steps * seeds / t["elapsed_s"],
        "cpu_s_per_step": t["cpu_s"] / (steps * seeds),
        "compile_s": t["compile_s"],
        "peak_rss_mb": peak_rss_mb(),
    }


def bench_pt(small: bool = False, dtype: str = "float32", seeds: int = 1) -> dict[str, Any]:
    from spot.reward.pt import PT

    if small:
        cfg, batch, length, steps = PTConfig(embd_dim=64, pref_attn_dim=64, dtype=dtype), 32, 50, 3
    else:
        cfg, batch, length, steps = PTConfig(dtype=dtype), 256, 100, 3
    out = reward_steps(PT(cfg), batch=batch, length=length, steps=steps, seeds=seeds)
    return {
        "what": f"PT train steps ({cfg.n_layer} layer, {cfg.n_head} heads, {cfg.embd_dim} dims, segment {length}, "
        f"batch {batch} pairs, {dtype}, {seeds} seed(s){' vmapped: seed-steps' if seeds > 1 else ''})",
        **out,
    }


def relabel_transitions(
    n_transitions: int,
    model: Any,
    relabel_cfg: RelabelConfig | None = None,
    obs_dim: int = 11,
    act_dim: int = 3,
    episode_len: int = 1000,
    seed: int = 0,
) -> dict[str, float]:
    """Relabel ``n_transitions`` random transitions with a freshly initialised ``model``:
    ``transitions_per_s`` (compile excluded), ``compile_s``, ``total_s``, ``cpu_s_total`` (all
    threads, compile included) and ``peak_rss_mb``."""
    import jax

    from spot.reward import relabel

    ds = synthetic_dataset(n_transitions, episode_len, obs_dim, act_dim, seed)
    params = model.init(jax.random.key(seed), obs_dim, act_dim)
    c0 = cpu_seconds()
    out = relabel.relabel_rewards(model, params, ds, relabel_cfg or RelabelConfig(), progress=False)
    return {
        "transitions_per_s": n_transitions / (out.total_s - out.compile_s),
        "compile_s": out.compile_s,
        "total_s": out.total_s,
        "cpu_s_total": cpu_seconds() - c0,
        "peak_rss_mb": peak_rss_mb(),
    }


def bench_relabel(small: bool = False, mode: str = "chunked") -> dict[str, Any]:
    from spot.reward.pt import PT

    n = 20_000 if small else 1_000_000
    cfg = PTConfig(embd_dim=64, pref_attn_dim=64) if small else PTConfig()
    rcfg = RelabelConfig(mode=mode, window=100 if mode == "chunked" else 25)
    return {
        "what": f"PT relabelling, {mode} mode, {n} transitions ({cfg.embd_dim} dims)",
        **relabel_transitions(n, PT(cfg), relabel_cfg=rcfg),
    }


def bench_cvae(small: bool = False) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from spot.subgoal import cvae
    from spot.subgoal.extract import Triplets

    cfg = CVAEConfig(batch_size=256)
    m, obs_dim, act_dim = (2_000, 11, 3) if small else (50_000, 11, 3)
    steps = 500 if small else 5000
    rng = np.random.default_rng(0)
    s = rng.normal(size=(m, obs_dim)).astype(np.float32)
    data = Triplets(
        jnp.asarray(s), jnp.asarray(rng.uniform(-1, 1, (m, act_dim)).astype(np.float32)), jnp.asarray(s + 0.1)
    )
    state = cvae.init(jax.random.key(0), obs_dim, act_dim, cfg, cvae.obs_stats(s))
    t = _time_chunks(cvae.make_train_chunk(cfg, steps), state, steps, (data, jnp.int32(m), jax.random.key(1)), 1)
    return {
        "what": f"CVAE steps (batch {cfg.batch_size}, hidden {cfg.hidden}, latent {cfg.latent_dim})",
        "steps_per_s": steps / t["elapsed_s"],
        "compile_s": t["compile_s"],
        "peak_rss_mb": peak_rss_mb(),
    }


def sac_step_parts(env: str, cfg: Any, capacity: int, chunks: int, acts: int) -> dict[str, float]:
    """The three parts of one environment step of the locomotion recipe's SAC (one update per step):
    an update of its train chunk (``cfg.update_every`` updates, batches drawn from ``capacity`` random
    rows), one stochastic action of its jitted actor and one step of the env (``hopper`` or
    ``walker2d``, in the model the recipe uses), each in milliseconds, and the environment steps per
    second their sum allows. Evaluations (10 deterministic episodes every 10k steps) are not counted."""
    import jax
    import jax.numpy as jnp

    from spot import envs, loop
    from spot.recipes import sac, sac_train
    from spot.recipes.locomotion import ENV_IDS

    gym_env = sac_train.make_env(ENV_IDS[env], cfg, **dict(envs.locomotion_make_kwargs(env)))
    obs_dim, act_dim = gym_env.observation_space.shape[0], gym_env.action_space.shape[0]
    rng = np.random.default_rng(0)
    shapes = {"observations": (obs_dim,), "next_observations": (obs_dim,), "actions": (act_dim,)}
    replay = sac.Replay(
        *(jnp.asarray(rng.standard_normal((capacity, *shapes.get(k, ())), np.float32)) for k in sac.Replay._fields)
    )
    state = sac.init_state(jax.random.key(0), obs_dim, act_dim, cfg)
    args = (replay, jnp.int32(capacity), jax.random.key(1), cfg, cfg.update_every)
    compile_s = loop.compile_seconds(sac.train_chunk, state, *args)
    state, metrics = sac.train_chunk(state, *args)  # warm-up, not timed
    jax.block_until_ready(state)
    t0, c0 = time.perf_counter(), cpu_seconds()
    for i in range(chunks):
        state, metrics = sac.train_chunk(
            state, replay, jnp.int32(capacity), jax.random.key(2 + i), cfg, cfg.update_every
        )
    jax.block_until_ready(state)
    update_s, update_cpu_s = (time.perf_counter() - t0) / (chunks * cfg.update_every), cpu_seconds() - c0
    obs, _ = gym_env.reset(seed=0)
    params, key = state.actor.params, jax.random.key(3)
    np.asarray(sac_train._act_at(params, obs, key, 0, False, cfg))  # compile
    t_act = t_env = 0.0
    for t in range(acts):
        t0 = time.perf_counter()
        action = np.asarray(sac_train._act_at(params, obs, key, t, False, cfg))
        t1 = time.perf_counter()
        obs, _, terminated, truncated, _ = gym_env.step(action)
        t_env += time.perf_counter() - t1
        t_act += t1 - t0
        if terminated or truncated:
            obs, _ = gym_env.reset()
    gym_env.close()
    act_s, env_s = t_act / acts, t_env / acts
    return {
        "update_ms": 1e3 * update_s,
        "update_cpus": update_cpu_s / (update_s * chunks * cfg.update_every),
        "act_ms": 1e3 * act_s,
        "env_step_ms": 1e3 * env_s,
        "steps_per_s": 1.0 / (update_s + act_s + env_s),
        "hours_per_1m_steps": 1e6 * (update_s + act_s + env_s) / 3600.0,
        "compile_s": compile_s,
        "peak_rss_mb": peak_rss_mb(),
    }


def bench_sac(small: bool = False, env: str | None = None, size: str | None = None) -> dict[str, Any]:
    """The recipe's SAC at ``size`` (``paper`` or ``paper-fast``) with its buffer of ``total_steps``
    rows (the step cap: 2M Hopper, 3M Walker2d); ``small``: 32x32 nets and 10k rows, for tests."""
    import dataclasses

    from spot.recipes import locomotion

    env, size = env or "walker2d", size or "paper"
    cfg = locomotion.SIZES[size].sac_config(env)
    capacity, chunks, acts = cfg.total_steps, 3, 2000
    if small:
        cfg = dataclasses.replace(cfg, hidden_dims=(32, 32), batch_size=64, update_every=100)
        capacity, chunks, acts = 10_000, 2, 200
    return {
        "what": f"SAC steps of the {env} recipe at size {size}{' (--small)' if small else ''} (batch {cfg.batch_size}, "
        f"{cfg.hidden_dims}, one update per step, {capacity} buffer rows)",
        **sac_step_parts(env, cfg, capacity, chunks, acts),
    }


def _env_steps_per_s(
    modes: dict[str, Any], repeats: int
) -> tuple[dict[str, list[Any]], dict[str, float], dict[str, float]]:
    """Each of ``modes`` (name -> a function returning evaluation results) once to build the envs
    and compile, then ``repeats`` rounds of one timed call of each, interleaved (a shared machine's
    load drifts): each mode's last results and env steps per second of wall and of CPU time."""
    results = {name: fn() for name, fn in modes.items()}
    wall, cpu = dict.fromkeys(modes, 0.0), dict.fromkeys(modes, 0.0)
    for _ in range(repeats):
        for name, fn in modes.items():
            t0, c0 = time.perf_counter(), cpu_seconds()
            results[name] = fn()
            wall[name] += time.perf_counter() - t0
            cpu[name] += cpu_seconds() - c0
    steps = {name: repeats * sum(int(r["lengths"].sum()) for r in res) for name, res in results.items()}
    return results, {n: steps[n] / wall[n] for n in modes}, {n: steps[n] / cpu[n] for n in modes}


def bench_eval(small: bool = False, episodes: int = 10, seeds: int = 1, stepper: str = "mujoco") -> dict[str, Any]:
    """Env steps per second of an evaluation on Hopper, ``seeds`` runs of ``episodes`` episodes:
    ``batched``: all episodes stepped together, the policy one jitted call per env step for all
    of them (:func:`spot.evaluation.evaluate_runs` with :func:`spot.run.policy_stages.eval_policy`, as runs and
    vmapped trials evaluate), the env stepped by ``stepper`` (``eval.stepper``; ``batched_gymnasium``:
    the same in gymnasium's envs, when ``stepper`` is ``mujoco``); ``sequential``: one episode after another
    (:func:`spot.evaluation.evaluate_sequential`), the same program on one observation per step;
    ``seq_eager``: one after another, ``iql.act`` run op by op (not jitted: spot's policy call
    before issue 40); ``before``: together, ``iql.act`` op by op (spot's evaluation before issue
    40 called it on the episodes still running). The actor: IQL's default, random init, its output
    layer scaled by 0.03 (small actions: Hopper stands about 80-110 steps). ``same_episodes``: the
    batched and the sequential returns and lengths are equal."""
    import jax

    from spot import evaluation, mujoco_step
    from spot.policy import iql
    from spot.run import policy_stages

    cfg = IQLConfig(hidden=(64, 64)) if small else IQLConfig()
    name, max_steps, repeats = "hopper-medium-replay", (30 if small else 0), (1 if small else 3)
    actors = iql.init_state(jax.random.split(jax.random.key(0), seeds), 11, 3, cfg).actor.params
    actors = {"params": {**actors["params"], "Dense_0": jax.tree.map(lambda a: a * 0.03, actors["params"]["Dense_0"])}}
    base = [10_000 * (s + 1) for s in range(seeds)]  # policy_stages.eval_seed of seeds 0, 1, ...
    one = [jax.tree.map(lambda a, s=s: a[s], actors) for s in range(seeds)]

    def eager(p: Any) -> Any:
        return lambda obs: np.asarray(iql.act(p, obs, cfg))

    def alone(policy: Any) -> Any:
        return lambda: [
            evaluation.evaluate_sequential(policy(p), name, episodes, b, max_steps=max_steps)
            for p, b in zip(one, base, strict=True)
        ]

    def together(policy: Any, how: str = "gymnasium") -> Any:
        return lambda: evaluation.evaluate_runs(policy, name, episodes, base, max_steps=max_steps, stepper=how)

    batched = policy_stages.eval_policy(actors, cfg, runs=True)
    used = evaluation.stepper_used(name, stepper)
    threads = f", physics on up to {mujoco_step.default_threads()} thread(s)" if used == "mujoco" else ""
    res, wall, cpu = _env_steps_per_s(
        {
            "batched": together(batched, stepper),
            **({"batched_gymnasium": together(batched)} if used != "gymnasium" else {}),
            "sequential": alone(lambda p: policy_stages.eval_policy(p, cfg)),
            "seq_eager": alone(eager),
            "before": together(lambda obs: np.stack([eager(p)(o) for p, o in zip(one, obs, strict=True)])),
        },
        repeats,
    )
    pairs = list(zip(res["batched"], res["sequential"], strict=True))
    same = all((a["returns"] == b["returns"]).all() and (a["lengths"] == b["lengths"]).all() for a, b in pairs)
    return {
        "what": f"evaluation env steps, Hopper, {seeds} run(s) x {episodes} episodes, actor {cfg.hidden}"
        f"{', 30 steps (--small)' if small else ''}; {repeats} timed round(s), env steps per second",
        "stepper": f"{used} (batched{threads}; sequential: gymnasium)",
        "env_steps": sum(int(r["lengths"].sum()) for r in res["batched"]),
        **{f"{mode}_steps_s": rate for mode, rate in wall.items()},
        "ratio": wall["batched"] / wall["sequential"],
        "ratio_cpu": cpu["batched"] / cpu["sequential"],
        "ratio_vs_seq_eager": wall["batched"] / wall["seq_eager"],
        "ratio_vs_before": wall["batched"] / wall["before"],
        **({"ratio_vs_batched_gymnasium": wall["batched"] / wall["batched_gymnasium"]} if used != "gymnasium" else {}),
        "same_episodes": same,
        "peak_rss_mb": peak_rss_mb(),
    }


BENCHES = {
    "iql": bench_iql,
    "pt": bench_pt,
    "relabel": bench_relabel,
    "cvae": bench_cvae,
    "sac": bench_sac,
    "eval": bench_eval,
}


def format_result(name: str, result: dict[str, Any]) -> str:
    """The figures of one benchmark, and the device JAX ran it on."""
    from spot import phases

    lines = [f"[{name}] {result.pop('what')}"]
    for key, value in result.items():
        lines.append(f"  {key:18s} {value:,.3f}" if isinstance(value, float) else f"  {key:18s} {value}")
    lines.append(f"  {'device':18s} {phases.devices()}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- a whole sweep
def bench_sweep(path: str, smoke: bool = False, **sweep_kwargs: Any) -> int:
    """``spot bench sweep FILE [--smoke]``: run the sweep (:func:`spot.sweep.run_sweep`, which prints
    its own summary and the totals of the time breakdown), then print one line per trial (seconds
    per phase, :mod:`spot.phases`), the totals, the CPU utilisation of the whole command's process
    tree (dataset builds, MLflow server, Ray and every trial) and the device the trials ran on, and
    last the floor of the launch's training and each phase's ratio to it (:mod:`spot.sweep.floor`).
    Returns the exit code of ``spot sweep``."""
    from spot import phases, sweep

    spec = sweep.load(path, smoke=smoke)
    try:
        with phases.CpuMeter() as cpu:
            rows = sweep.run_sweep(path, smoke=smoke, **sweep_kwargs)
    except sweep.Interrupted as e:
        print(f"interrupted: {e}", file=sys.stderr)
        return e.exit_code
    print(format_sweep_bench(rows, spec, cpu), flush=True)
    from spot.sweep import floor  # the floor (a calibration now, on the idle cores) and each phase's ratio to it

    print(floor.report(spec, rows, cpu), flush=True)
    return 0 if all(r.status == "FINISHED" for r in rows) else 1


def format_sweep_bench(rows: list[Any], spec: Any, cpu: Any) -> str:
    """The report of :func:`bench_sweep`: a title line, the per-trial breakdown and the command's
    CPU utilisation (``cpu``: a finished :class:`spot.phases.CpuMeter`)."""
    from spot.sweep.summary import format_breakdown

    done = sum(r.status == "FINISHED" for r in rows)
    table = format_breakdown(rows, spec.axis_keys, per_trial=True) or "(no trial was timed in this launch)"
    return "\n".join(
        [
            f"\n[sweep] {spec.experiment}: {done}/{len(rows)} runs finished in {cpu.wall_s:.1f} s "
            f"(the whole command: datasets, MLflow server, Ray, trials, summary)",
            table,
            f"command: {cpu.cpu_s:.1f} CPU-seconds over {cpu.wall_s:.1f} s: CPU utilisation "
            f"{100 * cpu.util:.0f}% of {cpu.cpus} cores",
        ]
    )
