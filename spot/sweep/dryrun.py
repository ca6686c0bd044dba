"""``spot sweep FILE --dry-run``: what a launch of the file would run, launching nothing.

A grid sweep lists every trial (its axis values and seeds). A search sweep has no trial list before
it runs (the searcher proposes the configs as results come in), so its dry run shows what will
run: the searcher and its ``num_samples``, each searched key's domain, the fixed part (the base
config and the seeds every proposed config runs) and the trial and run counts. A scheduler, with
either, is shown with the metric and mode it acts on and every option it runs with (spot's
defaults included), and ASHA's rungs.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from spot.sweep import search as search_lib
from spot.sweep.spec import Sweep, tag_value


def lines(sweep: Sweep) -> Iterator[str]:
    """The dry run's output, line by line (a grid of thousands of trials is printed as it goes)."""
    n_trials, n_runs = search_lib.counts(sweep)
    what = f"search: {sweep.search.algorithm}, " if sweep.search else ""
    yield (
        f"sweep '{sweep.experiment}' ({sweep.path}): {what}{n_trials} trials, {n_runs} runs, "
        f"seed_mode {sweep.seed_mode}, resources per trial {sweep.resources}"
    )
    if sweep.metric is not None:
        safe = "offline-safe" if sweep.metric in search_lib.OFFLINE_SAFE else "uses the online evaluation"
        yield f"  metric: {sweep.metric} ({safe}), mode {sweep.mode}"
    if sweep.search is not None:
        yield from _search_lines(sweep)
    if sweep.scheduler is not None:
        yield from _scheduler_lines(sweep.scheduler, sweep.metric, sweep.mode)
    if sweep.search is None:
        for i, t in enumerate(sweep.trials()):
            yield f"  {i:4d}  {t.label}  seeds={list(t.seeds)}"


def _search_lines(sweep: Sweep) -> Iterator[str]:
    found = sweep.search
    assert found is not None
    yield (
        f"  searcher: {search_lib.SEARCHER_NAMES[found.algorithm]}, seed {found.seed}, "
        f"num_samples {found.num_samples}: proposes {found.num_samples} configs"
    )
    yield f"  space ({len(found.space)} keys):"
    width = max(len(k) for k in found.space)
    for key, (kind, args) in found.space.items():
        note = " (integers, high excluded)" if kind == "randint" else ""
        yield f"    {key:<{width}}  {search_lib.domain_text(kind, args)}{note}"
    fixed = " ".join(f"{k}={tag_value(v)}" for k, v in sweep.base.items()) or "(the config's defaults)"
    yield f"  fixed: {fixed}"
    per_trial = len(sweep.seeds) if sweep.seed_mode != "trials" else 1
    yield (
        f"  trials: {found.num_samples} proposed configs x seeds {list(sweep.seeds)} = "
        f"{found.num_samples * len(sweep.seeds)} runs ({per_trial} seed{'s' * (per_trial != 1)} per trial, "
        f"seed_mode {sweep.seed_mode})"
    )


def _scheduler_lines(sched: search_lib.Scheduler, metric: Any, mode: Any) -> Iterator[str]:
    options = search_lib.scheduler_options(sched)
    shown = ", ".join(f"{k} {v}" for k, v in options.items())
    yield (
        f"  scheduler: {search_lib.STOPPER_NAMES[sched.name]} ({search_lib.SCHEDULER_CLASSES[sched.name]}) on "
        f"{metric} ({mode}): {shown}"
    )
    yield "    time: training_iteration, the results a trial reported (one per evaluation, one per seed's end)"
    if sched.name == "asha":
        rungs = asha_rungs(options["grace_period"], options["max_t"], options["reduction_factor"])
        yield f"    ASHA compares trials at {', '.join(map(str, rungs))} results; stops every trial at max_t"
    else:
        yield (
            "    median stopping: from grace_period results on, stops a trial whose best result is behind the median "
            "of the other trials' running means (once min_samples_required trials have reported)"
        )


def asha_rungs(grace_period: int, max_t: int, reduction_factor: int) -> list[int]:
    """The results at which Tune's ASHA (one bracket) compares a trial with the others, lowest first:
    ``grace_period * reduction_factor ** k`` up to ``max_t``, as ``ray.tune.schedulers.async_hyperband``
    builds its rungs."""
    import numpy as np

    n = int(np.log(max_t / grace_period) / np.log(reduction_factor) + 1)
    return [int(grace_period * reduction_factor**k) for k in range(n)]
