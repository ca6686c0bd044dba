"""The floor of a sweep and each phase's ratio to it (``spot bench sweep``).

The floor is the time the launch's training alone would take on this machine with every core busy
and nothing else to do: the IQL updates of every run it ran, at the rate one process gets on all
cores, plus the reward-model (MR/PT) steps of every reward model it trained (one per distinct
dataset, labels, reward config and seed: :func:`spot.sweep.order.reward_identity`), at their rate.
The rates come from a short calibration after the sweep (the real jitted train chunks on random
data at the sweep's sizes, :func:`spot.bench.iql_updates` and :func:`spot.bench.reward_steps`), or
are given.

Against it, the command's time is split into core-seconds (wall seconds x cores): each phase's
seconds summed over the trials times the CPUs each trial had (``time/trial_cpus``), and what is
left outside the trials (Ray and MLflow start-up, dataset builds, cores left idle). Each part over
the floor's core-seconds is its ratio; the parts add up to the command's wall time over the floor.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from spot import config as config_lib
from spot.sweep.order import reward_identity
from spot.sweep.spec import run_key
from spot.sweep.summary import PHASE_COLUMNS


@dataclass(frozen=True)
class Work:
    """The training the launch's runs did, and the sizes to calibrate its rates at."""

    iql_updates: int
    reward_steps: int
    reward_models: int
    iql_cfg: Any  # an IQLConfig of the runs (the first), or None if no run trained IQL
    reward_cfg: Any  # (the ExperimentConfig of the first run with a reward model, or None)
    approximate: bool = False  # some reward model counts its length in epochs: estimated pairs


@dataclass(frozen=True)
class Rates:
    """Updates (steps) per second on all cores, and where they come from."""

    iql_per_s: float
    reward_per_s: float
    how: str


def _reward_steps(cfg: config_lib.ExperimentConfig) -> tuple[int, bool]:
    """The reward model's gradient steps, and whether that is an estimate (``reward.length=epochs``
    counts epochs of the training pairs: estimated as ``labels.num_queries`` less the held-out part)."""
    from spot.reward.train import training_steps

    if cfg.reward.length != "epochs":
        return training_steps(cfg.reward, 0), False
    pairs = cfg.labels.num_queries - round(cfg.labels.num_queries * cfg.labels.eval_fraction)
    return training_steps(cfg.reward, pairs), True


def work_of(spec: Any, rows: list[Any]) -> Work:
    """The :class:`Work` of the runs of ``rows`` that ran in this launch (those with a breakdown)."""
    ran = {r.key for r in rows if r.timing}
    iql_updates, steps, approximate = 0, 0, False
    models: set[str] = set()
    first_iql = first_reward = None
    for trial, seed in spec.runs():
        if run_key(trial.overrides, seed) not in ran:
            continue
        cfg = config_lib.resolve(trial.overrides, {"seed": seed})
        iql_updates += cfg.iql.steps
        first_iql = first_iql or cfg.iql
        ident = reward_identity(cfg)
        if ident is not None and ident not in models:
            models.add(ident)
            n, estimated = _reward_steps(cfg)
            steps, approximate = steps + n, approximate or estimated
            first_reward = first_reward or cfg
    return Work(iql_updates, steps, len(models), first_iql, first_reward, approximate)


def calibrate(work: Work, obs_dim: int, act_dim: int, n: int) -> Rates:
    """Measure IQL's and the reward model's rates in this process, on all its cores, at the sizes of
    ``work`` (``n`` random transitions of ``obs_dim``/``act_dim``): about 2,000 IQL updates and 30
    reward-model steps after compiling each."""
    from spot import bench
    from spot.reward import models

    iql_rate = reward_rate = 0.0
    if work.iql_cfg is not None:
        cfg = replace(work.iql_cfg, chunk=500)
        iql_rate = bench.iql_updates(obs_dim, act_dim, n=n, steps=2000, cfg=cfg)["updates_per_s"]
    if work.reward_cfg is not None:
        c = work.reward_cfg
        model = models.from_config(c)
        reward_rate = bench.reward_steps(
            model, batch=c.reward.batch_size, length=c.labels.segment_length, steps=30, obs_dim=obs_dim, act_dim=act_dim
        )["steps_per_s"]
    return Rates(iql_rate, reward_rate, "measured now, after the sweep, by a short calibration on all cores")


def floor_s(work: Work, rates: Rates) -> float:
    """Seconds of training at the calibrated rates (0 for work with no rate)."""
    iql = work.iql_updates / rates.iql_per_s if work.iql_updates and rates.iql_per_s > 0 else 0.0
    reward = work.reward_steps / rates.reward_per_s if work.reward_steps and rates.reward_per_s > 0 else 0.0
    return iql + reward


def ratios(rows: list[Any], floor: float, wall_s: float, cores: int) -> dict[str, float]:
    """Each phase's core-seconds over the floor's (``floor`` x ``cores``), ``outside`` (the rest of
    the command's ``wall_s`` x ``cores``) and ``total`` (``wall_s`` / ``floor``); module docstring."""
    budget = floor * cores
    seen: set[str] = set()
    used = dict.fromkeys(PHASE_COLUMNS, 0.0)
    for r in rows:
        if not r.timing or (r.trial_id or r.key) in seen:  # a trial's breakdown is on each of its runs
            continue
        seen.add(r.trial_id or r.key)
        cpus = r.timing.get("time/trial_cpus", 1.0)
        for p in PHASE_COLUMNS:
            used[p] += r.timing.get(f"time/trial_{p}_s", 0.0) * cpus
    out = {p: used[p] / budget for p in PHASE_COLUMNS}
    # trials' CPUs are time averages, so their core-seconds can exceed the command's by a little
    out["outside"] = max(0.0, wall_s * cores - sum(used.values())) / budget
    out["total"] = wall_s / floor
    return out


def format_floor(work: Work, rates: Rates, rows: list[Any], wall_s: float, cores: int) -> str:
    """The floor's line and the ratios' line of ``spot bench sweep``."""
    floor = floor_s(work, rates)
    if floor <= 0:
        return "floor: no IQL updates or reward-model steps were timed in this launch"
    parts = [f"{work.iql_updates:,} IQL updates at {rates.iql_per_s:,.0f} updates/s"]
    if work.reward_steps:
        approx = "~" if work.approximate else ""
        parts.append(
            f"{approx}{work.reward_steps:,} reward-model steps ({work.reward_models} model"
            f"{'s' if work.reward_models != 1 else ''}) at {rates.reward_per_s:,.1f} steps/s"
        )
    r = ratios(rows, floor, wall_s, cores)
    cells = "  ".join(f"{p} {r[p]:.2f}x" for p in (*PHASE_COLUMNS, "outside"))
    return "\n".join(
        [
            f"floor: {' + '.join(parts)} = {floor:.1f} s on {cores} cores (rates {rates.how})",
            f"ratio to the floor (core-seconds over the floor's {floor * cores:.1f}): {cells}  "
            f"= {r['total']:.2f}x ({wall_s:.1f} s / {floor:.1f} s)",
            "  outside: the command's core-seconds outside the trials (Ray, MLflow, dataset builds, idle cores)",
        ]
    )


def report(spec: Any, rows: list[Any], cpu: Any, rates: Rates | None = None) -> str:
    """:func:`format_floor` of a finished launch (``cpu``: its :class:`spot.phases.CpuMeter`), with
    the rates calibrated here unless given; the dataset of the first run that ran gives the sizes."""
    from spot.run import pipeline

    work = work_of(spec, rows)
    if rates is None:
        timed = {r.key for r in rows if r.timing}
        ran = [(t, s) for t, s in spec.runs() if run_key(t.overrides, s) in timed]
        if not ran:
            return "floor: no run was timed in this launch"
        ds, _ = pipeline.open_dataset(config_lib.resolve(ran[0][0].overrides, {"seed": ran[0][1]}))
        obs_dim, act_dim = ds.observations.shape[1], ds.actions.shape[1]
        rates = calibrate(work, obs_dim, act_dim, len(ds.observations))
    return format_floor(work, rates, rows, cpu.wall_s, cpu.cpus)
