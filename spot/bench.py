"""``spot bench``: throughput, compile time and peak memory of each stage, at the paper's sizes.

These are measurements, printed, never asserted in tests. ``--small`` shrinks every size so a
check finishes in seconds. Peak memory is the process's ``ru_maxrss`` (it includes everything the
process did before, so run one benchmark per process for clean numbers: the CLI does).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

import spot  # noqa: F401  (XLA flags before jax)
from spot.config import CVAEConfig, IQLConfig, PTConfig, RelabelConfig


def bench_iql(small: bool = False, seeds: int = 1, order: str = IQLConfig.order) -> dict[str, Any]:
    from spot.policy import iql

    cfg = IQLConfig(hidden=(64, 64), chunk=100, order=order) if small else IQLConfig(chunk=1000, order=order)
    n = 10_000 if small else 1_000_000
    steps = 300 if small else 3000
    return {"what": f"IQL updates (batch {cfg.batch_size}, {cfg.hidden}, obs 11, act 3, {n} transitions, "
                    f"{seeds} seed(s), order {order})",
            **iql.bench_iql(obs_dim=11, act_dim=3, n=n, steps=steps, seeds=seeds, cfg=cfg)}


def bench_pt(small: bool = False, dtype: str = "float32") -> dict[str, Any]:
    from spot.reward import train

    if small:
        cfg, batch, length, steps = PTConfig(embd_dim=64, pref_attn_dim=64, dtype=dtype), 32, 50, 3
    else:
        cfg, batch, length, steps = PTConfig(dtype=dtype), 256, 100, 3
    out = train.bench_train_steps("pt", batch=batch, length=length, steps=steps, pt_cfg=cfg)
    return {"what": f"PT train steps ({cfg.n_layer} layer, {cfg.n_head} heads, {cfg.embd_dim} dims, segment {length}, "
                    f"batch {batch} pairs, {dtype})", **out}


def bench_relabel(small: bool = False, mode: str = "chunked") -> dict[str, Any]:
    from spot.reward import relabel

    n = 20_000 if small else 1_000_000
    cfg = PTConfig(embd_dim=64, pref_attn_dim=64) if small else PTConfig()
    rcfg = RelabelConfig(mode=mode, window=100 if mode == "chunked" else 25)
    return {"what": f"PT relabelling, {mode} mode, {n} transitions ({cfg.embd_dim} dims)",
            **relabel.bench_relabel(n, pt_cfg=cfg, relabel_cfg=rcfg)}


def bench_cvae(small: bool = False) -> dict[str, Any]:
    import jax

    from spot.reward.train import peak_rss_mb
    from spot.subgoal import cvae
    from spot.subgoal.extract import Triplets

    cfg = CVAEConfig(batch_size=256)
    m, obs_dim, act_dim = (2_000, 11, 3) if small else (50_000, 11, 3)
    steps = 500 if small else 5000
    rng = np.random.default_rng(0)
    s = rng.normal(size=(m, obs_dim)).astype(np.float32)
    data = Triplets(jax.numpy.asarray(s), jax.numpy.asarray(rng.uniform(-1, 1, (m, act_dim)).astype(np.float32)),
                    jax.numpy.asarray(s + 0.1))
    state = cvae.init(jax.random.key(0), obs_dim, act_dim, cfg, cvae.obs_stats(s))
    chunk = cvae.make_train_chunk(cfg, steps)
    t0 = time.perf_counter()
    compiled = chunk.lower(state, data, jax.random.key(1)).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(state, data, jax.random.key(1)))
    elapsed = time.perf_counter() - t0
    return {"what": f"CVAE steps (batch {cfg.batch_size}, hidden {cfg.hidden}, latent {cfg.latent_dim})",
            "steps_per_s": steps / elapsed, "compile_s": compile_s, "peak_rss_mb": peak_rss_mb()}


BENCHES = {"iql": bench_iql, "pt": bench_pt, "relabel": bench_relabel, "cvae": bench_cvae}


def format_result(name: str, result: dict[str, Any]) -> str:
    lines = [f"[{name}] {result.pop('what')}"]
    for key, value in result.items():
        lines.append(f"  {key:18s} {value:,.3f}" if isinstance(value, float) else f"  {key:18s} {value}")
    return "\n".join(lines)
