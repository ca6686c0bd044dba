"""The method table: which stage functions fill the reward, relabel and policy slots for each
``reward.kind`` (:data:`REWARD_KINDS`, set by the method preset); adding a method is one
:func:`register` call plus the module with its stage functions, and a method shipped in another
package is a ``spot.methods`` entry point (:func:`load_plugins`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from spot import SpotError
from spot import config as config_lib
from spot.config import ExperimentConfig
from spot.run.context import Context, Labelled, Policy, RewardModel, Rewards, Shaped
from spot.run.policy_stages import ipl_policy, iql_policy
from spot.run.reward_stages import (
    hpl_reward,
    hpl_rewards,
    learned_reward,
    learned_reward_online,
    model_rewards,
    true_reward,
    true_rewards,
    zero_rewards,
)
from spot.run.subgoal_stages import online_cvae


@dataclass(frozen=True)
class RewardKind:
    """The stages that fill the reward, relabel and policy slots for one ``reward.kind``."""

    reward: Callable[[Context, Labelled | None], RewardModel | None]
    relabel: Callable[[Context, Any], Rewards]
    policy: Callable[[Context, Shaped, Labelled | None], Policy] = iql_policy
    uses_labels: bool = True


REWARD_KINDS: dict[str, RewardKind] = {
    "none": RewardKind(true_reward, true_rewards, uses_labels=False),  # Oracle
    "mr": RewardKind(learned_reward, model_rewards),  # MR
    "pt": RewardKind(learned_reward, model_rewards),  # PT, SPOT
    "hpl": RewardKind(hpl_reward, hpl_rewards),  # HPL
    "ipl": RewardKind(true_reward, zero_rewards, policy=ipl_policy),  # IPL
}


def register(method: str, kind: RewardKind, preset: dict[str, Any] | None = None) -> None:
    """Add a method: its stages (under ``reward.kind = method``) and its config preset.

    ``spot run method=<method>`` then runs ``kind``'s stages; see docs/design.md, "Adding a method".
    """
    if method in REWARD_KINDS or method in config_lib.METHOD_PRESETS:
        raise SpotError(f"method {method!r} is already registered")
    config_lib.register_method(method, {"shaping.kind": "none", **(preset or {}), "reward.kind": method})
    REWARD_KINDS[method] = kind


PLUGIN_GROUP = "spot.methods"


def load_plugins() -> list[str]:
    """Call every ``spot.methods`` entry point (a function that calls :func:`register`), once per
    process, so that a method shipped in another package works with ``spot run`` and ``spot sweep``.
    Returns the entry points' names."""
    from importlib.metadata import entry_points

    names = []
    for ep in entry_points(group=PLUGIN_GROUP):
        if ep.name not in _LOADED_PLUGINS:
            ep.load()()
            _LOADED_PLUGINS.add(ep.name)
        names.append(ep.name)
    return names


_LOADED_PLUGINS: set[str] = set()


def stages_of(cfg: ExperimentConfig) -> RewardKind:
    """The stages of ``cfg``'s ``reward.kind``; with ``cvae.schedule=online`` (PT runs that need a
    CVAE) the reward slot is :func:`spot.run.reward_stages.learned_reward_online`."""
    try:
        kind = REWARD_KINDS[cfg.reward.kind]
    except KeyError:
        raise SpotError(
            f"reward.kind={cfg.reward.kind!r} has no stages; registered: {', '.join(REWARD_KINDS)}"
        ) from None
    return replace(kind, reward=learned_reward_online) if online_cvae(cfg) else kind
