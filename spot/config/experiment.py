"""The config schema, part two: the sections of SPOT's subgoals, CVAE and shaping, of the policy
(IQL), of evaluation and of tracking, and :class:`ExperimentConfig`, which composes every section
(:data:`STAGES`) under the method, budget, variant and seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from spot.config.schema import (
    DataConfig,
    F,
    HPLConfig,
    IPLConfig,
    LabelsConfig,
    MRConfig,
    PTConfig,
    RelabelConfig,
    RewardConfig,
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
    stepper: str = F(
        "mujoco",
        "how locomotion evaluation episodes step: 'mujoco' drives MuJoCo directly, all episodes' "
        "observations and rewards computed at once (spot.mujoco_step; the same returns, to the last digit, as "
        "gymnasium's env), 'gymnasium' the env's own step; other envs always run in gymnasium",
        choices=("mujoco", "gymnasium"),
    )


@dataclass(frozen=True)
class TrackingConfig:
    uri: str = F("", "MLflow tracking URI; empty = local store ./spot_runs/mlflow.db in the working folder")
    experiment: str = F("spot", "MLflow experiment name")
    record: str = F(
        "",
        "a folder: record the run there as files instead of logging it to MLflow (a machine without MLflow or "
        "its store); `spot results import FOLDER` logs the records into a store later; empty = MLflow",
    )


STAGES: dict[str, type] = {
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
