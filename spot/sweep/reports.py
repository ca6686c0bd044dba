"""A sweep trial's reports to Tune: the metrics a scheduler or searcher acts on, and a trial that
Tune's scheduler stopped early.

Each evaluation reports ``eval/score`` (with ``score`` and ``iql_step`` for Tune's status table),
and the reward stages report the reward model's held-out ``reward/best_eval_acc`` and
``reward/best_eval_loss`` (of the checkpoint kept) through the run's ``on_eval``
(:func:`evaluated`). When the scheduler stops a trial, Ray's ``tune.report`` raises
``SystemExit(0)`` in the trial's thread; :class:`Reports` turns it into :class:`StoppedEarly`, the
run ends KILLED and :func:`mark_stopped` gives it the reason (``stopped early by ASHA at step
N``). See docs/sweeps.md, "Search and early stopping".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Report = Callable[[dict[str, Any]], None]


class StoppedEarly(KeyboardInterrupt):
    """Tune's scheduler stopped the trial (its ``tune.report`` raised ``SystemExit(0)``): a
    KeyboardInterrupt, so that the open runs end KILLED (:func:`spot.tracking.start_run`)."""


class Reports:
    """``tune.report`` for a trial: every result carries the last value of each metric reported so
    far (a scheduler or searcher reads its metric from every result), one without ``metric`` (the
    reward stage's before the first evaluation) is not sent, and a stop raises :class:`StoppedEarly`.
    Without a ``metric`` (no search or scheduler) each report is sent as it is."""

    def __init__(self, report: Report, metric: str | None = None, stopper: str = "") -> None:
        self.report, self.metric, self.stopper, self.last = report, metric, stopper, {}

    def __call__(self, metrics: dict[str, Any]) -> None:
        self.last.update(metrics)
        if self.metric is not None and self.metric not in self.last:
            return
        try:  # (without a metric, a grid sweep's reports as they were: each its own)
            self.report(dict(self.last) if self.metric is not None else dict(metrics))
        except SystemExit as e:
            if e.code not in (0, None):
                raise
            at = f"at step {self.last['iql_step']}" if "iql_step" in self.last else "after the reward stage"
            raise StoppedEarly(f"stopped early by {self.stopper or 'the scheduler'} {at}") from None


def evaluated(seed: int, report: Report) -> Callable[[dict[str, float]], None]:
    """A run's ``on_eval``: an evaluation's score (``eval/score``, and ``score``/``iql_step`` for
    Tune's table), or the reward model's held-out metrics (``reward/best_eval_*``, passed by the
    reward stages to an ``on_eval`` marked ``takes_reward_metrics``), reported for ``seed``."""

    def on_eval(m: dict[str, float]) -> None:
        if "score" in m:
            report({"seed": seed, "score": m["score"], "eval/score": m["score"], "iql_step": m["step"]})
        else:
            report({"seed": seed, **{k: float(v) for k, v in m.items()}})

    on_eval.takes_reward_metrics = True  # type: ignore[attr-defined]  # the reward stages call it then too
    return on_eval


def mark_stopped(client: Any, ctx: Any, attempts: list[str], stop: StoppedEarly) -> None:
    """The runs of ``attempts`` (their ``attempt`` tags), ended KILLED by the stop, get its reason
    as their ``failure_reason`` (without the exception's type)."""
    from spot import tracking

    for attempt in attempts:
        for run in tracking.search_tagged(client, [ctx.experiment_id], {"attempt": attempt}):
            client.set_tag(run.info.run_id, "failure_reason", str(stop))
            if run.info.status != "KILLED":
                client.set_terminated(run.info.run_id, "KILLED")


def close_stopped(client: Any, ctx: Any, trials: list[Any]) -> int:
    """After Tune's run, on the driver: the runs still RUNNING of trials Tune ended TERMINATED (a
    trial that ran to its end closed its runs FINISHED) were stopped by the scheduler, their process
    gone before its thread closed them (Ray ends a stopped trial's actor right away unless the next
    trial reuses it): KILLED with ``stopped early by <scheduler> at step N``, N the last evaluation
    logged. Returns how many runs were closed."""
    from spot import tracking

    closed = 0
    for trial in trials:
        if trial.status != "TERMINATED":
            continue
        found = {"sweep_id": ctx.sweep_id, "trial_id": str(trial.trial_id)}
        for run in tracking.search_tagged(client, [ctx.experiment_id], found):
            reason = run.data.tags.get("failure_reason", "")
            if run.info.status == "KILLED" and reason.startswith(f"{StoppedEarly.__name__}: "):
                # the process ended between closing the run and naming its reason (mark_stopped)
                client.set_tag(run.info.run_id, "failure_reason", reason.split(": ", 1)[1])
            if run.info.status != "RUNNING":
                continue
            steps = [m.step for m in client.get_metric_history(run.info.run_id, "eval/score")]
            at = f"at step {max(steps)}" if steps else "after the reward stage"
            client.set_tag(run.info.run_id, "failure_reason", f"stopped early by {ctx.stopper or 'the scheduler'} {at}")
            client.set_terminated(run.info.run_id, "KILLED")
            closed += 1
    return closed
