"""The method-plugin API (docs/extending.md): what a method added from outside spot is built from.

``stages.register(name, stages.RewardKind(reward, relabel, policy), preset=...)`` adds a method; its
stage functions take a :class:`Context` and the typed outputs of earlier stages and may reuse the
stock ones below. The stages themselves live in :mod:`spot.run` by role (context, label, reward,
subgoal and policy stages, the method table); this module only re-exports the public names, the
same objects (``stages.REWARD_KINDS`` is the table ``register`` fills).
"""

from spot.run.context import (
    Context,
    Labelled,
    Policy,
    RewardModel,
    Rewards,
    Shaped,
    Subgoals,
    dataset_deps,
    save_model,
    untimed,
)
from spot.run.methods import PLUGIN_GROUP, REWARD_KINDS, RewardKind, load_plugins, register, stages_of
from spot.run.policy_stages import ipl_policy, iql_policy
from spot.run.reward_stages import (
    hpl_reward,
    hpl_rewards,
    learned_reward,
    model_rewards,
    true_reward,
    true_rewards,
    zero_rewards,
)

__all__ = [
    "PLUGIN_GROUP",
    "REWARD_KINDS",
    "Context",
    "Labelled",
    "Policy",
    "RewardKind",
    "RewardModel",
    "Rewards",
    "Shaped",
    "Subgoals",
    "dataset_deps",
    "hpl_reward",
    "hpl_rewards",
    "iql_policy",
    "ipl_policy",
    "learned_reward",
    "load_plugins",
    "model_rewards",
    "register",
    "save_model",
    "stages_of",
    "true_reward",
    "true_rewards",
    "untimed",
    "zero_rewards",
]
