"""Everything MLflow: where runs go, what every run records, and how runs are found again.

* :mod:`spot.tracking.store`: the one tracking-URI resolver (:func:`resolve_uri`), the local
  stores, experiments.
* :mod:`spot.tracking.provenance`: what every run records about itself (tags, params, MLflow's
  own fields, the environment and the files every run starts with).
* :mod:`spot.tracking.trackers`: the :class:`Tracker` interface and its MLflow and in-memory
  implementations.
* :mod:`spot.tracking.record`: a run's MLflow run (:func:`start_run`: params, dataset input,
  system metrics, FAILED on error) and :func:`record_failure` for an attempt that failed before it.
* :mod:`spot.tracking.run_temp`: the folders where runs stage their artifact files.
* :mod:`spot.tracking.queries`: quoted filter strings, paging through runs, finished-run lookup,
  orphan closing, artifacts (used by sweeps, tables and figures).
* :mod:`spot.tracking.tagnames`: the names tags have in MLflow (first-class ``method``,
  ``dataset``, ``seed``, ``variant``, ``axis.*``; the bookkeeping under ``spot.``) and reading the
  old bare names of stores written before.
* :mod:`spot.tracking.models`: a run's trained models as data-only artifacts with a JSON header
  (``models/<name>.npz`` + ``.json``), saved and loaded again (``spot eval``, ``spot figures``).
* :mod:`spot.tracking.ui`: the ``spot ui`` command and links that open the runs table (a sweep's shared view).
* :mod:`spot.tracking.recorded`: runs recorded as files where no MLflow store is at hand
  (``tracking.record``), imported into one later (``spot results import``);
  :mod:`spot.tracking.record_checks` checks a record whole before it is imported.
* :mod:`spot.tracking.limits`: deadlines of MLflow's HTTP requests (set for spot's processes when
  this package is imported, unless the environment sets them), one-line errors for a request that
  got no answer, and the cap on ``failure_reason``.

With no tracking URI every command's store is ``sqlite:///<cwd>/spot_runs/mlflow.db`` with artifacts
under ``<cwd>/spot_runs/artifacts`` (``spot run`` writes it; sweeps serve it, :mod:`spot.sweep.mlflow_server`;
an older folder's ``mlruns/mlflow.db`` is still read when it is the only one).
"""

from spot.tracking import tagnames
from spot.tracking.limits import TrackingUnreachable, failure_reason, set_http_deadlines, waiting_on
from spot.tracking.models import MODELS_DIR, load_artifact_text, load_model, run_config, save_model
from spot.tracking.provenance import (
    COMMAND_ENV,
    PACKAGES,
    active_params,
    command_line,
    environment,
    git_commit,
    mlflow_tags,
    package_versions,
    reproduce_command,
    run_tags,
)
from spot.tracking.queries import (
    artifact_uri,
    close_orphans,
    download_artifact,
    finished_run,
    first_run,
    local_artifact,
    quote,
    search_runs,
    search_tagged,
    tag_filter,
)
from spot.tracking.record import log_params, record_failure, start_run
from spot.tracking.store import (
    LOCAL_STORES,
    OLD_RUN_STORE,
    RUN_STORE,
    SWEEP_STORE,
    all_experiments,
    experiment_id,
    experiments,
    given_uri,
    has_experiment,
    reader,
    resolve_uri,
    sqlite_path,
)
from spot.tracking.trackers import MemoryTracker, MlflowTracker, Tracker, finite_metrics, json_safe
from spot.tracking.ui import run_url, runs_url, sweep_url, ui_command, where_logged

set_http_deadlines()  # before any MLflow request of this process (MLflow reads them at each request)

__all__ = [
    "TrackingUnreachable",
    "failure_reason",
    "set_http_deadlines",
    "waiting_on",
    "COMMAND_ENV",
    "MODELS_DIR",
    "active_params",
    "command_line",
    "environment",
    "json_safe",
    "load_artifact_text",
    "load_model",
    "mlflow_tags",
    "reproduce_command",
    "run_config",
    "run_url",
    "runs_url",
    "save_model",
    "sweep_url",
    "ui_command",
    "where_logged",
    "LOCAL_STORES",
    "OLD_RUN_STORE",
    "PACKAGES",
    "RUN_STORE",
    "SWEEP_STORE",
    "MemoryTracker",
    "MlflowTracker",
    "Tracker",
    "all_experiments",
    "artifact_uri",
    "close_orphans",
    "download_artifact",
    "experiment_id",
    "experiments",
    "finished_run",
    "finite_metrics",
    "first_run",
    "git_commit",
    "given_uri",
    "has_experiment",
    "local_artifact",
    "log_params",
    "package_versions",
    "quote",
    "record_failure",
    "reader",
    "resolve_uri",
    "run_tags",
    "search_runs",
    "search_tagged",
    "tagnames",
    "sqlite_path",
    "start_run",
    "tag_filter",
]
