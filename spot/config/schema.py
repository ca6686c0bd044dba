"""The config schema, part one: the field helper :func:`F` and the sections of a run's data, its
preference labels and its preference learners (reward models MR, PT and HPL, relabelling, IPL).

One frozen dataclass per section; every field carries ``help`` text and, where it applies,
``choices`` or a numeric ``range``, which :mod:`spot.config.keys` checks. The other sections and
:class:`~spot.config.experiment.ExperimentConfig`, which composes them all, are in
:mod:`spot.config.experiment`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


def F(
    default: Any, help: str, *, choices: tuple | None = None, range: tuple[float | None, float | None] | None = None
) -> Any:  # noqa: A002
    """A documented config field."""
    meta = {"help": help, "choices": choices, "range": range}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (configs are frozen)")
    return field(default=default, metadata=meta)


MAX_LAYERS = 64
"""Most hidden layers a ``*.hidden`` tuple (and ``pt.n_layer``, ``hpl.n_layer``) may have: each
layer is traced and compiled on its own, so a tuple of thousands compiles for hours."""


# --------------------------------------------------------------------------- stages
@dataclass(frozen=True)
class DataConfig:
    name: str = F(
        "hopper-medium-replay",
        "registry name (see `spot data list`) or path to a D4RL/robomimic hdf5 file or a Minari dataset id",
    )
    size: str = F(
        "small",
        "size of a locally built dataset; paper-fast (locomotion only) = paper's rows and SAC stop targets "
        "with a SAC ~4x cheaper per step on CPU (128x128, batch 128, lr 1e-3; docs/datasets.md)",
        choices=("tiny", "small", "paper", "paper-fast"),
    )
    build_seed: int = F(0, "seed of the local recipe that builds the dataset", range=(0, None))
    source: str = F(
        "auto",
        "'recipe' builds locally, 'file' reads data.name as a file; 'auto' picks file if it exists",
        choices=("auto", "recipe", "file"),
    )


@dataclass(frozen=True)
class LabelsConfig:
    source: str = F(
        "script",
        "'script' = scripted teacher on true reward; 'human' = PT human label files in labels.path; 'auto' = the "
        "PT human label files shipped with spot when the "
        "dataset is the real D4RL/robomimic file they index (spot.data.human_labels), the scripted teacher "
        "otherwise",
        choices=("script", "human", "auto"),
    )
    path: str = F("", "folder with PT label files (indices_num*, indices_2_num*, label_human); for source=human")
    num_queries: int = F(500, "number of preference queries (pairs of segments)", range=(1, None))
    query_counts: str = F(
        "budget",
        "where labels.num_queries comes from: budget = the budget preset (or the default 500); pt = the PT "
        "README / authors' scripts per dataset (100 for *-medium-expert and robomimic ph, 500 for *-medium-replay "
        "and robomimic mh; other datasets keep the budget's), unless labels.num_queries is set in the YAML file or "
        "an override",
        choices=("budget", "pt"),
    )
    segment_length: int = F(100, "segment (query) length H", range=(2, None))
    teacher: str = F(
        "sum",
        "scripted teacher score: undiscounted sum or discounted sum of true reward",
        choices=("sum", "discounted"),
    )
    score: str = F(
        "reward",
        "per-step reward the scripted teacher sums: 'reward' = the dataset's reward; 'dense' = its dense reward "
        "infos/dense_reward (robosuite's staged reach/grasp/lift/hover reward, recorded by the robosuite recipe; "
        "the sparse success reward makes nearly every pair a tie)",
        choices=("reward", "dense"),
    )
    discount: float = F(0.99, "discount of the 'discounted' teacher", range=(0.0, 1.0))
    tie_threshold: float = F(-1.0, "|S1 - S2| <= threshold gives y = 0.5; negative disables ties (PT's MuJoCo teacher)")
    mistake_rate: float = F(0.0, "probability that the scripted teacher flips a label", range=(0.0, 1.0))
    allow_cross_episode: bool = F(False, "allow scripted segments to cross episode ends (PT human files do)")
    eval_fraction: float = F(0.1, "fraction of queries the reward model is evaluated on", range=(0.0, 0.9))
    eval_split: str = F(
        "holdout",
        "reward-model (MR, PT, HPL) and IPL queries: holdout = train on a random (1 - labels.eval_fraction), "
        "evaluate on the disjoint rest; pt_subset = train on all N queries, evaluate on the last eval_fraction of "
        "them (overlapping the training set, as the PT repo does)",
        choices=("holdout", "pt_subset"),
    )
    seed: int = F(42, "seed of query sampling (PT repo: data_seed 42), fixed across run seeds", range=(0, None))


@dataclass(frozen=True)
class PTConfig:
    embd_dim: int = F(256, "transformer embedding size", range=(8, None))
    n_layer: int = F(1, "causal transformer layers", range=(1, MAX_LAYERS))
    n_head: int = F(4, "attention heads", range=(1, None))
    dropout: float = F(0.1, "dropout on embeddings, attention and residuals", range=(0.0, 0.9))
    pref_attn_dim: int = F(256, "query/key size of the preference attention layer", range=(1, None))
    max_timestep: int = F(1000, "size of the learned timestep embedding table - 1", range=(1, None))
    lr: float = F(1e-4, "AdamW learning rate (after warmup)", range=(0.0, 1.0))
    weight_decay: float = F(1e-4, "AdamW weight decay", range=(0.0, 1.0))
    warmup_steps: int = F(500, "linear warmup steps (Table 5: 500)", range=(0, None))
    warmup_fraction: float = F(
        0.0,
        "if > 0, the warmup lasts this fraction of reward.steps instead of pt.warmup_steps (PT repo: 0.1)",
        range=(0.0, 1.0),
    )
    schedule: str = F(
        "warmup_constant",
        "learning-rate schedule: warmup_constant = linear 0 -> lr over the warmup, then lr (Table 5: lr 1e-4, "
        "warmup); warmup_cosine = lr -> pt.peak_factor*lr over the warmup, then cosine back to lr at reward.steps "
        "(PT repo: optax warmup_cosine_decay_schedule)",
        choices=("warmup_constant", "warmup_cosine"),
    )
    peak_factor: float = F(
        10.0, "peak learning rate / lr of the warmup_cosine schedule (PT repo: 10)", range=(1.0, None)
    )
    b2: float = F(0.99, "AdamW beta2 (Table 5: 0.99; PT repo: optax's default 0.999)", range=(0.0, 1.0))
    dtype: str = F(
        "float32",
        "compute dtype of the transformer matmuls (bfloat16 = mixed precision; params stay float32)",
        choices=("float32", "bfloat16"),
    )


@dataclass(frozen=True)
class MRConfig:
    hidden: tuple[int, ...] = F((256, 256), "MLP hidden sizes of r(s, a)")
    lr: float = F(3e-4, "Adam learning rate", range=(0.0, 1.0))


@dataclass(frozen=True)
class RewardConfig:
    kind: str = F(
        "pt",
        "reward model: none (true reward), mr (Markovian MLP), pt (Preference Transformer), hpl (hindsight VAE + "
        "r(s,a,z), marginalised over the prior), ipl (no reward model: IPL's implicit reward)",
        choices=("none", "mr", "pt", "hpl", "ipl"),
    )
    steps: int = F(10_000, "reward-model gradient steps (reward.length=steps)", range=(1, None))
    length: str = F(
        "steps",
        "how the MR/PT training length is counted: steps = reward.steps gradient steps; epochs = reward.epochs "
        "epochs as the PT repo counts them, epochs * (floor(N / reward.batch_size) + 1) steps for N training queries",
        choices=("steps", "epochs"),
    )
    epochs: int = F(
        10_000, "MR/PT epochs for reward.length=epochs (PT repo / authors' scripts: 10000)", range=(1, None)
    )
    batch_size: int = F(256, "preference pairs per step", range=(1, None))
    clip_action: float = F(
        0.0,
        "MR/PT training segments' actions clipped to +-clip_action; 0 = no clipping (PT repo: 0.999)",
        range=(0.0, 1.0),
    )
    eval_every: int = F(100, "steps between held-out evaluations (best held-out loss is kept)", range=(1, None))
    eval_epochs: int = F(
        0,
        "if > 0, evaluate every eval_epochs epochs as the PT repo counts them, eval_epochs * (floor(N / "
        "reward.batch_size) + 1) steps, instead of every reward.eval_every steps (PT repo / authors: eval_period 5)",
        range=(0, None),
    )
    best_min_delta: float = F(
        0.0,
        "an evaluation is a new best checkpoint only when its held-out loss is below the best so far by more than "
        "this (PT repo / authors: flax EarlyStopping min_delta 1e-3); 0 = any lower loss",
        range=(0.0, None),
    )
    eval_initial: bool = F(
        False,
        "the untrained model's held-out loss is the first best (the PT repo's epoch-0 evaluation); it is never a "
        "checkpoint itself: when no evaluation beats it, the last parameters are kept (train_offline.py falls back "
        "to model.pkl)",
    )


@dataclass(frozen=True)
class RelabelConfig:
    mode: str = F(
        "chunked",
        "PT relabelling: 'chunked' = whole trajectory chunks in one pass (default, fast); 'sliding' = PT repo's "
        "causal window ending at t",
        choices=("chunked", "sliding"),
    )
    window: int = F(100, "chunk length (chunked) or window length (sliding; PT repo flag default 25)", range=(1, None))
    batch_size: int = F(256, "windows/chunks per forward pass", range=(1, None))
    scale: float = F(
        0.0,
        "the return range the normalisation scales to (the 1000 in relabel.normalize's formulas): 0 = the evaluation "
        "env's max episode steps, as the PT repo does (1000 locomotion, 500 robosuite and Meta-World)",
        range=(0.0, None),
    )
    normalize: str = F(
        "pt",
        "reward normalisation after relabelling: pt = r*1000/(Rmax-Rmin)+0.5 (PT repo, locomotion), iql = "
        "r*1000/(Rmax-Rmin), minmax = steps mapped to [0,1] then iql (default for mr/pt/spot on locomotion at "
        "budgets small and tiny), wiserl = r*1000/max(|Rmin|,|Rmax|,Rmax-Rmin,1) (HPL's WiseRL), none",
        choices=("pt", "iql", "wiserl", "minmax", "none"),
    )


@dataclass(frozen=True)
class IPLConfig:
    """Inverse Preference Learning (Hejna & Sadigh 2023); IQL's section supplies expectile,
    temperature, tau, discount, hidden sizes, lr, replay batch size, steps and chunk."""

    chi2_coeff: float = F(
        0.5,
        "c of the chi^2 regulariser c * E[r^2] on the implicit reward (D4RL 0.5, Meta-World 3, robomimic 4)",
        range=(0.0, None),
    )
    target_clipping: bool = F(
        True, "clip V(s') in the implicit reward to +-1/(c (1 - gamma)) (D4RL on, Meta-World off)"
    )
    feedback_batch: int = F(8, "preference pairs per update (D4RL/robomimic 8, Meta-World 16)", range=(1, None))
    subsample: int = F(
        64,
        "random contiguous window of each segment used per update (D4RL 64, Meta-World 16, robomimic ph 32)",
        range=(2, None),
    )
    use_replay: bool = F(
        True, "mix unlabelled dataset transitions into the value/regulariser/actor losses (off for Meta-World)"
    )
    value_replay_weight: float = F(0.5, "weight of replay data in the value loss", range=(0.0, 1.0))
    chi2_replay_weight: float = F(0.5, "weight of replay data in the chi^2 regulariser", range=(0.0, 1.0))
    policy_replay_weight: float = F(0.5, "weight of replay data in the actor loss", range=(0.0, 1.0))


@dataclass(frozen=True)
class HPLConfig:
    """Hindsight Preference Learning (Gao et al. 2024, WiseRL tuned gym configs)."""

    future_len: int = F(5, "k: the hindsight encoder sees steps t..t+k", range=(1, None))
    seq_len: int = F(100, "length of unlabelled segments for the VAE", range=(2, None))
    latent_groups: int = F(8, "discrete latent: number of one-hot categorical groups", range=(1, None))
    latent_classes: int = F(16, "discrete latent: classes per group (z_dim = groups x classes)", range=(2, None))
    embd_dim: int = F(256, "hindsight encoder (non-causal GPT) embedding size", range=(8, None))
    n_layer: int = F(3, "hindsight encoder layers", range=(1, MAX_LAYERS))
    n_head: int = F(4, "hindsight encoder heads", range=(1, None))
    dropout: float = F(0.1, "hindsight encoder dropout", range=(0.0, 0.9))
    decoder_hidden: tuple[int, ...] = F((512, 512), "decoder MLP hidden sizes")
    decoder_embd: int = F(64, "decoder input embedding size", range=(1, None))
    prior_hidden: tuple[int, ...] = F((512, 512), "prior p(z|s,a) MLP hidden sizes")
    reward_hidden: tuple[int, ...] = F((256, 256, 256), "reward r(s,a,z) MLP hidden sizes")
    reward_sigmoid: bool = F(True, "sigmoid on the reward output (tuned configs)")
    vae_steps: int = F(250_000, "VAE gradient steps", range=(1, None))
    vae_batch: int = F(64, "unlabelled segments per VAE step", range=(1, None))
    reward_steps: int = F(100_000, "reward-model gradient steps", range=(1, None))
    reward_batch: int = F(8, "preference pairs per reward step", range=(1, None))
    extra_batch: int = F(512, "unlabelled transitions per step for the prior-latent regulariser", range=(1, None))
    kl_coef: float = F(1.0, "KL weight", range=(0.0, None))
    kl_balance: float = F(0.8, "KL balancing alpha: alpha KL(sg(q)||p) + (1-alpha) KL(q||sg(p))", range=(0.0, 1.0))
    reg_coef: float = F(
        1e-4, "Huber regulariser of r(s,a,z_prior) toward 0 (hopper 1e-4, walker2d 0)", range=(0.0, None)
    )
    prior_samples: int = F(20, "prior samples averaged when relabelling", range=(1, None))
    lr: float = F(3e-4, "Adam learning rate (VAE and reward)", range=(0.0, 1.0))
    chunk: int = F(
        500,
        "gradient steps per jitted lax.scan chunk (each phase does exactly its steps: the last chunk is shorter when "
        "they are not a multiple)",
        range=(1, None),
    )
