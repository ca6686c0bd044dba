"""``spot bench programs``: the per-step overhead of the programs of a paper-budget Table 1 row.

Each stage's real jitted program (PT's and MR's vmapped reward-model chunk, the vmapped CVAE chunk,
IQL's vmapped chunk over all runs, the relabelling program and the evaluation's policy call), at
tiny layer sizes and at the vmap widths of ``spot run --methods oracle,mr,pt,spot --seeds 0,1,2``
(3 seeds for the reward models and CVAEs, 12 runs for IQL), timed two ways after compiling:

* ``in_program``: one chunk of ``length`` steps (one scan on the device): the time a step costs
  inside the program;
* ``per_call``: ``calls`` one-step programs, each result fetched to the host before the next call
  (what a step costs when the host drives every step; for the relabelling and the policy call that
  is how they run: one call per batch, one per env step).

Against each, the time the step's FLOPs (:mod:`spot.flops`, from the layer sizes) take at this
machine's matmul rate, measured in the same command (:func:`matmul_rate`): the difference is the
per-step overhead, what a step costs beyond its arithmetic. At tiny sizes the FLOP time is next to
nothing, so the overhead is nearly all of it; at the paper's sizes a stage's time is about
``steps x (FLOPs / rate + overhead)`` (docs/benchmarks.md, "GPU: expected figures").
Measurements, printed; the tests check the arithmetic, never a time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from spot import flops
from spot.config import CVAEConfig, IQLConfig, MRConfig, PTConfig

OBS, ACT = 11, 3  # Hopper
STAGES = ("pt", "mr", "cvae", "iql", "relabel", "policy")


def matmul_rate(n: int | None = None, repeats: int = 5) -> tuple[float, int]:
    """``(FLOP/s, n)``: the best of ``repeats`` timed ``[n, n] @ [n, n]`` float32 products (jitted,
    compiled and run once first); ``n`` defaults to 1024 on a CPU and 8192 on an accelerator."""
    import jax
    import jax.numpy as jnp

    n = n or (1024 if jax.default_backend() == "cpu" else 8192)
    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32)
    product = jax.jit(jnp.matmul)
    jax.block_until_ready(product(a, b))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(product(a, b))
        best = min(best, time.perf_counter() - t0)
    return flops.dense(n, n, n) / best, n


@dataclass
class Program:
    """A stage's program: ``make(length) -> (chunk, state, args)`` builds its chunk of ``length``
    steps (``length`` None: a per-call program, ``call(args)``), and its FLOPs per step (all seeds)."""

    stage: str
    width: int
    flops_per_step: int
    make: Callable[[int], tuple[Any, Any, tuple]] | None = None
    call: Callable[[], Any] | None = None


def _reward(stage: str, width: int) -> Program:
    import jax
    import jax.numpy as jnp

    from spot import bench
    from spot.reward import train, update, vmapped
    from spot.reward.mr import MR
    from spot.reward.pt import PT

    pairs, length, steps = 4, 5, 10_000
    if stage == "pt":
        cfg = PTConfig(embd_dim=8, n_head=1, pref_attn_dim=8, max_timestep=length)
        model, per_seed = PT(cfg), flops.pt_train_step(pairs, length, OBS, ACT, 8, 1, 8)
    else:
        model, per_seed = MR(MRConfig(hidden=(8, 8))), flops.mr_train_step(pairs, length, OBS, ACT, (8, 8))

    def make(chunk_length: int) -> tuple[Any, Any, tuple]:
        keys = jax.random.split(jax.random.key(0), width)
        data = vmapped._stack(
            [train.pref_pairs(bench.synthetic_pairs(pairs, length, OBS, ACT, s)) for s in range(width)]
        )
        states = vmapped._stack([update.init_state(model, k, OBS, ACT, steps) for k in keys])
        chunk = vmapped._vmapped_train_chunk(model, pairs, chunk_length, steps, 64)
        return chunk, jax.device_put(states), (jax.device_put(data), jnp.stack(list(keys)))

    return Program(stage, width, width * per_seed, make)


def _cvae(width: int) -> Program:
    import jax
    import jax.numpy as jnp

    from spot.subgoal import cvae, vmapped
    from spot.subgoal.cvae import Triplets

    cfg, rows = CVAEConfig(hidden=(8, 8), latent_dim=2, batch_size=8), 64

    def make(chunk_length: int) -> tuple[Any, Any, tuple]:
        rng = np.random.default_rng(0)
        s = rng.normal(size=(width, rows, OBS)).astype(np.float32)
        a = rng.uniform(-1, 1, (width, rows, ACT)).astype(np.float32)
        stats = (np.zeros(OBS, np.float32), np.ones(OBS, np.float32))
        keys = jax.random.split(jax.random.key(0), width)
        state = vmapped._stack([cvae.init(k, OBS, ACT, cfg, stats) for k in keys])
        count = jnp.full((width,), rows, jnp.int32)
        data = Triplets(jnp.asarray(s), jnp.asarray(a), jnp.asarray(s + 0.1))
        return vmapped._vmapped_chunk(cfg, chunk_length), state, (data, count, keys)

    return Program("cvae", width, width * flops.cvae_step(8, OBS, ACT, 2, (8, 8)), make)


def _iql(width: int) -> Program:
    import dataclasses

    import jax
    import jax.numpy as jnp

    from spot.batches import Transitions
    from spot.policy import iql

    cfg, n = IQLConfig(hidden=(8, 8), batch_size=8, order="sequential"), 1000

    def make(chunk_length: int) -> tuple[Any, Any, tuple]:
        rng = np.random.default_rng(0)
        c = dataclasses.replace(cfg, chunk=chunk_length)
        data = Transitions(
            obs=jnp.asarray(rng.normal(size=(n, OBS)).astype(np.float32)),
            act=jnp.asarray(rng.uniform(-1, 1, (n, ACT)).astype(np.float32)),
            rew=jnp.asarray(rng.normal(size=(width, n)).astype(np.float32)),
            next_obs=jnp.asarray(rng.normal(size=(n, OBS)).astype(np.float32)),
            mask=jnp.ones(n, jnp.float32),
        )
        keys = jax.random.split(jax.random.key(0), width)
        return iql.make_vmapped_train_chunk(c, per_seed_rewards=True), iql.init_state(keys, OBS, ACT, c), (data, keys)

    return Program("iql", width, width * flops.iql_update(OBS, ACT, (8, 8), 8, "sequential"), make)


def _relabel() -> Program:
    import jax

    from spot import bench
    from spot.reward import pt, relabel

    cfg, window, batch, n = PTConfig(embd_dim=8, n_head=1, pref_attn_dim=8), 5, 8, 1000
    ds = bench.synthetic_dataset(n, 100, OBS, ACT)
    params = pt.init_params(jax.random.key(0), cfg, OBS, ACT)
    program = relabel._sliding_program(cfg, window)
    obs_all, act_all = jax.device_put(ds.observations), jax.device_put(ds.actions)
    rows, starts = np.arange(batch, dtype=np.int32) + window, np.zeros(batch, np.int32)
    per_window = flops.pt_forward(window, OBS, ACT, 8, 1, 8, last_only=True)
    return Program(
        "relabel", 1, batch * per_window, call=lambda: jax.device_get(program(params, obs_all, act_all, rows, starts))
    )


def _policy(width: int) -> Program:
    import jax

    from spot.policy import iql
    from spot.run import policy_stages

    cfg, episodes = IQLConfig(hidden=(8, 8)), 10
    actors = iql.init_state(jax.random.split(jax.random.key(0), width), OBS, ACT, cfg).actor.params
    policy = policy_stages.eval_policy(actors, cfg, runs=True)
    obs = np.zeros((width, episodes, OBS), np.float32)
    return Program("policy", width, flops.policy_act(width * episodes, OBS, ACT, (8, 8)), call=lambda: policy(obs))


def programs(stages: tuple[str, ...] = STAGES) -> list[Program]:
    """The programs of ``stages`` at tiny sizes and the paper row's vmap widths."""
    build = {
        "pt": lambda: _reward("pt", 3),
        "mr": lambda: _reward("mr", 3),
        "cvae": lambda: _cvae(3),
        "iql": lambda: _iql(12),
        "relabel": _relabel,
        "policy": lambda: _policy(12),
    }
    return [build[s]() for s in stages]


def _time_in_program(p: Program, length: int) -> float:
    """Seconds per step of one ``length``-step chunk (compiled and run once first)."""
    import jax

    chunk, state, args = p.make(length)
    state, metrics = chunk(state, length, *args)
    jax.block_until_ready((state, metrics))
    t0 = time.perf_counter()
    state, metrics = chunk(state, length, *args)
    jax.block_until_ready((state, metrics))
    return (time.perf_counter() - t0) / length


def _time_per_call(p: Program, calls: int) -> float:
    """Seconds per call of a one-step program, its result fetched to the host each time."""
    import jax

    if p.call is not None:
        call = p.call
    else:
        chunk, state, args = p.make(1)
        holder = [state]

        def call() -> Any:
            holder[0], metrics = chunk(holder[0], 1, *args)
            return jax.device_get(metrics)

    call()  # compile
    t0 = time.perf_counter()
    for _ in range(calls):
        call()
    return (time.perf_counter() - t0) / calls


def bench_programs(small: bool = False, stages: tuple[str, ...] = STAGES) -> dict[str, Any]:
    """Every stage's rows (:func:`overhead_rows`) and the matmul rate they are measured against."""
    rate, n = matmul_rate()
    length, calls = (50, 20) if small else (2000, 200)
    return {"rate": rate, "matmul_n": n, "rows": overhead_rows(programs(stages), rate, length, calls)}


def overhead_rows(progs: list[Program], rate: float, length: int, calls: int) -> list[dict[str, Any]]:
    """One row per program: its FLOPs per step, the µs a step's FLOPs take at ``rate``, the µs a step
    takes inside a ``length``-step chunk and per host call (``calls`` calls), and the overheads
    (measured minus predicted)."""
    rows = []
    for p in progs:
        predicted = p.flops_per_step / rate
        in_program = _time_in_program(p, length) if p.make is not None else None
        per_call = _time_per_call(p, calls)
        rows.append(
            {
                "stage": p.stage,
                "width": p.width,
                "flops_per_step": p.flops_per_step,
                "predicted_us": 1e6 * predicted,
                "in_program_us": None if in_program is None else 1e6 * in_program,
                "overhead_us": None if in_program is None else 1e6 * (in_program - predicted),
                "per_call_us": 1e6 * per_call,
                "call_overhead_us": 1e6 * (per_call - predicted),
            }
        )
    return rows


def format_programs(result: dict[str, Any]) -> str:
    """The table ``spot bench programs`` prints, and the device it ran on."""
    from spot import phases

    lines = [
        "[programs] each stage's program at tiny sizes, vmapped as in the paper-budget Table 1 row, against "
        f"its FLOPs at this machine's matmul rate ({result['rate'] / 1e9:,.1f} GFLOP/s: "
        f"[{result['matmul_n']}, {result['matmul_n']}] @ [{result['matmul_n']}, {result['matmul_n']}] float32)",
        f"  {'stage':8s} {'width':>5s} {'FLOP/step':>11s} {'predicted':>10s} {'in program':>10s} "
        f"{'overhead':>10s} {'per call':>10s} {'overhead':>10s}   (µs per step)   {'steps/s':>9s} {'FLOP-bound':>12s}",
    ]

    def us(x: float | None) -> str:
        return f"{'-':>10s}" if x is None else f"{x:10,.1f}"

    for r in result["rows"]:
        measured = r["in_program_us"] if r["in_program_us"] is not None else r["per_call_us"]
        lines.append(
            f"  {r['stage']:8s} {r['width']:5d} {r['flops_per_step']:11,d} {us(r['predicted_us'])} "
            f"{us(r['in_program_us'])} {us(r['overhead_us'])} {us(r['per_call_us'])} {us(r['call_overhead_us'])}"
            f"                   {1e6 / measured:9,.0f} {1e6 / r['predicted_us']:12,.0f}"
        )
    lines.append(
        "  steps/s: in the program (per call where there is none); FLOP-bound: what the FLOPs alone allow at the rate"
    )
    lines.append(f"  {'device':8s} {phases.devices()}")
    return "\n".join(lines)
