"""Presets: the flat ``{"a.b": value}`` layers that :func:`spot.config.resolve` applies over the
dataclass defaults, in this order: method, budget, suite (by ``data.name``), variant (with its
method- and suite-specific part), then the PT protocol's query count.

The layers are data tables (:data:`METHOD_PRESETS`, :data:`BUDGET_PRESETS`, :data:`SUITE_PRESETS`,
:data:`VARIANT_PRESETS`); the functions hold only the rules that depend on more than one of method,
budget, variant and dataset. :data:`METHOD_PRESETS` and :data:`REWARD_KINDS` grow by
:func:`spot.config.register_method`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

# --------------------------------------------------------------------------- method presets
METHOD_PRESETS: dict[str, dict[str, Any]] = {
    "oracle": {"reward.kind": "none", "shaping.kind": "none", "relabel.normalize": "iql"},
    "mr": {"reward.kind": "mr", "shaping.kind": "none"},
    "pt": {"reward.kind": "pt", "shaping.kind": "none"},
    "ipl": {"reward.kind": "ipl", "shaping.kind": "none", "relabel.normalize": "none"},
    "hpl": {"reward.kind": "hpl", "shaping.kind": "none", "relabel.normalize": "wiserl"},
    "spot": {"reward.kind": "pt", "shaping.kind": "cosine", "shaping.weight": 1.0},
}
REWARD_KINDS: list[str] = ["none", "mr", "pt", "hpl", "ipl"]  # RewardConfig.kind; grows by register_method


# --------------------------------------------------------------------------- budget presets
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
