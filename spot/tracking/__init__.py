"""Everything MLflow: where runs go, what every run records, and how runs are found again.

* :mod:`spot.tracking.store`: the one tracking-URI resolver (:func:`resolve_uri`), the local
  stores, experiments.
* :mod:`spot.tracking.record`: what a run logs (tags, params, the :class:`Tracker` interface, its
  MLflow and in-memory implementations, :func:`start_run`).
* :mod:`spot.tracking.queries`: quoted filter strings, paging through runs, finished-run lookup,
  failure records, orphan closing, artifacts (used by sweeps, tables and figures).

With no tracking URI a run's store is ``sqlite:///<cwd>/mlruns/mlflow.db`` with artifacts under
``<cwd>/mlruns/artifacts`` (one process writes it; sweeps use a server, :mod:`spot.mlflow_server`).
"""

from spot.tracking.queries import (
    artifact_uri,
    close_orphans,
    download_artifact,
    finished_run,
    first_run,
    local_artifact,
    quote,
    record_failure,
    search_runs,
    tag_filter,
)
from spot.tracking.record import (
    PACKAGES,
    MemoryTracker,
    MlflowTracker,
    Tracker,
    finite_metrics,
    git_commit,
    log_params,
    package_versions,
    run_tags,
    start_run,
)
from spot.tracking.store import (
    LOCAL_STORES,
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

__all__ = [
    "LOCAL_STORES", "PACKAGES", "RUN_STORE", "SWEEP_STORE", "MemoryTracker", "MlflowTracker", "Tracker",
    "all_experiments", "artifact_uri", "close_orphans", "download_artifact", "experiment_id", "experiments",
    "finished_run", "finite_metrics", "first_run", "git_commit", "given_uri", "has_experiment", "local_artifact",
    "log_params", "package_versions", "quote", "record_failure", "reader", "resolve_uri", "run_tags",
    "search_runs", "sqlite_path", "start_run", "tag_filter",
]
