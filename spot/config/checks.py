"""Rules between fields, checked whenever a config is resolved or replaced (so `spot sweep` rejects
a bad trial before launch), and the memory bound: a lower bound of the bytes each training stage
allocates, refused when it exceeds this machine's memory.
"""

from __future__ import annotations

import functools

from spot import SpotError
from spot.config.experiment import ExperimentConfig
from spot.config.presets import suite_of
from spot.config.schema import HPLConfig


def _rule(ok: bool, message: str) -> None:
    if not ok:
        raise SpotError(f"config: {message}")


def check(cfg: ExperimentConfig) -> ExperimentConfig:
    """Rules between fields, checked when a config is resolved (so `spot sweep` rejects a bad
    trial before launch). Returns ``cfg``; raises :class:`spot.SpotError` naming the keys."""
    kind = cfg.reward.kind
    _rule(bool(cfg.tracking.experiment.strip()), "tracking.experiment is empty; expected an MLflow experiment name")
    _rule(
        cfg.shaping.kind == "none" or kind == "pt",
        f"shaping.kind={cfg.shaping.kind!r} needs reward.kind=pt (subgoals come from PT attention); "
        f"got reward.kind={kind!r}",
    )
    _rule(
        kind == "none" or cfg.labels.source != "human" or bool(cfg.labels.path),
        "labels.source=human needs labels.path (a folder of PT label files; labels.source=auto uses the files "
        "shipped with spot when the dataset is the real file they index)",
    )
    _rule(
        not cfg.shaping.state_action or cfg.shaping.kind in ("cosine", "constant", "none"),
        f"shaping.state_action=true is implemented for shaping.kind cosine (and its constant control); got "
        f"shaping.kind={cfg.shaping.kind!r}",
    )
    _rule(
        cfg.cvae.schedule == "offline" or cfg.subgoal.source == "attention",
        "cvae.schedule=online trains on the attention subgoals of each minibatch; the control "
        "subgoal.source=random needs cvae.schedule=offline",
    )
    _rule(
        cfg.data.size != "paper-fast" or suite_of(cfg.data.name) in (None, "locomotion"),
        f"data.size=paper-fast is a size of the locomotion recipes (hopper-*, walker2d-*); "
        f"data.name={cfg.data.name!r} is built at tiny, small or paper",
    )
    _rule(
        kind != "hpl" or cfg.labels.segment_length <= cfg.hpl.seq_len,
        f"labels.segment_length={cfg.labels.segment_length} exceeds hpl.seq_len={cfg.hpl.seq_len}: "
        f"HPL's hindsight encoder sees at most hpl.seq_len steps",
    )
    _check_shapes(cfg)
    check_memory(cfg)
    return cfg


def _check_shapes(cfg: ExperimentConfig) -> None:
    """Model shapes that cannot work: attention heads that do not divide the width, a held-out
    split that leaves no training query."""
    kind = cfg.reward.kind
    for stage, used in (("pt", kind == "pt"), ("hpl", kind == "hpl")):
        width, heads = getattr(cfg, stage).embd_dim, getattr(cfg, stage).n_head
        _rule(
            not used or width % heads == 0,
            f"{stage}.embd_dim={width} is not divisible by {stage}.n_head={heads}; expected a width that splits "
            f"into equal heads (a multiple of {stage}.n_head)",
        )
    lc, q = cfg.labels, cfg.labels.num_queries
    n_eval = max(round(lc.eval_fraction * q), 1) if lc.eval_fraction > 0 else 0
    _rule(
        kind == "none" or lc.source != "script" or lc.eval_split != "holdout" or n_eval < q,
        f"labels.eval_fraction={lc.eval_fraction} of labels.num_queries={q} holds out {n_eval} queries and leaves "
        f"none for training; expected more queries or labels.eval_fraction=0",
    )


# --------------------------------------------------------------------------- memory before allocating
def _mlp(hidden: tuple[int, ...], d_in: int = 1, d_out: int = 1) -> int:
    """Parameters of an MLP ``d_in -> hidden -> d_out`` (weights and biases)."""
    sizes = (d_in, *hidden, d_out)
    return sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))


def _micro_batch(batch_size: int, micro: int = 64) -> int:
    """Pairs per gradient-accumulation micro-batch of the MR/PT trainer (the rule of
    :func:`spot.reward.update.micro_batches`, which this layer cannot import): the activations a
    step keeps are one micro-batch's."""
    n = max(1, batch_size // micro)
    while batch_size % n:
        n -= 1
    return batch_size // n


def _transformer(width: int, layers: int, positions: int) -> int:
    """Parameters of a GPT-2 stack of ``layers`` blocks (attention 4 D^2, MLP 8 D^2) and a
    position/timestep table, weights only."""
    return layers * 12 * width * width + positions * width


def memory_needs(cfg: ExperimentConfig) -> dict[str, tuple[int, str]]:
    """A lower bound of the bytes each training stage of ``cfg`` allocates for its main arrays,
    with the keys that size them: ``{stage: (bytes, "key=value, ...")}``.

    Counted: float32 parameters with Adam's two moments (x3), and the largest activations a
    gradient step keeps (attention weights ``batch x heads x tokens^2``, hidden layers ``batch x
    width``). Input and output sizes count as 1 and the dataset is not counted, so every stage
    needs at least this much; the stages run one after another, so a run needs at least the
    largest."""
    kind, iql, out = cfg.reward.kind, cfg.iql, {}
    act = 2 if cfg.pt.dtype == "bfloat16" else 4
    nets = 4 * _mlp(iql.hidden)  # actor, two critics, value (+ two target critics, not counted)
    rows = iql.batch_size + (2 * cfg.ipl.feedback_batch * cfg.ipl.subsample if kind == "ipl" else 0)
    out["policy"] = (
        12 * nets + 4 * 4 * rows * sum(iql.hidden),
        f"iql.hidden={iql.hidden}, iql.batch_size={iql.batch_size}",
    )
    tokens, pairs = 2 * cfg.labels.segment_length, 2 * _micro_batch(cfg.reward.batch_size)
    if kind == "pt":
        pt = cfg.pt
        params = _transformer(pt.embd_dim, pt.n_layer, pt.max_timestep + 1) + pt.embd_dim * (2 * pt.pref_attn_dim + 1)
        # per block at least the queries of the last (the state tokens): heads x T x 2T weights, T x 4D MLP
        attn = pt.n_layer * pairs * (pt.n_head * tokens * tokens // 2 + tokens // 2 * 4 * pt.embd_dim) * act
        out["reward"] = (
            12 * params + attn,
            f"pt.embd_dim={pt.embd_dim}, pt.n_layer={pt.n_layer}, pt.n_head={pt.n_head}, pt.max_timestep="
            f"{pt.max_timestep}, reward.batch_size={cfg.reward.batch_size}, labels.segment_length="
            f"{cfg.labels.segment_length}",
        )
        window = 2 * cfg.relabel.window  # tokens; sliding computes one query in the last block
        queries = window // 2 if cfg.relabel.mode == "chunked" else 1
        out["relabel"] = (
            4 * params + cfg.relabel.batch_size * pt.n_head * queries * window * act,
            f"relabel.batch_size={cfg.relabel.batch_size}, relabel.window={cfg.relabel.window}, pt.n_head={pt.n_head}",
        )
    if kind == "mr":
        out["reward"] = (
            12 * _mlp(cfg.mr.hidden) + 4 * pairs * cfg.labels.segment_length * sum(cfg.mr.hidden),
            f"mr.hidden={cfg.mr.hidden}, reward.batch_size={cfg.reward.batch_size}, "
            f"labels.segment_length={cfg.labels.segment_length}",
        )
    if kind == "pt" and (cfg.shaping.kind != "none" or cfg.subgoal.diagnostics):
        cv = cfg.cvae
        out["cvae"] = (
            12 * 3 * _mlp(cv.hidden) + 4 * 3 * cv.batch_size * sum(cv.hidden),
            f"cvae.hidden={cv.hidden}, cvae.batch_size={cv.batch_size}",
        )
    if kind == "hpl":
        out["reward"] = _hpl_needs(cfg.hpl)
    return out


def _hpl_needs(h: HPLConfig) -> tuple[int, str]:
    z = h.latent_groups * h.latent_classes
    params = (
        _transformer(h.embd_dim, h.n_layer, h.seq_len)
        + _mlp(h.decoder_hidden, h.decoder_embd)
        + _mlp(h.prior_hidden, 1, z)
        + _mlp(h.reward_hidden, z + 1)
    )
    acts = h.n_layer * h.vae_batch * (h.n_head * h.seq_len * h.seq_len + h.seq_len * 4 * h.embd_dim)
    acts += h.prior_samples * h.extra_batch * sum(h.reward_hidden)
    return (
        12 * params + 4 * acts,
        f"hpl.embd_dim={h.embd_dim}, hpl.n_layer={h.n_layer}, hpl.seq_len={h.seq_len}, hpl.vae_batch={h.vae_batch}, "
        f"hpl.prior_samples={h.prior_samples}, hpl.extra_batch={h.extra_batch}",
    )


@functools.cache
def memory_bytes() -> int:
    """This machine's physical memory (not what is free now: a check that depended on other
    processes' use would refuse a sweep's later trials while its earlier ones run)."""
    import psutil

    return int(psutil.virtual_memory().total)


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"


def check_memory(cfg: ExperimentConfig, available: int | None = None) -> None:
    """Refuse a config whose largest stage (:func:`memory_needs`, a lower bound) needs more than
    ``available`` bytes (default :func:`memory_bytes`), naming the stage and the keys that size it."""
    available = memory_bytes() if available is None else available
    stage, (need, keys) = max(memory_needs(cfg).items(), key=lambda item: item[1][0])
    _rule(
        need <= available,
        f"the {stage} stage needs at least {_gib(need)} for its parameters and activations ({keys}), more than "
        f"this machine's {_gib(available)} of memory; expected smaller sizes",
    )
