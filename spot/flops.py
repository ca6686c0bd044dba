"""FLOPs of spot's programs, counted from the layer sizes (docs/benchmarks.md, "GPU: expected figures").

Only the matrix products count (a multiply-add is 2 FLOPs); biases, activations, LayerNorms,
softmaxes and the optimiser's element-wise updates are left out (a few per cent at the sizes where
FLOPs matter). A training step counts :data:`TRAIN` times its forward pass: the backward pass
computes two products per forward product (the gradients of the weights and of the inputs).
Causal attention is counted in full, as XLA computes it (masked, not skipped).

These are the numbers ``spot bench programs`` divides by the machine's measured matmul rate to
predict a step's time, and the per-stage estimates of a paper-budget Table 1 row are built from
(:func:`paper_row`). Pure arithmetic: no JAX.
"""

from __future__ import annotations

from collections.abc import Sequence

TRAIN = 3
"""A training step's FLOPs per forward pass's: forward, and the backward's two products per product."""


def dense(rows: int, n_in: int, n_out: int) -> int:
    """One ``[rows, n_in] @ [n_in, n_out]`` product."""
    return 2 * rows * n_in * n_out


def mlp(rows: int, n_in: int, hidden: Sequence[int], n_out: int) -> int:
    """A forward pass of an MLP ``n_in -> hidden... -> n_out`` over ``rows`` rows."""
    sizes = [n_in, *hidden, n_out]
    return sum(dense(rows, a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True))


def iql_update(obs_dim: int, act_dim: int, hidden: Sequence[int], batch: int, order: str = "parallel") -> int:
    """One IQL update (:func:`spot.policy.iql.update`) on ``batch`` transitions, in forward passes
    over the batch: the two target critics (2), the value loss (V forward and backward: 3), the
    actor loss (3), the two critics' loss (6), and ``V(s')`` (1; ``sequential``: V' on ``[s; s']``, 2)."""
    value = mlp(batch, obs_dim, hidden, 1)
    critic = mlp(batch, obs_dim + act_dim, hidden, 1)
    actor = mlp(batch, obs_dim, hidden, act_dim)
    next_value = 2 * value if order == "sequential" else value
    return 2 * critic + TRAIN * value + TRAIN * actor + 2 * TRAIN * critic + next_value


def transformer_block(n_query: int, n_key: int, width: int, mlp_ratio: int = 4) -> int:
    """A pre-LN GPT-2 block (:class:`spot.nets.TransformerBlock`) computing ``n_query`` outputs over
    ``n_key`` tokens: keys and values of every token, the queries, logits and attention output of
    the queried ones, the output projection and the ``mlp_ratio``-wide MLP at them."""
    kv = dense(n_key, width, 2 * width)
    q_out = dense(n_query, width, width) * 2  # query and output projections
    attention = 2 * (2 * n_query * n_key * width)  # logits q.k and probs @ v, over all heads
    return kv + q_out + attention + mlp(n_query, width, [mlp_ratio * width], width)


def pt_forward(
    length: int, obs_dim: int, act_dim: int, width: int, n_layer: int, pref_dim: int, last_only: bool = False
) -> int:
    """One segment of ``length`` steps through the Preference Transformer (:mod:`spot.reward.pt`):
    the state and action embeddings, ``n_layer - 1`` full blocks over the ``2 length`` tokens, the
    last block at the ``length`` state tokens, the preference head and the preference attention.
    ``last_only``: the relabelling's sliding window, the last block and head at the last state only."""
    tokens = 2 * length
    embed = dense(length, obs_dim, width) + dense(length, act_dim, width)
    blocks = (n_layer - 1) * transformer_block(tokens, tokens, width)
    if last_only:
        return embed + blocks + transformer_block(1, tokens, width) + dense(1, width, 2 * pref_dim + 1)
    head = dense(length, width, 2 * pref_dim + 1)
    pref_attention = 2 * length * length * pref_dim + 2 * (2 * length * length)  # q.k; z and w
    return embed + blocks + transformer_block(length, tokens, width) + head + pref_attention


def pt_train_step(pairs: int, length: int, obs_dim: int, act_dim: int, width: int, n_layer: int, pref_dim: int) -> int:
    """One PT training step on ``pairs`` preference pairs (two segments each)."""
    return TRAIN * 2 * pairs * pt_forward(length, obs_dim, act_dim, width, n_layer, pref_dim)


def mr_train_step(pairs: int, length: int, obs_dim: int, act_dim: int, hidden: Sequence[int]) -> int:
    """One MR training step: ``r(s, a)`` at every step of both segments of ``pairs`` pairs."""
    return TRAIN * mlp(2 * pairs * length, obs_dim + act_dim, hidden, 1)


def cvae_step(batch: int, obs_dim: int, act_dim: int, latent: int, hidden: Sequence[int], goal_dim: int = 0) -> int:
    """One CVAE step (:mod:`spot.subgoal.cvae`) on ``batch`` triplets: encoder on ``[g, s, a]`` and
    prior on ``[s, a]`` (mean and log-std of ``z``), decoder on ``[z, s, a]``; ``goal_dim``: the
    subgoal's size (default ``obs_dim``)."""
    goal = goal_dim or obs_dim
    encoder = mlp(batch, goal + obs_dim + act_dim, hidden, 2 * latent)
    prior = mlp(batch, obs_dim + act_dim, hidden, 2 * latent)
    decoder = mlp(batch, latent + obs_dim + act_dim, hidden, goal)
    return TRAIN * (encoder + prior + decoder)


def policy_act(rows: int, obs_dim: int, act_dim: int, hidden: Sequence[int]) -> int:
    """The IQL actor's mean action for ``rows`` observations (an evaluation's env step)."""
    return mlp(rows, obs_dim, hidden, act_dim)


def paper_row(transitions: int = 1_000_000, obs_dim: int = 11, act_dim: int = 3) -> list[dict[str, int | str]]:
    """The stages of a paper-budget Table 1 row (``spot run --methods oracle,mr,pt,spot --seeds 0,1,2
    budget=paper variant=paper``) on a locomotion dataset of ``transitions`` rows: per stage its
    ``steps`` (program steps, or host calls where the host drives each), ``width`` (runs vmapped
    in one program) and ``flops`` (all of the stage). The sizes are budget paper's (Table 5, 6):
    PT 1 layer of 256 dims, MR 256-256, 500 queries of 100 steps (all trained on, the last 50 held
    out too: ``labels.eval_split=pt_subset``; a held-out evaluation every 10 steps:
    ``reward.eval_epochs=5``), batch 256, 10k steps; CVAE
    32-64-32, latent 16, batch 256, 100k steps; PT relabelling in sliding windows of 25 at 256
    windows a call, MR at 6,400 rows a call; IQL 256-256, batch 256, order sequential, 1M updates
    for 12 runs (SPOT reuses PT's reward models and relabelling). The evaluation is env steps, not
    FLOPs: see docs/benchmarks.md."""
    pairs, length, held_out, evals = 256, 100, 50, 1000
    hidden, width, seeds = (256, 256), 256, 3
    pt_segment = pt_forward(length, obs_dim, act_dim, width, 1, width)
    mr_segment = mlp(length, obs_dim + act_dim, hidden, 1)
    pt_window = pt_forward(25, obs_dim, act_dim, width, 1, width, last_only=True)
    return [
        {
            "stage": "pt",
            "steps": 10_000,
            "width": seeds,
            "flops": seeds * (10_000 * pt_train_step(pairs, length, obs_dim, act_dim, width, 1, width))
            + seeds * evals * 2 * held_out * pt_segment,
        },
        {
            "stage": "mr",
            "steps": 10_000,
            "width": seeds,
            "flops": seeds * (10_000 * mr_train_step(pairs, length, obs_dim, act_dim, hidden))
            + seeds * evals * 2 * held_out * mr_segment,
        },
        {
            "stage": "cvae",
            "steps": 100_000,
            "width": seeds,
            "flops": seeds * 100_000 * cvae_step(256, obs_dim, act_dim, 16, (32, 64, 32)),
        },
        {
            "stage": "relabel",
            "steps": seeds * (-(-transitions // 256) + -(-transitions // 6400)),
            "width": 1,
            "flops": seeds * transitions * (pt_window + mlp(1, obs_dim + act_dim, hidden, 1)),
        },
        {
            "stage": "iql",
            "steps": 1_000_000,
            "width": 12,
            "flops": 12 * 1_000_000 * iql_update(obs_dim, act_dim, hidden, 256, "sequential"),
        },
    ]
