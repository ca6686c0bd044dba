"""The parent run of a launch: created with the sweep file, its trials and its axes as params,
reopened on ``--resume``, and closed with the summary when the launch ends.
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

from spot.sweep import search as search_lib
from spot.sweep.spec import Sweep, tag_value
from spot.sweep.summary import Row
from spot.sweep.trial import SweepContext


def open_parent(client: Any, experiment_id: str, sweep: Sweep, state: dict[str, Any], *, resume: bool) -> str:
    """Create the launch's parent run (recorded in ``state``), or reopen it on resume."""
    from spot import tracking
    from spot.tracking.processes import process_tags
    from spot.tracking.tagnames import stored, stored_tags

    if resume:
        parent_id = state["parent_run_id"]
        n = tracking.close_orphans(
            client,
            experiment_id,
            {"sweep_id": state["sweep_id"]},
            "process ended during an interrupted launch",
            keep=(parent_id,),
        )
        print(
            f"resuming {state['sweep_id']}: {n} run(s) left RUNNING by the interrupted launch marked KILLED", flush=True
        )
        client.update_run(parent_id, status="RUNNING")
        client.set_tag(parent_id, stored("resumed_at"), time.strftime("%Y-%m-%d %H:%M:%S"))
        for key, value in process_tags().items():  # this driver owns the reopened run now
            client.set_tag(parent_id, key, value)
        return parent_id
    parent = client.create_run(
        experiment_id,
        run_name=f"sweep {state['sweep_id']}",
        tags=stored_tags(  # spot.sweep_id, spot.sweep_name, ... (the bookkeeping names)
            {
                "sweep_id": state["sweep_id"],
                "sweep_name": sweep.name,
                "spot.role": "sweep",
                "smoke": str(sweep.smoke),
                "sweep_file": str(sweep.path.resolve()),
                "git_commit": tracking.git_commit(),
                **process_tags(),
            }
        ),
    )
    parent_id = parent.info.run_id
    client.log_text(parent_id, sweep.path.read_text(), "sweep.yaml")
    client.log_dict(parent_id, [t.to_config() for t in sweep.trials()], "trials.json")
    client.log_batch(parent_id, params=_parent_params(sweep))
    state["parent_run_id"] = parent_id
    return parent_id


def _parent_params(sweep: Sweep) -> list[Any]:
    from mlflow.entities import Param

    params = {
        "sweep.trials": len(sweep.trials()),
        "sweep.runs": len(sweep.runs()),
        "sweep.seeds": list(sweep.seeds),
        "sweep.seed_mode": sweep.seed_mode,
        "sweep.cpu": sweep.resources["cpu"],
        "sweep.gpu": sweep.resources["gpu"],
        **{f"grid.{k}": v for k, v in sweep.grid.items()},
        **{f"zip.{k}": v for k, v in sweep.zip.items()},
        **{f"base.{k}": v for k, v in sweep.base.items()},
        **search_lib.parent_params(sweep),  # metric, searcher, space, scheduler; a search's trials and runs
    }
    return [Param(k, tag_value(v)[:6000]) for k, v in params.items()]


def close_parent(client: Any, ctx: SweepContext, rows: list[Row], table: str, *, interrupted: bool) -> None:
    """Log the summary to the parent run and end it: FINISHED if every run finished, KILLED if
    interrupted, else FAILED."""
    from mlflow.entities import Metric

    n_done = sum(r.status == "FINISHED" for r in rows)
    now = int(time.time() * 1000)
    client.log_batch(
        ctx.parent_run_id,
        metrics=[
            Metric(k, v, now, 0)
            for k, v in (
                ("sweep/runs_total", len(rows)),
                ("sweep/runs_finished", n_done),
                ("sweep/runs_failed", len(rows) - n_done),
            )
        ],
    )
    client.log_text(ctx.parent_run_id, table + "\n", "summary.txt")
    log_curves_figure(client, ctx)
    client.set_terminated(
        ctx.parent_run_id, "KILLED" if interrupted else "FINISHED" if n_done == len(rows) else "FAILED"
    )


CURVES_ARTIFACT = "curves.png"


def curves_by(axis_keys: tuple[str, ...], params: set[str]) -> str:
    """What a sweep's curves are grouped by: its first swept param (beside the method), else the method."""
    return next((k for k in axis_keys if k != "method" and f"params.{k}" in params), "method")


def log_curves_figure(client: Any, ctx: SweepContext) -> str | None:
    """Log the sweep's evaluation curves (mean over seeds, 95 % CI band, per swept value) as
    :data:`CURVES_ARTIFACT` of its parent run. Best effort: a figure that cannot be drawn or logged
    is a warning and ``None``, never a failed sweep; returns the artifact path when logged."""
    try:
        from spot.results import export, figures_curves, load

        runs = load.load_runs(ctx.tracking_uri, [ctx.experiment_name], ctx.sweep_id)
        if runs.empty:
            return None
        runs = export.add_curves(runs, client)
        by = curves_by(ctx.axis_keys, set(runs.columns))
        summary = figures_curves.summarize_curves(figures_curves.curve_points(runs, by))
        fig = figures_curves.draw_curves(summary, title=f"sweep {ctx.sweep_id} ({ctx.sweep_name})")
        with tempfile.TemporaryDirectory(prefix="spot-curves-") as tmp:
            figures_curves.save(fig, Path(tmp) / CURVES_ARTIFACT)
            client.log_artifact(ctx.parent_run_id, str(Path(tmp) / CURVES_ARTIFACT))
        return CURVES_ARTIFACT
    except Exception as err:  # noqa: BLE001 - a picture never fails the sweep
        warnings.warn(
            f"sweep {ctx.sweep_id}: no curves figure on its parent run ({type(err).__name__}: {err})", stacklevel=2
        )
        return None
