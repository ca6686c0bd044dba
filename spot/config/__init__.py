"""Run configuration: one frozen dataclass per stage, composed into :class:`ExperimentConfig`.

Resolution order (later wins): dataclass defaults (the paper's values) < method preset
(``method=spot`` etc.) < budget preset (``budget=small`` etc.) < suite preset (what the reference
implementations change for Meta-World / robomimic, chosen by ``data.name``) < variant preset
(``variant=paper|authors``, docs/fidelity.md) < YAML file < ``a.b=value`` overrides. ``method`` and
``budget`` themselves may be given in the YAML file or as overrides.

Every field carries ``help`` text and, where it applies, ``choices`` or a numeric ``range``;
:func:`resolve` validates everything and raises :class:`spot.SpotError` with the dotted key,
the bad value, what was expected and (for unknown keys) the nearest valid keys.
Configs round-trip through a flat ``{"a.b": value}`` dict (:func:`to_flat` / :func:`from_flat`),
which is what MLflow logs as params.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from spot import SpotError


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
class SubgoalConfig:
    diagnostics: bool = F(
        True,
        "in PT runs without shaping, still extract subgoals and train the CVAE to log the Fig. 2 extrapolation-error "
        "diagnostics (the CVAE is cached and shared with SPOT runs of the same seed)",
    )
    top_k: float = F(10.0, "K of the top-K% attention filter, eq. 6", range=(0.0, 100.0))
    group: str = F(
        "top",
        "percentile group (Table 2): top = top K%, top_next = top K-2K%, bottom_next = bottom K-2K%, bottom = bottom "
        "K%",
        choices=("top", "top_next", "bottom_next", "bottom"),
    )
    reward_filter: bool = F(True, "also require r_t >= segment mean (eq. 5); off = ablation")
    filter_groups: str = F(
        "top",
        "groups the reward filter applies to: top = the top group only, the other Table 2 groups by attention alone "
        "(the authors' code, which produced Table 2); all = every group (eq. 5 read literally)",
        choices=("top", "all"),
    )
    weight: str = F(
        "column_mean",
        "per-step attention weight w_t from the preference attention A (softmax over keys): column_mean = w_j = "
        "mean_t A_tj (the weight PT's logit puts on r_j, eq. 3); diagonal = w_t = A_tt (the authors' code)",
        choices=("column_mean", "diagonal"),
    )
    filter_on: str = F(
        "r_hat",
        "per-step value the reward filter compares with its segment mean: r_hat = PT's per-step reward (eq. 5); z = "
        "the attention-weighted z_t = sum_j A_tj r_j (the authors' code)",
        choices=("r_hat", "z"),
    )
    last_step: bool = F(False, "the last step of every preferred segment is always a subgoal (the authors' code)")
    triplets: str = F(
        "next_subgoal",
        "CVAE triplets: next_subgoal = every step paired with the first subgoal at or after it; interval = "
        "subgoal.interval_draws uniform draws from each interval [g_(i-1), g_i) (g_0 = segment start) paired with "
        "g_i, so a subgoal step maps to the next subgoal (the authors' code, one draw per interval per "
        "reward-model step)",
        choices=("next_subgoal", "interval"),
    )
    source: str = F(
        "attention",
        "where the CVAE's training subgoals come from: attention = the attention subgoals of eq. 5-6; random = the "
        "same number of dataset states drawn uniformly at random (a control: does the gain come from attention "
        "subgoals?)",
        choices=("attention", "random"),
    )
    interval_draws: int = F(
        10,
        "draws per interval for subgoal.triplets=interval (the CVAE trains on this fixed set; the authors redraw one "
        "per interval at every reward-model step)",
        range=(1, None),
    )
    selection: str = F(
        "quantile",
        "how a group's attention criterion picks steps: quantile = per-segment linear quantiles q(p) of w (top: w >= "
        "q(1 - K%), bottom: w <= q(K%), ...), every step that passes; authors = the authors' code (SGPbrl a5b03df): "
        "thresholds are sorted weights at rank int(p * T) (bottom: w <= sort(w)[int(K% T)]), at most int(K% T) steps "
        "(top: T - int((1 - K%) T)) pass, the first in time, and only a group that selects fewer starts its first "
        "interval at step 0 (their padding with index 0); one that selects them all draws no triplet before its "
        "first subgoal",
        choices=("quantile", "authors"),
    )


@dataclass(frozen=True)
class CVAEConfig:
    latent_dim: int = F(16, "latent size (not printed in the paper's Table 6)", range=(1, None))
    hidden: tuple[int, ...] = F((32, 64, 32), "encoder/prior/decoder hidden sizes (Table 6)")
    lr: float = F(1e-4, "Adam learning rate (Table 6)", range=(0.0, 1.0))
    batch_size: int = F(256, "triplets per step", range=(1, None))
    steps: int = F(100_000, "gradient steps (Table 6)", range=(1, None))
    beta: float = F(1.0, "KL weight beta (Table 6)", range=(0.0, None))
    loss: str = F(
        "mse_cos",
        "mse = eq. 7 only; mse_cos = eq. 7 + cosine term (Table 7); authors = the authors' code: per-dimension MSE - "
        "[mean((cos+1)/2) + 0.1 var(cos)] + beta * KL averaged over latent dimensions",
        choices=("mse", "mse_cos", "authors"),
    )
    cos_sign: str = F(
        "minus",
        "sign of the cosine term: minus = the cosine rewards a subgoal pointing along the target (mse_cos: + (1 - "
        "cos)/2, the intended eq. 8; authors: MSE - [...], SGPbrl a5b03df); plus = as eq. 8 is printed (mse_cos: + "
        "(1 + cos)/2; authors: MSE + [...], SGPbrl b6d94e2, the commit the experiments ran)",
        choices=("minus", "plus"),
    )
    log_std_clip: bool = F(
        True, "clip the encoder's and prior's log-std to [-5, 2]; false = unclipped (the authors' CVAE)"
    )
    holdout: float = F(
        0.1,
        "fraction of the preferred segments whose triplets the offline CVAE does not train on (they give the "
        "cvae/heldout_* metrics); 0 = train on every triplet (the paper; the online CVAE always does)",
        range=(0.0, 0.9),
    )
    inputs: str = F(
        "zscore",
        "states and subgoals fed to the CVAE: zscore = standardised with the dataset's observation mean and std; raw "
        "= as recorded (the authors' code)",
        choices=("zscore", "raw"),
    )
    schedule: str = F(
        "offline",
        "when the CVAE trains: offline = after the reward model, on the subgoals of its best checkpoint over all "
        "training queries (no dropout), cvae.steps steps of cvae.batch_size triplets; online = during reward "
        "learning (the authors' code): one step per reward-model step on the triplets of that step's minibatch, "
        "extracted from the training forward pass (dropout on), cvae.steps and cvae.batch_size unused; the CVAE "
        "is then part of the reward stage's cache entry",
        choices=("offline", "online"),
    )


@dataclass(frozen=True)
class ShapingConfig:
    kind: str = F(
        "none",
        "shaping term: none, cosine (eq. 11-12), neg_distance, potential; constant = a control: every transition gets "
        "the dataset mean of the cosine term (a survival bonus of the same mean)",
        choices=("none", "cosine", "neg_distance", "potential", "constant"),
    )
    weight: float = F(1.0, "lambda of eq. 13", range=(-1.0, 1.0))
    subgoal: str = F("mean", "g_hat from the prior mean or a prior sample", choices=("mean", "sample"))
    potential_sign: str = F(
        "neg",
        "potential of the potential-based term (Table 3): neg = Phi(x) = -||x - g_hat|| (higher near the subgoal); "
        "pos = +||x - g_hat|| (the authors' code, which produced Table 3: its lambda axis is the negative of "
        "neg's)",
        choices=("neg", "pos"),
    )
    potential_terminal: bool = F(
        True, "Phi(s') = 0 where the transition terminates (Ng et al.); the authors' code does not mask"
    )
    state_action: bool = F(
        False,
        "subgoals are a state and an action: the CVAE decodes (g_s, g_a) and the cosine term is (cos(s, g_s) + 1)/2 + "
        "(cos(a, g_a) + 1)/2 on the current s, a, in [0, 2] (the authors' state_action option); false = the state-only "
        "cosine on s' (eq. 11-12). Needs shaping.kind cosine, constant or none",
    )


IQL_ORDERS = ("parallel", "sequential")  # IQLConfig.order; spot.policy.iql explains both


@dataclass(frozen=True)
class IQLConfig:
    expectile: float = F(0.7, "expectile tau of the value loss", range=(0.0, 1.0))
    temperature: float = F(3.0, "AWR inverse temperature beta", range=(0.0, None))
    tau: float = F(0.005, "target-network Polyak rate", range=(0.0, 1.0))
    discount: float = F(0.99, "discount gamma", range=(0.0, 1.0))
    hidden: tuple[int, ...] = F((256, 256), "hidden sizes of actor, critics and value")
    lr: float = F(3e-4, "Adam learning rate (actor uses a cosine schedule)", range=(0.0, 1.0))
    batch_size: int = F(256, "transitions per update", range=(1, None))
    steps: int = F(1_000_000, "gradient updates", range=(1, None))
    chunk: int = F(
        1000,
        "updates per jitted lax.scan chunk (a run does exactly iql.steps: the last chunk is shorter when iql.steps is "
        "not a multiple)",
        range=(1, None),
    )
    actor_std: str = F(
        "state_independent",
        "actor log-std: state_independent = one learned vector (IQL reference); state_dependent = a linear head on "
        "the actor's trunk (HPL's WiseRL IQL)",
        choices=("state_independent", "state_dependent"),
    )
    log_std_min: float = F(
        -5.0,
        "lower clip of the actor's log-std (IQL reference -5; WiseRL HPL -7); the upper clip is 2",
        range=(-20.0, 2.0),
    )
    actor_dist: str = F(
        "gaussian",
        "actor distribution: gaussian = N(tanh(MLP(s)), sigma) without squash correction (IQL reference); "
        "tanh_gaussian = tanh-squashed N(MLP(s), sigma), log-prob with the tanh correction, action tanh(mean) "
        "(WiseRL HPL); deterministic = the action tanh(MLP(s)) regressed on the data's by the AWR-weighted squared "
        "error, -log pi read as sum_i (mean_i - a_i)^2 (CORL's and Uni-RLHF's IQL on hopper-medium-replay; the "
        "log-std vector stays in the parameters, unused)",
        choices=("gaussian", "tanh_gaussian", "deterministic"),
    )
    actor_dropout: float = F(
        0.0,
        "dropout after each hidden layer of the actor while training (IQL, IPL); none when acting (PT repo "
        "adroit/robomimic configs, IPL robomimic: 0.1)",
        range=(0.0, 0.9),
    )
    clip_action: float = F(
        0.0,
        "dataset actions the policy (IQL, IPL) trains on clipped to +-clip_action; 0 = no clipping (IQL "
        "D4RLDataset: 1 - 1e-5)",
        range=(0.0, 1.0),
    )
    order: str = F(
        "parallel",
        "value network the actor and critics see: 'parallel' the one at the start of the update (CORL, unifloral; "
        "faster), 'sequential' the just-updated one (ikostrikov/PT repo)",
        choices=IQL_ORDERS,
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


@dataclass(frozen=True)
class EvalConfig:
    every: int = F(5000, "IQL updates between evaluations", range=(1, None))
    episodes: int = F(
        10, "evaluation episodes (deterministic policy) at every evaluation (the paper's 10)", range=(1, None)
    )
    final_episodes: int = F(
        0,
        "episodes of the evaluation after the last update, which gives eval/score_final (and counts for "
        "eval/score_best); 0 = eval.episodes. More episodes here narrow the final score's episode noise at "
        "little cost: the episodes run in lockstep, one batched policy call per step",
        range=(0, None),
    )
    max_steps: int = F(
        0,
        "cut every evaluation episode after this many steps; 0 = the env's own horizon (the paper's "
        "protocol: 1000 locomotion, 500 Meta-World and robosuite). Budget tiny sets 100 so that smoke "
        "checks do not spend most of their time in robosuite's 15-20 ms steps; a cut episode's score is "
        "not comparable with a full one's",
        range=(0, None),
    )


@dataclass(frozen=True)
class TrackingConfig:
    uri: str = F("", "MLflow tracking URI; empty = local store ./mlruns in the working folder")
    experiment: str = F("spot", "MLflow experiment name")
    record: str = F(
        "",
        "a folder: record the run there as files instead of logging it to MLflow (a machine without MLflow or "
        "its store); `spot results import FOLDER` logs the records into a store later; empty = MLflow",
    )


_STAGES: dict[str, type] = {
    "data": DataConfig,
    "labels": LabelsConfig,
    "reward": RewardConfig,
    "pt": PTConfig,
    "mr": MRConfig,
    "relabel": RelabelConfig,
    "subgoal": SubgoalConfig,
    "cvae": CVAEConfig,
    "shaping": ShapingConfig,
    "iql": IQLConfig,
    "ipl": IPLConfig,
    "hpl": HPLConfig,
    "eval": EvalConfig,
    "tracking": TrackingConfig,
}

METHODS = ("oracle", "mr", "pt", "ipl", "hpl", "spot")
BUDGETS = ("paper", "lab", "small", "tiny")
VARIANTS = ("spot", "paper", "authors")


@dataclass(frozen=True)
class ExperimentConfig:
    method: str = F("spot", "method preset", choices=METHODS)
    budget: str = F(
        "small",
        "budget preset: paper (the paper's sizes, for GPUs/clusters), lab (D4RL-grade local data at size paper, about "
        "15 minutes of one CPU core per run: the reproduction on 2 cores, docs/reproduction.md), small (2 CPU cores, "
        "minutes), tiny (tests)",
        choices=BUDGETS,
    )
    variant: str = F(
        "spot",
        "fidelity preset (docs/fidelity.md): spot = this package's defaults; paper = what the paper's text says, the "
        "reference code where it is silent; authors = what the authors' code (SGPbrl) does. Sets only named keys "
        "(VARIANT_PRESETS), each of which can be overridden on its own",
        choices=VARIANTS,
    )
    seed: int = F(0, "run seed (root PRNG key)", range=(0, None))
    data: DataConfig = field(default_factory=DataConfig)
    labels: LabelsConfig = field(default_factory=LabelsConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    pt: PTConfig = field(default_factory=PTConfig)
    mr: MRConfig = field(default_factory=MRConfig)
    relabel: RelabelConfig = field(default_factory=RelabelConfig)
    subgoal: SubgoalConfig = field(default_factory=SubgoalConfig)
    cvae: CVAEConfig = field(default_factory=CVAEConfig)
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    iql: IQLConfig = field(default_factory=IQLConfig)
    ipl: IPLConfig = field(default_factory=IPLConfig)
    hpl: HPLConfig = field(default_factory=HPLConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)


# --------------------------------------------------------------------------- presets
METHOD_PRESETS: dict[str, dict[str, Any]] = {
    "oracle": {"reward.kind": "none", "shaping.kind": "none", "relabel.normalize": "iql"},
    "mr": {"reward.kind": "mr", "shaping.kind": "none"},
    "pt": {"reward.kind": "pt", "shaping.kind": "none"},
    "ipl": {"reward.kind": "ipl", "shaping.kind": "none", "relabel.normalize": "none"},
    "hpl": {"reward.kind": "hpl", "shaping.kind": "none", "relabel.normalize": "wiserl"},
    "spot": {"reward.kind": "pt", "shaping.kind": "cosine", "shaping.weight": 1.0},
}

# IPL's and HPL's sizes shared by the CPU budgets (lab and small), smaller than the paper's.
_CPU_BASELINE_SIZES: dict[str, Any] = {
    "ipl.subsample": 32,
    "hpl.embd_dim": 64,
    "hpl.n_layer": 1,
    "hpl.decoder_hidden": (128, 128),
    "hpl.prior_hidden": (128, 128),
    "hpl.reward_hidden": (64, 64),
    "hpl.vae_batch": 16,
    "hpl.extra_batch": 128,
    "hpl.prior_samples": 10,
}

BUDGET_PRESETS: dict[str, dict[str, Any]] = {
    # The paper's sizes (Table 5, Table 6, IQL reference): GPU / cluster work.
    "paper": {"data.size": "paper"},
    # The reproduction on 2 CPU cores (docs/reproduction.md): the paper-size local datasets and the
    # paper's query protocol (500 queries of 100 steps; suite presets set their own counts), IQL at the
    # paper's sizes for 100k updates, about 15 minutes of one core per run (IQL ~110 updates/s on one
    # core). The updates were chosen from measured Oracle learning curves on the local
    # hopper-medium-replay (size paper): see docs/reproduction.md. Reward model and CVAE are smaller than
    # the paper's (they are computed once per seed and shared by every run that needs them).
    "lab": {
        "data.size": "paper",
        "labels.num_queries": 500,
        "labels.segment_length": 100,
        "reward.steps": 600,
        "reward.epochs": 75,  # 600 steps at 500 queries, batch 64 (8 steps per epoch)
        "reward.batch_size": 64,
        "reward.eval_every": 50,
        "pt.embd_dim": 64,
        "pt.pref_attn_dim": 64,
        "pt.n_head": 4,
        "pt.warmup_steps": 60,
        "mr.hidden": (128, 128),
        "relabel.window": 100,
        "cvae.steps": 20_000,
        "cvae.lr": 1e-3,
        "iql.steps": 100_000,
        "iql.chunk": 5000,
        "eval.every": 10_000,
        "eval.episodes": 10,
        "eval.final_episodes": 30,
        **_CPU_BASELINE_SIZES,
        "hpl.vae_steps": 5000,
        "hpl.reward_steps": 2000,
    },
    # Finishes on 2 CPU cores in minutes per run.
    "small": {
        "data.size": "small",
        "labels.num_queries": 200,
        "labels.segment_length": 50,
        "reward.steps": 300,
        "reward.epochs": 43,  # ~300 steps at 200 queries, batch 32 (7 steps per epoch)
        "reward.batch_size": 32,
        "reward.eval_every": 50,
        "pt.embd_dim": 64,
        "pt.pref_attn_dim": 64,
        "pt.n_head": 4,
        "pt.warmup_steps": 30,
        "mr.hidden": (64, 64),
        "relabel.window": 50,
        "cvae.steps": 3000,
        "cvae.lr": 1e-3,
        "iql.steps": 20_000,
        "iql.chunk": 1000,
        "eval.every": 5000,
        "eval.episodes": 5,
        **_CPU_BASELINE_SIZES,
        "hpl.seq_len": 50,
        "hpl.vae_steps": 2000,
        "hpl.reward_steps": 1000,
    },
    # Seconds: tests and smoke checks.
    "tiny": {
        "data.size": "tiny",
        "labels.num_queries": 40,
        "labels.segment_length": 20,
        "reward.steps": 20,
        "reward.epochs": 3,
        "reward.batch_size": 8,
        "reward.eval_every": 10,
        "pt.embd_dim": 16,
        "pt.pref_attn_dim": 16,
        "pt.n_head": 2,
        "pt.warmup_steps": 2,
        "mr.hidden": (16, 16),
        "relabel.window": 20,
        "relabel.batch_size": 64,
        "cvae.steps": 50,
        "cvae.batch_size": 32,
        "cvae.hidden": (16, 16),
        "iql.steps": 200,
        "iql.chunk": 100,
        "iql.hidden": (32, 32),
        "iql.batch_size": 64,
        "eval.every": 100,
        "eval.episodes": 1,
        "eval.max_steps": 100,
        "ipl.subsample": 10,
        "ipl.feedback_batch": 4,
        "hpl.seq_len": 25,
        "hpl.embd_dim": 16,
        "hpl.n_layer": 1,
        "hpl.n_head": 2,
        "hpl.latent_groups": 2,
        "hpl.latent_classes": 4,
        "hpl.decoder_hidden": (16, 16),
        "hpl.decoder_embd": 8,
        "hpl.prior_hidden": (16, 16),
        "hpl.reward_hidden": (16, 16),
        "hpl.vae_steps": 20,
        "hpl.vae_batch": 4,
        "hpl.reward_steps": 20,
        "hpl.extra_batch": 16,
        "hpl.prior_samples": 3,
        "hpl.chunk": 10,
    },
}


# The PT repo's data and reward-model protocol, shared by `paper` (the reference code where the paper is
# silent) and `authors` (SGPbrl keeps it): human labels where they exist, the per-dataset query
# counts, training on all N queries with the last 10 % as the evaluation subset, its best-checkpoint
# rule (an evaluation every 5 epochs, a new best only 1e-3 below the best so far, the untrained model's
# loss first) and its action clipping (PT reward data 0.999; IQL D4RLDataset 1 - 1e-5). The training
# length is not shared (row 15): `paper` takes Table 5's 10k steps, `authors` the PT repo's epochs.
_PT_PROTOCOL: dict[str, Any] = {
    "labels.source": "auto",
    "labels.query_counts": "pt",
    "labels.eval_split": "pt_subset",
    "reward.eval_epochs": 5,  # new_preference_reward_main.py eval_period
    "reward.best_min_delta": 1e-3,  # flax EarlyStopping(min_delta=1e-3) decides has_improved
    "reward.eval_initial": True,  # epoch 0 is evaluated, never saved
    "reward.clip_action": 0.999,
    "iql.clip_action": 1.0 - 1e-5,
}

# HPL's own IQL (WiseRL scripts/configs/hpl/tuned/*, row 41 of docs/fidelity.md) for `paper` and
# `authors` (the authors' code has no HPL; it reports HPL from the HPL authors' codebase): the actor
# choices at every budget, the sizes (batch 512, 3x256 networks) at budget paper only.
HPL_IQL_CHOICES: dict[str, Any] = {
    "iql.actor_std": "state_dependent",
    "iql.log_std_min": -7.0,
    "iql.actor_dist": "tanh_gaussian",
}
HPL_IQL_SIZES: dict[str, Any] = {"iql.batch_size": 512, "iql.hidden": (256, 256, 256)}


def variant_method_preset(variant: str, method: str, budget: str, data_name: str = "") -> dict[str, Any]:
    """What a variant changes for one method or suite only: HPL's own IQL settings; actor dropout
    0.1 on robomimic (PT repo robomimic/adroit configs, IPL robomimic configs); for `authors`, IQL
    expectile 0.7 on Meta-World for the methods their scripts run (hyperparameter_meta.sh passes
    configs/mujoco_config.py to meta_world_train_offline.py; the suite preset's 0.75 is IPL's)."""
    out: dict[str, Any] = {}
    if variant in ("paper", "authors") and method == "hpl":
        out.update(HPL_IQL_CHOICES, **(HPL_IQL_SIZES if budget == "paper" else {}))
    robomimic_file = data_name.endswith((".hdf5", ".h5")) and Path(data_name).stem.startswith("low_dim")
    if variant in ("paper", "authors") and data_name and (suite_of(data_name) == "robosuite" or robomimic_file):
        out["iql.actor_dropout"] = 0.1
    if variant == "authors" and method in ("mr", "pt", "spot") and data_name and suite_of(data_name) == "metaworld":
        out["iql.expectile"] = 0.7
    return out


# PT README / SGPbrl hyperparameter.sh query counts; robomimic: the PT label files' counts.
PT_QUERY_COUNTS = {"-medium-expert": 100, "-medium-replay": 500, "-ph": 100, "-mh": 500}


def pt_query_count(data_name: str) -> int | None:
    """The PT protocol's number of queries for a dataset name (registry name, D4RL name or file
    path), or None where it names none."""
    from spot.data import registry

    path = Path(data_name)
    if data_name.endswith((".hdf5", ".h5")):  # a file: D4RL hopper_medium_expert-v2, robomimic lift/ph/low_dim
        data_name = f"-{path.parent.name}" if path.stem.startswith("low_dim") else path.stem.replace("_", "-")
    base = registry.canonical(data_name)
    for tail, count in PT_QUERY_COUNTS.items():
        if base.endswith(tail):
            return count
    return None


# Fidelity presets (docs/fidelity.md has the sources of every entry): applied after the suite
# preset, before the YAML file. Only choices, never sizes, so they combine with every budget.
VARIANT_PRESETS: dict[str, dict[str, Any]] = {
    "spot": {},
    "paper": {
        **_PT_PROTOCOL,
        "subgoal.filter_groups": "all",  # eq. 5 states the reward criterion for the subgoal set
        "cvae.holdout": 0.0,  # §4.1.3: the CVAE trains on the triplets, none held out
        "relabel.mode": "sliding",
        "relabel.window": 25,  # paper silent: PT repo (seq_len flag 25)
        "iql.order": "sequential",  # paper silent: ikostrikov IQL (vendored by the PT repo)
    },
    # SGPbrl a5b03df, the cleaned commit, for JaxPref/PrefTransformer.py (reward model, subgoals, CVAE);
    # b6d94e2 for what a5b03df does not hold (hyperparameter.sh, train_offline.py, learner.py, critic.py).
    # b6d94e2's own PrefTransformer.py differs in its CVAE loss sign (cvae.cos_sign=plus) and its 5-seed
    # Table 1 block shapes on state and action (shaping.state_action=true): keys, not set here.
    "authors": {
        **_PT_PROTOCOL,  # the PT repo's protocol, kept by SGPbrl (hyperparameter.sh, new_preference_reward_main.py)
        "reward.length": "epochs",  # --n_epochs 10000, int(N / batch) + 1 steps per epoch
        "pt.n_layer": 3,
        "pt.n_head": 1,  # PrefTransformer.get_default_config; scripts do not override
        # the PT repo's optimiser, kept by SGPbrl: warmup 10 % of the steps to 10x lr, cosine back to lr,
        # optax.adamw's default b2 (new_preference_reward_main.py, PrefTransformer.py)
        "pt.schedule": "warmup_cosine",
        "pt.peak_factor": 10.0,
        "pt.warmup_fraction": 0.1,
        "pt.b2": 0.999,
        "subgoal.weight": "diagonal",
        "subgoal.filter_on": "z",
        "subgoal.last_step": True,
        "subgoal.triplets": "interval",
        "subgoal.selection": "authors",  # sort(w)[int(p T)] thresholds, first int(K% T) in time
        "subgoal.filter_groups": "top",
        "relabel.mode": "sliding",
        "relabel.window": 25,  # train_offline.py seq_len 25
        "shaping.potential_sign": "pos",
        "shaping.potential_terminal": False,  # critic.py potential_based
        "shaping.subgoal": "sample",  # subgoal_cvae_model.py: a prior sample (its noise from a fixed key)
        "cvae.loss": "authors",
        "cvae.inputs": "raw",  # PrefTransformer.py vae_train_step, raw batches
        "cvae.log_std_clip": False,  # subgoal_cvae_model.py: log_var unclipped
        "cvae.holdout": 0.0,  # every triplet (the online CVAE ignores it)
        "cvae.schedule": "online",  # PrefTransformer.py train: one CVAE step per PT step, that minibatch's triplets
        "iql.order": "sequential",  # learner.py: critic target uses the just-updated value network
    },
}


# Per benchmark suite, what the reference implementations change (reference/algorithms.md §1.4,
# §3.2, §4.3): applied after the budget preset, before the YAML file. Keys are (suite, method);
# method "*" applies to every method of the suite.
SUITE_PRESETS: dict[tuple[str, str], dict[str, Any]] = {
    # Meta-World (IPL's setting): segments of 25, discounted-return scripted labels without ties,
    # IQL expectile 0.75 (IPL repo's mr_iql / ipl_iql Meta-World configs), no D4RL +0.5 shift;
    # IPL: chi2 3, no target clipping, no replay data, feedback batch 16, subsample 16, 3x256.
    ("metaworld", "*"): {
        "labels.segment_length": 25,
        "labels.teacher": "discounted",
        "iql.expectile": 0.75,
        "relabel.window": 25,
        "hpl.seq_len": 25,
    },
    ("metaworld", "mr"): {"relabel.normalize": "iql"},
    ("metaworld", "pt"): {"relabel.normalize": "iql"},
    ("metaworld", "spot"): {"relabel.normalize": "iql"},
    ("metaworld", "ipl"): {
        "ipl.chi2_coeff": 3.0,
        "ipl.target_clipping": False,
        "ipl.use_replay": False,
        "ipl.feedback_batch": 16,
        "ipl.subsample": 16,
        "iql.hidden": (256, 256, 256),
    },
    # robomimic / robosuite (PT repo configs/adroit+robomimic: temperature 0.5; IPL robomimic:
    # beta 2 = temperature 0.5, chi2 4); segments of 50 (ph) or 100 (mh) follow the PT label files.
    # Scripted labels score segments with robosuite's dense staged reward and tie equal scores
    # (PT's robosuite teacher, label_type 1): the sparse reward of successful demos ties nearly all.
    ("robosuite", "*"): {
        "iql.temperature": 0.5,
        "labels.score": "dense",
        "labels.tie_threshold": 0.0,
        "labels.allow_cross_episode": True,
    },  # demos end at success (Lift: ~40 steps); PT segments cross episodes
    ("robosuite", "mr"): {"relabel.normalize": "iql"},
    ("robosuite", "pt"): {"relabel.normalize": "iql"},
    ("robosuite", "spot"): {"relabel.normalize": "iql"},
    ("robosuite", "ipl"): {"ipl.chi2_coeff": 4.0},
}
_SUITE_SEGMENT = {
    "-ph": {"labels.segment_length": 50, "ipl.subsample": 32},
    "-mh": {"labels.segment_length": 100, "ipl.subsample": 64},
}


def suite_of(data_name: str) -> str | None:
    """The registry family of a dataset name (``locomotion``, ``metaworld``, ``robosuite``), or
    None for anything else (a file path: no suite preset)."""
    from spot.data import registry

    entry = registry.REGISTRY.get(registry.canonical(data_name))
    return entry.family if entry else None


def suite_preset(data_name: str, method: str, budget: str) -> dict[str, Any]:
    """The suite preset of ``data_name`` for ``method`` (robosuite segment sizes at budgets paper and lab)."""
    suite = suite_of(data_name)
    out: dict[str, Any] = {}
    if suite is None:
        return out
    out.update(SUITE_PRESETS.get((suite, "*"), {}))
    out.update(SUITE_PRESETS.get((suite, method), {}))
    if suite == "locomotion" and budget not in ("paper", "lab") and method in ("mr", "pt", "spot"):
        # Locally built small/tiny datasets have short episodes (hopper-medium-replay small: 30 steps
        # on average), where PT's "+0.5" leaves most learned rewards negative and IQL learns to fall
        # (measured: PT score 0.88 with pt, 7.60 with minmax, oracle 7.95; docs/design.md).
        out["relabel.normalize"] = "minmax"
    if suite == "robosuite" and budget in ("paper", "lab"):
        for tail, keys in _SUITE_SEGMENT.items():
            if data_name.endswith(tail):
                out.update(keys)
    return out


# --------------------------------------------------------------------------- flat dicts
def _fields(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def valid_keys() -> list[str]:
    keys = []
    for name, _f in _fields(ExperimentConfig).items():
        if name in _STAGES:
            keys += [f"{name}.{sub}" for sub in _fields(_STAGES[name])]
        else:
            keys.append(name)
    return keys


def field_info(key: str) -> tuple[Any, dict]:
    """``(type, metadata)`` of a dotted key."""
    parts = key.split(".")
    if len(parts) == 1:
        f = _fields(ExperimentConfig)[parts[0]]
    else:
        f = _fields(_STAGES[parts[0]])[parts[1]]
    return _hints(_STAGES[parts[0]] if len(parts) > 1 else ExperimentConfig)[parts[-1]], dict(f.metadata)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """``typing.get_type_hints(cls)``, once per class: it evaluates every annotation string anew,
    ~95 % of a :func:`resolve` (13 ms of 14) before it was cached, which bounds how many trials a
    sweep can check."""
    return typing.get_type_hints(cls)


def to_flat(cfg: ExperimentConfig) -> dict[str, Any]:
    """``{"iql.steps": 1000, ...}`` for every field (MLflow params)."""
    flat: dict[str, Any] = {}
    for name in _fields(ExperimentConfig):
        value = getattr(cfg, name)
        if dataclasses.is_dataclass(value):
            for sub in _fields(type(value)):
                flat[f"{name}.{sub}"] = getattr(value, sub)
        else:
            flat[name] = value
    return flat


def from_flat(flat: dict[str, Any]) -> ExperimentConfig:
    """Inverse of :func:`to_flat`; values may be strings (as MLflow returns params)."""
    return _build({k: _coerce(k, v) for k, v in _check_keys(flat, "config").items()})


def _build(flat: dict[str, Any]) -> ExperimentConfig:
    top: dict[str, Any] = {}
    stages: dict[str, dict[str, Any]] = {s: {} for s in _STAGES}
    for key, value in flat.items():
        if "." in key:
            s, sub = key.split(".", 1)
            stages[s][sub] = value
        else:
            top[key] = value
    return ExperimentConfig(**top, **{s: _STAGES[s](**kw) for s, kw in stages.items()})


# --------------------------------------------------------------------------- validation
def _check_keys(flat: dict[str, Any], where: str) -> dict[str, Any]:
    keys = valid_keys()
    for key in flat:
        if key not in keys:
            close = difflib.get_close_matches(key, keys, n=3, cutoff=0.5)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise SpotError(f"{where}: unknown config key '{key}'{hint} (see `spot config keys`)")
    return flat


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


MAX_INT = 2**31 - 1
"""Largest integer a config value may take (seeds, steps, sizes): beyond it JAX's int32 and
PRNG seeds overflow."""


def _to_int(value: Any) -> int:
    """An exact integer from an int, an integral float or a decimal/scientific string; ValueError
    or OverflowError otherwise (bools, fractions, NaN, infinities)."""
    if isinstance(value, bool):
        raise ValueError
    if isinstance(value, float) and not value.is_integer():
        raise ValueError
    if isinstance(value, str) and "e" in value.lower():
        number = float(value)
        if not number.is_integer():
            raise ValueError
        return int(number)
    return int(value)


MAX_STR = 4096
"""Longest string value (paths, names): PATH_MAX on Linux."""
FLOAT32_MAX = 3.4028234663852886e38
"""Largest float32: JAX computes in float32, where a larger config value is already inf."""
_SHOWN = 60


def shown(value: Any) -> str:
    """``repr(value)`` for an error line, cut to about 60 characters (a value may be megabytes)."""
    text = repr(value)
    return text if len(text) <= _SHOWN else f"{text[: _SHOWN - 15]}... ({len(text)} characters)"


def _coerce_tuple(key: str, tp: Any, value: Any) -> tuple:
    inner = typing.get_args(tp)[0]
    if isinstance(value, str):
        text = value.strip().strip("()[]")
        value = [v for v in (p.strip() for p in text.split(",")) if v]
    if not isinstance(value, (list, tuple)):
        raise ValueError
    if len(value) > MAX_LAYERS:
        raise SpotError(f"config key '{key}': {len(value)} layer sizes; expected at most {MAX_LAYERS}")
    out = tuple(_to_int(v) if inner is int else inner(v) for v in value)
    if inner is int and (not out or min(out) < 1 or max(out) > MAX_INT):
        raise SpotError(
            f"config key '{key}': value {shown(value)}: expected one or more layer sizes, each 1 <= size <= {MAX_INT}"
        )
    return out


def _coerce_bool(value: Any) -> bool:
    if isinstance(value, str):
        if value.lower() in ("true", "1", "yes", "on"):
            return True
        if value.lower() in ("false", "0", "no", "off"):
            return False
        raise ValueError
    if isinstance(value, (bool, int)) and value in (0, 1):
        return bool(value)
    raise ValueError


def _coerce_float(key: str, value: Any) -> float:
    if isinstance(value, bool):
        raise ValueError
    out = float(value)
    if not math.isfinite(out):
        raise SpotError(f"config key '{key}': value {shown(value)} is not a finite number")
    if abs(out) > FLOAT32_MAX:
        raise SpotError(
            f"config key '{key}': value {shown(value)} is beyond float32 (|value| <= {FLOAT32_MAX:.4g}); "
            "JAX computes in float32, where it is inf"
        )
    return out


def _coerce_str(key: str, value: Any) -> str:
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise ValueError
    out = str(value)
    if len(out) > MAX_STR:
        raise SpotError(f"config key '{key}': a string of {len(out)} characters; expected at most {MAX_STR}")
    bad = next((c for c in out if ord(c) < 32 or ord(c) == 127), None)
    if bad is not None:
        raise SpotError(
            f"config key '{key}': value {shown(out)} holds the control character {bad!r}; expected printable text"
        )
    return out


def _coerce(key: str, value: Any) -> Any:
    """Convert ``value`` to the field's type (strings from the CLI or MLflow included) and validate."""
    tp, meta = field_info(key)
    origin = typing.get_origin(tp)
    try:
        if origin is tuple:
            out = _coerce_tuple(key, tp, value)
        elif tp is bool:
            out = _coerce_bool(value)
        elif tp is int:
            out = _to_int(value)
        elif tp is float:
            out = _coerce_float(key, value)
        elif tp is str:
            out = _coerce_str(key, value)
        else:  # pragma: no cover - every field has one of the types above
            raise TypeError(f"unsupported field type {tp}")
    except (ValueError, TypeError, OverflowError):
        expected = f"a tuple of {_type_name(typing.get_args(tp)[0])}" if origin is tuple else _type_name(tp)
        raise SpotError(f"config key '{key}': value {shown(value)} is not {expected}") from None
    choices = _REGISTERED_CHOICES[key]() if key in _REGISTERED_CHOICES else meta.get("choices")
    if choices and out not in choices:
        raise SpotError(f"config key '{key}': value {shown(out)} is not one of {', '.join(map(repr, choices))}")
    if tp is int and abs(out) > MAX_INT:
        raise SpotError(f"config key '{key}': value {shown(value)} is too large; expected at most {MAX_INT}")
    rng = meta.get("range")
    if rng is not None:
        lo, hi = rng
        if (lo is not None and out < lo) or (hi is not None and out > hi):
            raise SpotError(
                f"config key '{key}': value {out!r} is out of range; expected "
                f"{lo if lo is not None else '-inf'} <= value <= {hi if hi is not None else 'inf'}"
            )
    return out


def _flatten_yaml(data: Any, where: str, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        raise SpotError(f"{where}: expected a mapping of config keys, got {type(data).__name__}")
    flat: dict[str, Any] = {}
    for k, v in data.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten_yaml(v, where, key + "."))
        else:
            flat[key] = v
    return flat


# Public for sweep files (spot.sweep.spec), whose base/grid/zip blocks follow the same rules.
flatten_yaml = _flatten_yaml
check_keys = _check_keys


MAX_YAML_BYTES = 1 << 20
"""Largest YAML file (run config, sweep file) spot reads."""


MAX_YAML_DEPTH = 16
"""Deepest nesting of mappings and lists in a YAML file or override value (a sweep file's
``smoke: {grid: {iql: {hidden: [[64, 64]]}}}`` is 6 deep, its root mapping included). PyYAML
composes nodes recursively, so a 10,000-deep ``[[[...]]]`` (20 KB) would end in a RecursionError."""


class TooDeep(yaml.composer.ComposerError):
    """A YAML document nested deeper than :data:`MAX_YAML_DEPTH`."""


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses aliases (``*name``: an alias bomb expands a few lines into
    billions of keys), duplicate mapping keys (PyYAML silently keeps the last one) and nesting
    deeper than :data:`MAX_YAML_DEPTH`."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                f"alias '*{event.anchor}' found: spot's YAML files take no aliases; write the value out",
                event.start_mark,
            )
        if not self.check_event(yaml.MappingStartEvent, yaml.SequenceStartEvent):
            return super().compose_node(parent, index)  # a scalar: no deeper
        depth = getattr(self, "_depth", 0)
        if depth >= MAX_YAML_DEPTH:
            raise TooDeep(
                None,
                None,
                f"nested deeper than {MAX_YAML_DEPTH} levels; expected at most {MAX_YAML_DEPTH}",
                self.peek_event().start_mark,
            )
        self._depth = depth + 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth = depth

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                if isinstance(key, typing.Hashable):
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r}", key_node.start_mark
                        )
                    seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path, where: str) -> Any:
    """Parse a YAML file with :class:`StrictLoader`: at most :data:`MAX_YAML_BYTES`, UTF-8, no
    aliases, no duplicate keys. Raises SpotError starting with ``where`` (e.g. ``config file 'x'``)."""
    path = Path(path)
    if not path.is_file():
        raise SpotError(f"{where} does not exist")
    size = path.stat().st_size
    if size > MAX_YAML_BYTES:
        raise SpotError(f"{where}: {size} bytes; expected a YAML file of at most {MAX_YAML_BYTES} bytes")
    try:
        with path.open("rb") as fh:
            raw = fh.read(MAX_YAML_BYTES + 1)  # bounded: the file may grow after the stat
        if len(raw) > MAX_YAML_BYTES:
            raise SpotError(f"{where}: grew past {MAX_YAML_BYTES} bytes while read; expected a YAML file at most that")
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SpotError(f"{where}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None
    except OSError as e:
        raise SpotError(f"{where}: cannot be read ({e.strerror})") from None
    try:
        return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        raise SpotError(f"{where}: not valid YAML: {yaml_problem(e)}") from None
    except ValueError as e:  # PyYAML's int(): an integer of more than 4300 digits
        raise SpotError(f"{where}: not valid YAML: {str(e).split(';')[0]}") from None


def yaml_problem(error: yaml.YAMLError) -> str:
    """A PyYAML error on one line: the problem and where (PyYAML's own text quotes the source)."""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    context = getattr(error, "context", None)
    mark = getattr(error, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{context + ': ' if context else ''}{problem}{where}"


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML run config into a flat dict (keys checked, values not yet coerced)."""
    path = Path(path)
    data = read_yaml(path, f"config file '{path}'") or {}
    return _check_keys(_flatten_yaml(data, f"config file '{path}'"), f"config file '{path}'")


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """``["iql.steps=1000", "method=pt"]`` -> flat dict (values parsed as YAML scalars)."""
    flat: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise SpotError(f"override '{item}': expected KEY=VALUE, e.g. iql.steps=1000")
        key, text = item.split("=", 1)
        try:
            value = yaml.load(text, Loader=StrictLoader) if text.strip() else ""  # noqa: S506
        except TooDeep as e:
            raise SpotError(f"override '{key.strip()}': value {yaml_problem(e)}") from None
        except (yaml.YAMLError, ValueError):  # ValueError: an integer of more than 4300 digits
            value = text
        flat[key.strip()] = value if value is not None else ""
    return _check_keys(flat, "override")


# --------------------------------------------------------------------------- methods and cross-field rules
REWARD_KINDS: list[str] = ["none", "mr", "pt", "hpl", "ipl"]  # RewardConfig.kind; grows by register_method
_REGISTERED_CHOICES = {"method": lambda: tuple(METHOD_PRESETS), "reward.kind": lambda: tuple(REWARD_KINDS)}


def register_method(method: str, preset: dict[str, Any]) -> None:
    """Make ``method=<method>`` a valid config with ``preset`` (flat dotted keys) as its method
    preset; a new ``reward.kind`` in the preset becomes valid too. Used by
    :func:`spot.stages.register`, which adds the method's stages."""
    if method in METHOD_PRESETS:
        raise SpotError(f"method {method!r} is already registered")
    kind = preset.get("reward.kind")
    if kind is not None and kind not in REWARD_KINDS:
        REWARD_KINDS.append(kind)
    METHOD_PRESETS[method] = dict(_check_keys(preset, f"method preset {method!r}"))


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
    :func:`spot.reward.train.micro_batches`, which this layer cannot import): the activations a
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


def resolve(*layers: dict[str, Any]) -> ExperimentConfig:
    """Resolve flat layers (YAML file, overrides, ...) on top of method and budget presets."""
    user: dict[str, Any] = {}
    for layer in layers:
        user.update(_check_keys(layer, "config"))
    method = _coerce("method", user.get("method", ExperimentConfig.method))
    budget = _coerce("budget", user.get("budget", ExperimentConfig.budget))
    flat = to_flat(ExperimentConfig())
    flat.update(METHOD_PRESETS[method])
    flat.update(BUDGET_PRESETS[budget])
    data_name = str(user.get("data.name", flat["data.name"]))
    flat.update(suite_preset(data_name, method, budget))
    variant = _coerce("variant", user.get("variant", ExperimentConfig.variant))
    flat.update(VARIANT_PRESETS[variant])
    flat.update(variant_method_preset(variant, method, budget, data_name))
    counts = _coerce("labels.query_counts", user.get("labels.query_counts", flat["labels.query_counts"]))
    if counts == "pt" and pt_query_count(data_name) is not None:
        flat["labels.num_queries"] = pt_query_count(data_name)  # below the YAML file and overrides
    flat.update(user)
    flat["method"], flat["budget"], flat["variant"] = method, budget, variant
    return check(_build({k: _coerce(k, v) for k, v in flat.items()}))


def load(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> ExperimentConfig:
    """YAML file (optional) + CLI overrides -> validated :class:`ExperimentConfig`."""
    layers = [load_yaml(path)] if path else []
    layers.append(parse_overrides(overrides))
    return resolve(*layers)


def replace(cfg: ExperimentConfig, **dotted: Any) -> ExperimentConfig:
    """Copy of ``cfg`` with dotted-key changes, e.g. ``replace(cfg, **{"iql.steps": 10})``."""
    flat = to_flat(cfg)
    flat.update(_check_keys(dotted, "replace"))
    return check(_build({k: _coerce(k, v) for k, v in flat.items()}))


def to_yaml(cfg: ExperimentConfig) -> str:
    nested: dict[str, Any] = {}
    for key, value in to_flat(cfg).items():
        if isinstance(value, tuple):
            value = list(value)
        if "." in key:
            s, sub = key.split(".", 1)
            nested.setdefault(s, {})[sub] = value
        else:
            nested[key] = value
    return yaml.safe_dump(nested, sort_keys=False)
