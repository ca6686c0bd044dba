"""The order a sweep's trials start in, so that what overlaps does.

Trials of one sweep often share a stage: a SPOT run reuses the reward model of the PT run with the
same dataset, labels, reward config and seed (the stage cache, :mod:`spot.cache`, computes an entry
once and makes a trial that needs it meanwhile wait on its lock). Tune starts trials in the order
of its grid, as many at once as the sweep allows, so :func:`trial_order` puts

1. the trials that train a reward model another trial reuses (its first user in the grid),
2. then the trials that need no shared reward model (Oracle, or a reward model of their own),
3. then the trials that reuse a reward model trained by an earlier one,

each group in the grid's order, except that within a group a trial whose programs an earlier trial
already compiles (:func:`program_identity`: the same config on another dataset of the same
environment, or another seed) waits until the group's trials with programs of their own have
started. Two trials of the same shapes started together both compile every program (neither finds
it in the persistent compilation cache yet); one after the other, the second loads them from the
cache. In the Table 1 smoke sweep the medium-replay and medium-expert (or mh and ph) datasets of an
environment are neighbours in the grid, and so started together.

The reward model's users then start as late as the sweep allows
(their producer has had the longest time to store it), and what can run beside it (Oracle's IQL
beside PT's reward model) does. A sweep with one slot per core (two 1-CPU trials on 2 cores) starts
PT and Oracle together and SPOT when one of them ends; the quickstart starts all three at once (half
a CPU each), and SPOT waits on the stage cache's lock until PT's reward model is stored. Only the
start order changes: every run's config, seed and stage-cache keys
are those of the grid, and the summary lists the runs in the grid's order.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from spot import config as config_lib


def reward_identity(cfg: config_lib.ExperimentConfig) -> str | None:
    """What the run's learned reward model depends on (dataset, labels, reward and model config,
    seed; with the online CVAE its config too), as text: runs with equal text train the same
    stage-cache entry (:func:`spot.run.reward_stages.learned_reward`). None for a run that trains no
    reward model (Oracle, HPL, IPL)."""
    from spot.run import methods, reward_stages

    stages = methods.stages_of(cfg)
    if stages.reward not in (reward_stages.learned_reward, reward_stages.learned_reward_online):
        return None
    kind = cfg.reward.kind
    parts: dict[str, Any] = {
        "stage": stages.reward.__name__,
        "data": cfg.data,
        "labels": cfg.labels,
        "reward": cfg.reward,
        kind: getattr(cfg, kind),
        "seed": cfg.seed,
    }
    if stages.reward is reward_stages.learned_reward_online:
        parts.update(subgoal=cfg.subgoal, cvae=cfg.cvae, state_action=cfg.shaping.state_action)
    plain = {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v for k, v in parts.items()}
    return json.dumps(plain, sort_keys=True, default=str)


def program_identity(cfg: config_lib.ExperimentConfig) -> str:
    """What the programs a run compiles depend on, as text: its whole config except the seed, with
    the dataset named by its evaluation environment (datasets of one environment have the same
    observation and action sizes, so the same program shapes; only a few small programs depend on
    the number of transitions). A dataset spot does not know is named as it is."""
    from spot import SpotError
    from spot.envs import env_spec

    plain = dataclasses.asdict(cfg)
    plain.pop("seed", None)
    try:
        spec = env_spec(cfg.data.name)
        plain["data"] = {**plain["data"], "name": [spec.env_id, list(spec.make_kwargs)]}
    except SpotError:
        pass
    return json.dumps(plain, sort_keys=True, default=str)


def _identities(trial: Any) -> set[str]:
    """The reward identities of a trial's seeds (a trial may run several seeds)."""
    out = set()
    for seed in trial.seeds:
        ident = reward_identity(config_lib.resolve(trial.overrides, {"seed": seed}))
        if ident is not None:
            out.add(ident)
    return out


def trial_order(trials: list[Any]) -> list[Any]:
    """``trials`` (:class:`spot.sweep.spec.Trial`) in the order to start them (module docstring):
    producers of shared reward models, then the trials that share none, then their reusers; within
    each group the trials whose programs no earlier trial compiles first, each part in the grid's
    order."""
    idents = [_identities(t) for t in trials]
    users: dict[str, int] = {}
    for ids in idents:
        for i in ids:
            users[i] = users.get(i, 0) + 1
    seen: set[str] = set()
    groups: tuple[list[Any], list[Any], list[Any]] = ([], [], [])
    for trial, ids in zip(trials, idents, strict=True):
        shared = {i for i in ids if users[i] > 1}
        if shared and shared <= seen:
            groups[2].append(trial)  # every shared model it needs comes from an earlier trial
        elif shared - seen:
            groups[0].append(trial)  # the first to need one of them: it trains it
        else:
            groups[1].append(trial)
        seen |= shared
    compiled: set[str] = set()
    ordered: list[Any] = []
    for group in groups:  # within each group: trials with programs of their own first
        own, again = [], []
        for trial in group:
            key = program_identity(config_lib.resolve(trial.overrides, {"seed": trial.seeds[0]}))
            (again if key in compiled else own).append(trial)
            compiled.add(key)
        ordered += own + again
    return ordered
