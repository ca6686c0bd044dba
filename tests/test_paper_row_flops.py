"""spot.flops (FLOPs from layer sizes) against hand-computed counts and against XLA's own cost
analysis of the programs; spot bench programs' arithmetic (issue 40 item 4)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot import bench_programs, flops
from spot.batches import Transitions
from spot.config import CVAEConfig, IQLConfig, PTConfig
from spot.policy import iql
from spot.reward import pt
from spot.subgoal import cvae


def test_dense_and_mlp_by_hand():
    assert flops.dense(256, 256, 256) == 2 * 256**3 == 33_554_432
    # 11 -> 256 -> 256 -> 1 over 4 rows: (11*256 + 256*256 + 256*1) = 68,608 multiply-adds a row
    assert flops.mlp(4, 11, (256, 256), 1) == 2 * 4 * 68_608


def test_iql_update_by_hand():
    """Multiply-adds a row: value 11-256-256-1 = 68,608; critic 14-256-256-1 = 69,376; actor
    11-256-256-3 = 69,120. Parallel: value 4 passes (V(s') and 3 for its loss), critics 2 x (1
    target + 3) = 8, actor 3: 1,036,800 a row, x 2 x 256 rows = 530,841,600 (docs: ~0.53 GFLOP).
    Sequential: V' on [s; s'] is one more value pass: 1,105,408 a row."""
    assert flops.iql_update(11, 3, (256, 256), 256) == 2 * 256 * 1_036_800 == 530_841_600
    assert flops.iql_update(11, 3, (256, 256), 256, "sequential") == 2 * 256 * 1_105_408


def test_transformer_and_pt_by_hand():
    """A block of 4 queries over 4 tokens, width 8: keys/values 4*8*16 = 512, query and output
    4*8*8 each = 512, logits and attention output 2*4*4*8 = 256, MLP 4*(8*32 + 32*8) = 2,048:
    3,328 multiply-adds. PT at the paper's sizes (segment 100, 1 layer, 256 dims, preference
    attention 256; obs 11, act 3): embeddings 100*14*256 = 358,400; the last block at the 100
    state tokens over 200: 14*100*256^2 + 4*100^2*256 = 101,990,400; the head 100*256*513 =
    13,132,800; the preference attention 100*100*256 + 2*100*100 = 2,580,000: 118,061,600 a
    segment (docs: 0.24 GFLOP forward); a step of 256 pairs is 3 x 2 x 256 segments."""
    assert flops.transformer_block(4, 4, 8) == 2 * 3_328
    assert flops.pt_forward(100, 11, 3, 256, 1, 256) == 2 * 118_061_600
    assert flops.pt_train_step(256, 100, 11, 3, 256, 1, 256) == 3 * 2 * 256 * 2 * 118_061_600
    # a window of 25 steps, last state only: 25*14*256 + 50*256*512 + 2*256*256 + 2*50*256 + 256*1024*2
    # + 256*513 = 89,600 + 6,553,600 + 131,072 + 25,600 + 524,288 + 131,328 = 7,455,488
    assert flops.pt_forward(25, 11, 3, 256, 1, 256, last_only=True) == 2 * 7_455_488


def test_cvae_and_mr_by_hand():
    """CVAE 32-64-32, latent 16, obs 11, act 3: encoder 25-32-64-32-32 = 5,920, prior 14-...-32 =
    5,568, decoder 30-32-64-32-11 = 5,408: 16,896 a triplet (docs: 17 k). MR 14-256-256-1 =
    69,376 a step of a segment, 2 x 256 x 100 steps a training step."""
    assert flops.cvae_step(256, 11, 3, 16, (32, 64, 32)) == 3 * 2 * 256 * 16_896
    assert flops.mr_train_step(256, 100, 11, 3, (256, 256)) == 3 * 2 * (2 * 256 * 100) * 69_376


def _xla_flops(fn, *args) -> float:
    cost = jax.jit(fn).lower(*args).compile().cost_analysis()
    return float((cost[0] if isinstance(cost, list) else cost)["flops"])


@pytest.mark.parametrize("order", ["parallel", "sequential"])
def test_counts_agree_with_xla_cost_analysis(order):
    """XLA counts every operation (element-wise ones too), so it finds a little more than the
    matrix products alone: within 0-20 % of it for an IQL update, PT's forward passes and a CVAE
    gradient, at sizes where products dominate."""
    cfg = IQLConfig(hidden=(128, 128), batch_size=128, order=order)
    state = iql.init_state(jax.random.key(0), 11, 3, cfg)
    batch = Transitions(jnp.zeros((128, 11)), jnp.zeros((128, 3)), jnp.zeros(128), jnp.zeros((128, 11)), jnp.ones(128))
    ratio = _xla_flops(lambda s, b: iql.update(s, b, cfg), state, batch) / flops.iql_update(
        11, 3, (128, 128), 128, order
    )
    assert 1.0 <= ratio < 1.2, ratio
    pcfg = PTConfig(embd_dim=64, n_layer=2, n_head=2, pref_attn_dim=32, max_timestep=50)
    params = pt.init_params(jax.random.key(0), pcfg, 11, 3)
    seg = (jnp.zeros((16, 20, 11)), jnp.zeros((16, 20, 3)), jnp.ones((16, 20), jnp.int32), jnp.ones((16, 20)))
    for last_only, fn in ((False, pt.forward), (True, pt.last_step_reward)):
        got = _xla_flops(lambda p, *s, fn=fn: fn(p, pcfg, *s), params, *seg)
        ratio = got / (16 * flops.pt_forward(20, 11, 3, 64, 2, 32, last_only=last_only))
        assert 1.0 <= ratio < 1.2, (last_only, ratio)
    ccfg = CVAEConfig(batch_size=128)
    st = cvae.init(jax.random.key(0), 11, 3, ccfg, (np.zeros(11, np.float32), np.ones(11, np.float32)))
    trip = cvae.Triplets(jnp.zeros((128, 11)), jnp.zeros((128, 3)), jnp.zeros((128, 11)))
    grad = jax.grad(lambda p, b: cvae.loss_fn(p, b, jax.random.key(0), ccfg)[0])
    ratio = _xla_flops(grad, st.params, trip) / flops.cvae_step(128, 11, 3, 16, (32, 64, 32))
    assert 1.0 <= ratio < 1.2, ratio


def test_paper_row_totals():
    """PT: 3 seeds x 10k steps x 362.7 GFLOP and 1,000 held-out evaluations of 2 x 50 segments;
    IQL: 12 runs x 1M sequential updates of 565,968,896 FLOPs."""
    rows = {r["stage"]: r for r in flops.paper_row()}
    assert list(rows) == ["pt", "mr", "cvae", "relabel", "iql"]
    pt_step, pt_segment = 3 * 2 * 256 * 2 * 118_061_600, 2 * 118_061_600
    assert rows["pt"]["flops"] == 3 * 10_000 * pt_step + 3 * 1000 * 100 * pt_segment
    assert rows["iql"]["flops"] == 12 * 1_000_000 * 2 * 256 * 1_105_408 and rows["iql"]["width"] == 12
    assert rows["relabel"]["steps"] == 3 * (3907 + 157)  # ceil(1e6 / 256) and ceil(1e6 / 6400) calls


def test_overhead_rows_are_measured_minus_predicted():
    """The policy call and MR's vmapped chunk at tiny sizes, against a made-up rate: every
    overhead is the measured time minus the FLOPs' time at that rate."""
    rate = 1e9
    rows = bench_programs.overhead_rows(bench_programs.programs(("mr", "policy")), rate, length=5, calls=3)
    assert [r["stage"] for r in rows] == ["mr", "policy"]
    mr, policy = rows
    assert mr["width"] == 3 and mr["flops_per_step"] == 3 * flops.mr_train_step(4, 5, 11, 3, (8, 8))
    assert policy["flops_per_step"] == flops.policy_act(120, 11, 3, (8, 8))
    for r in rows:
        assert r["predicted_us"] == pytest.approx(1e6 * r["flops_per_step"] / rate)
        assert r["call_overhead_us"] == pytest.approx(r["per_call_us"] - r["predicted_us"])
        assert r["per_call_us"] > 0
    assert mr["overhead_us"] == pytest.approx(mr["in_program_us"] - mr["predicted_us"])
    assert policy["in_program_us"] is None  # one call per env step: no chunk
    text = bench_programs.format_programs({"rate": rate, "matmul_n": 8, "rows": rows})
    assert "mr" in text and "policy" in text and "device" in text


def test_bench_programs_takes_no_seeds(capsys):
    from spot.cli import main

    assert main(["bench", "programs", "--seeds", "2"]) == 2
    assert "error: spot bench programs: --seeds does not go with it" in capsys.readouterr().err
