"""Where to look at runs: the ``spot ui`` command and links that open the runs table.

MLflow 3's UI opens an experiment on its GenAI overview unless the experiment is an ML one (spot
tags its experiments so, :mod:`spot.tracking.naming`); ``workflowType=machine_learning`` asks for the
classic runs table as well, and ``searchFilter`` fills its search box (:func:`runs_url`).

The columns of the runs table and which rows are expanded are UI state that MLflow keeps in the
browser's local storage, not in the URL. The one way a link carries them is MLflow's shared view
(its "Share" button): the state as JSON in the experiment tag ``mlflow.sharedViewState.<key>`` and
``viewStateShareKey=<key>`` in the link (the UI reads the search filter, sort and columns from it,
but never which rows are expanded, and ignores it when the link has a ``searchFilter`` of its own).
A sweep's link (:func:`sweep_url`, its view written by :func:`share_sweep_view`) therefore filters on
the parent run, so the trials are the table's rows and not collapsed under it, and shows the
method, dataset, seed, swept axes and scores as columns.

``spot ui`` (:mod:`spot.cli.ui`) serves a store with the venv's own ``mlflow server``, the lean way:
one worker and job execution off (``MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false``, the only switch
mlflow 3.17 has for it: an environment variable, no ``mlflow ui`` option). Measured on this 2-core
machine under load (load average 5-7), time to ``/health`` and the summed RSS of the process tree:
20.6 s and 507 MB against 59 s and 2.47 GB for the default command (four workers and the job runner).
"""

from __future__ import annotations

import json
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlencode

from spot.tracking.queries import tag_filter

DEFAULT_URL = "http://127.0.0.1:5000"
"""Where ``mlflow ui`` serves by default."""


def ui_command(backend_uri: str, artifacts: str | Path | None = None) -> str:
    """``spot ui --tracking-uri URI``: the lean UI on that store (artifacts beside a SQLite store,
    where spot writes them; ``artifacts`` is accepted for the callers that name it)."""
    return shlex.join(["spot", "ui", "--tracking-uri", backend_uri])


def server_command(backend_uri: str, artifacts: str | Path, port: int) -> str:
    """The ``mlflow server`` command ``spot ui`` runs, as text (for a machine without spot)."""
    parts = ["mlflow", "server", "--backend-store-uri", backend_uri, "--artifacts-destination", str(artifacts)]
    parts += ["--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
    return "MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false " + shlex.join(parts)


def runs_url(experiment_id: str, search_filter: str = "", base: str = DEFAULT_URL) -> str:
    """The UI's runs table of an experiment (``#/experiments/<id>/runs?workflowType=machine_learning``)
    with ``search_filter`` in its search box (URL-encoded)."""
    query = {"workflowType": "machine_learning"}
    if search_filter:
        query["searchFilter"] = search_filter
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs?{urlencode(query, quote_via=quote)}"


SHARED_VIEW_TAG = "mlflow.sharedViewState."
"""Prefix of the experiment tag holding a shared view of the runs table (MLflow's UI constant)."""
SWEEP_COLUMNS = ("method", "dataset", "seed", "variant")
SCORE_COLUMNS = ("eval/score_final", "eval/score_best", "eval/score_paper")


def share_key(sweep_id: str) -> str:
    """The shared view's key of one sweep launch."""
    return f"spot-{sweep_id}"


def column(kind: str, name: str) -> str:
    """A runs-table column as the UI names it: ``tags.`method```, ``metrics.`eval/score_final```."""
    return f"{kind}.`{name}`"


def sweep_view(parent_run_id: str, axis_keys: Sequence[str]) -> dict[str, Any]:
    """The shared view of a sweep launch: its trials' runs (children of ``parent_run_id``, so none is
    collapsed under the parent) with the first-class tags, every swept axis and the scores."""
    tags = [*SWEEP_COLUMNS, *(f"axis.{k}" for k in axis_keys if k not in ("method", "data.name"))]
    return {
        "searchFilter": tag_filter({"mlflow.parentRunId": parent_run_id}),
        "orderByKey": "tags.`mlflow.runName`",  # not the start time: then the UI nests children under parents
        "orderByAsc": True,
        "selectedColumns": [*(column("tags", t) for t in tags), *(column("metrics", m) for m in SCORE_COLUMNS)],
        "runsHiddenMode": "SHOW_ALL",
    }


def share_sweep_view(
    client: Any, experiment_id: str, sweep_id: str, parent_run_id: str, axis_keys: Sequence[str]
) -> None:
    """Write :func:`sweep_view` as the experiment's shared view :func:`share_key` (``sweep_url``'s)."""
    value = json.dumps(sweep_view(parent_run_id, axis_keys), separators=(",", ":"))
    client.set_experiment_tag(experiment_id, SHARED_VIEW_TAG + share_key(sweep_id), value)


def sweep_url(experiment_id: str, sweep_id: str, base: str = DEFAULT_URL) -> str:
    """The runs table in the shared view of one sweep launch (:func:`share_sweep_view`)."""
    query = {"viewStateShareKey": share_key(sweep_id), "workflowType": "machine_learning"}
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs?{urlencode(query, quote_via=quote)}"


def run_url(experiment_id: str, run_id: str, base: str = DEFAULT_URL) -> str:
    """One run's page, in the UI's model-training workspace (``workflowType``: the UI otherwise keeps
    the workspace last chosen in the browser, which may be GenAI)."""
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs/{run_id}?workflowType=machine_learning"


def where_logged(tracking_uri: str, experiment_id: str, run_id: str) -> list[str]:
    """The lines ``spot run`` prints at its end: the store, how to open it, the link to the run.

    A ``sqlite:`` store gets the ``spot ui`` command and links on its default address; a server's
    links use the server's address.
    """
    from spot.tracking.store import sqlite_path

    db = sqlite_path(tracking_uri)
    lines = [f"logged to {tracking_uri} (experiment id {experiment_id}, run {run_id})"]
    if db is not None:
        lines.append(f"open the runs with: {ui_command(tracking_uri, db.resolve().parent / 'artifacts')}")
        base = DEFAULT_URL
    elif tracking_uri.startswith(("http://", "https://")):
        base = tracking_uri
    else:
        return lines
    lines.append(f"then: {run_url(experiment_id, run_id, base)}")
    lines.append(f"runs table: {runs_url(experiment_id, base=base)}")
    return lines
