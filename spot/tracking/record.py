"""An MLflow run for a pipeline run, and how a failed run is marked.

:func:`start_run` opens the run and yields its :class:`~spot.tracking.trackers.MlflowTracker`: the
tags, params and files of :mod:`spot.tracking.provenance`, the dataset as a logged input
(:func:`log_dataset_input`) and MLflow's system metrics (``system/*``, :class:`SystemMetrics`).
A run that fails inside :func:`start_run` ends FAILED with a ``failure_reason``;
:func:`record_failure` gives an attempt that failed before its run opened (config, dataset) a
FAILED run of its own.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from spot import config as config_lib
from spot import phases
from spot.tracking.limits import failure_reason, waiting_on
from spot.tracking.locking import prepare_store
from spot.tracking.naming import default_name, log_paper_score, run_name
from spot.tracking.processes import close_dead_runs, process_tags
from spot.tracking.provenance import active_params, log_run_files, mlflow_tags, run_tags, start_tags
from spot.tracking.queries import client_uri, first_run
from spot.tracking.store import experiment_id, resolve_uri
from spot.tracking.tagnames import get, stored, stored_tags
from spot.tracking.trackers import MlflowTracker

DIGEST_CHARS = 32  # MLflow keeps at most 36 characters of a dataset digest


def log_dataset_input(
    client: Any, run_id: str, ds: Any, card: Mapping[str, Any], cfg: config_lib.ExperimentConfig, digest: str
) -> None:
    """The run's dataset as an MLflow input (context ``training``): its name, the file it was read
    from, the first :data:`DIGEST_CHARS` hex digits of its fingerprint as the digest, and a schema
    of its arrays (name, dtype, shape)."""
    import numpy as np
    from mlflow.data.meta_dataset import MetaDataset
    from mlflow.data.sources import LocalArtifactDatasetSource
    from mlflow.entities import DatasetInput, InputTag
    from mlflow.types import Schema, TensorSpec

    from spot.data import registry

    path = Path(cfg.data.name)
    if not path.exists():
        path = registry.dataset_path(cfg.data.name, cfg.data.size, cfg.data.build_seed)
    arrays = [
        (name, getattr(ds, name, None))
        for name in ("observations", "actions", "rewards", "next_observations", "terminals")
    ]
    schema = Schema(
        [TensorSpec(np.dtype(a.dtype), (-1, *a.shape[1:]), name) for name, a in arrays if isinstance(a, np.ndarray)]
    )
    name = str(card.get("name") or cfg.data.name)
    dataset = MetaDataset(
        LocalArtifactDatasetSource(str(path.resolve())), name=name, digest=digest[:DIGEST_CHARS], schema=schema
    )
    tags = [InputTag("mlflow.data.context", "training")]
    _log_inputs_once_inserted(client, run_id, [DatasetInput(dataset._to_mlflow_entity(), tags)])


INPUT_RACE_TRIES = 5


def _log_inputs_once_inserted(client: Any, run_id: str, datasets: list[Any]) -> None:
    """``client.log_inputs``, tried again when a concurrent run inserted the same dataset first.

    MLflow's SQL store looks the dataset (experiment, name, digest) up and inserts it when missing;
    two runs of one sweep starting together both miss it and the second insert fails on the unique
    constraint (session 8: a sweep's second trial died at launch). On retry the row exists and
    MLflow links it to the run. Any other error, or the same one :data:`INPUT_RACE_TRIES` times,
    is raised."""
    from mlflow.exceptions import MlflowException

    for attempt in range(INPUT_RACE_TRIES):
        try:
            client.log_inputs(run_id, datasets=datasets)
            return
        except MlflowException as err:
            text = str(err).lower()  # sqlite: "UNIQUE constraint failed"; postgres: "violates unique constraint"
            if "unique constraint" not in text or "dataset" not in text or attempt == INPUT_RACE_TRIES - 1:
                raise
            time.sleep(0.2 * (attempt + 1))


class SystemMetrics:
    """MLflow's system metrics monitor (CPU, memory, disk, network, GPU if any: ``system/*``) on
    one run, sampled every ``interval`` seconds (``$MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL``,
    default 10). MLflow's monitor logs nothing for a run shorter than one interval; :meth:`stop`
    then logs the samples it took, so every run has at least one point."""

    def __init__(self, run_id: str, tracking_uri: str, interval: float | None = None) -> None:
        import logging

        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        logging.getLogger("mlflow.system_metrics").setLevel(logging.WARNING)  # no start/stop lines per run
        interval = interval or float(os.environ.get("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL", 10))
        self.monitor = SystemMetricsMonitor(run_id, sampling_interval=interval, tracking_uri=tracking_uri)

    def start(self) -> SystemMetrics:
        self.monitor.start()
        return self

    def stop(self) -> None:
        mon = self.monitor
        mon.finish()
        if mon._logging_step == 0:  # nothing published yet: the samples of a short run
            metrics = mon.aggregate_metrics()
            if metrics:
                mon.publish_metrics(metrics)
                mon.mlflow_logger.flush()


LOOKUP_TAGS = ("trial_key", "attempt")
"""The tags sweeps find a run by (finished-run lookups on resume, failure records; stored as
``spot.trial_key`` and ``spot.attempt``, :mod:`spot.tracking.tagnames`). A run is
created without them; they arrive in the same ``log_batch`` as the last of its params
(:func:`create_run`), so a process killed in between leaves a run that no lookup finds (closed
later as a dead process's run), never one that is found without its params."""


def create_run(
    client: Any, experiment_id: str, name: str, tags: dict[str, str], cfg: config_lib.ExperimentConfig
) -> Any:
    """``client.create_run`` with ``tags`` (under their stored names, :mod:`spot.tracking.tagnames`)
    except :data:`LOOKUP_TAGS`; returns the run. Follow it with :func:`log_params` and
    :func:`lookup_tags` of the same ``tags``."""
    lookup = {stored(k) for k in LOOKUP_TAGS}
    return client.create_run(
        experiment_id, run_name=name, tags={k: v for k, v in stored_tags(tags).items() if k not in lookup}
    )


def lookup_tags(tags: dict[str, str]) -> dict[str, str]:
    """The :data:`LOOKUP_TAGS` among ``tags``, under their stored names (they go with the params:
    :func:`log_params`)."""
    lookup = {stored(k) for k in LOOKUP_TAGS}
    return {k: v for k, v in stored_tags(tags).items() if k in lookup}


def log_params(client: Any, run_id: str, cfg: config_lib.ExperimentConfig, tags: dict[str, str] | None = None) -> None:
    """The resolved config as params (flat dotted keys, :func:`active_params`), in batches of
    MLflow's limit; ``tags`` go in the last batch (one request: the store writes both or neither)."""
    from mlflow.entities import Param, RunTag

    flat = active_params(cfg)
    params = [Param(k, str(list(v) if isinstance(v, tuple) else v)) for k, v in flat.items()]
    starts = list(range(0, len(params), 100)) or [0]  # MLflow's limit of params per batch
    for i in starts:
        last = i == starts[-1]
        run_tags_ = [RunTag(k, v) for k, v in stored_tags(tags or {}).items()] if last else []
        client.log_batch(run_id, params=params[i : i + 100], tags=run_tags_)


def record_failure(
    client: Any,
    experiment_id: str,
    cfg: config_lib.ExperimentConfig,
    tags: dict[str, str],
    error: BaseException,
    *,
    parent_run_id: str | None = None,
) -> str | None:
    """Make sure the attempt ``tags['attempt']`` has a FAILED run; return the run created, if any.

    The pipeline's run already ends FAILED when the run failed after it started; this covers a
    failure before that (config, dataset), with the config params, the run tags and the
    ``failure_reason`` tag (capped, :func:`spot.tracking.limits.failure_reason`).
    """
    if first_run(client, experiment_id, {"attempt": get(tags, "attempt")}) is not None:
        return None
    all_tags = run_tags(cfg, {"name": cfg.data.name}, tags)
    all_tags.update(mlflow_tags(cfg, all_tags))
    all_tags["failure_reason"] = failure_reason(error)
    if parent_run_id:
        all_tags["mlflow.parentRunId"] = parent_run_id
    with waiting_on(client_uri(client), "recording a failed run"):
        name = run_name(cfg.method, all_tags["dataset"], cfg.seed, all_tags)
        run = create_run(client, experiment_id, name, all_tags, cfg)
        log_params(client, run.info.run_id, cfg, lookup_tags(all_tags))
        client.set_terminated(run.info.run_id, "FAILED")
    return run.info.run_id


@contextlib.contextmanager
def start_run(
    cfg: config_lib.ExperimentConfig,
    card: dict[str, Any],
    *,
    run_name: str | None = None,
    extra_tags: dict[str, str] | None = None,
    parent_run_id: str | None = None,
    dataset: Any = None,
    system_metrics: bool = True,
) -> Iterator[MlflowTracker]:
    """Open an MLflow run for ``cfg`` and yield its :class:`MlflowTracker`.

    The run gets the tags of :func:`run_tags` and :func:`mlflow_tags` (with ``dataset``: its
    fingerprint as ``data_digest`` and the dataset as a logged input), the active config as params,
    the config YAML, dataset card, package versions and environment as artifacts, and MLflow's
    system metrics while it runs (``system_metrics``). It ends FINISHED, or FAILED (KILLED on
    Ctrl-C) with a ``failure_reason`` tag when the body raises.
    """
    from mlflow.tracking import MlflowClient

    uri = resolve_uri(cfg.tracking.uri)
    prepare_store(uri)  # a new SQLite store is created and migrated by one process at a time
    client = phases.timed_calls(MlflowClient(uri))  # its calls are a sweep trial's 'tracking' phase
    exp_id = experiment_id(cfg.tracking.experiment, uri)
    close_dead_runs(client, [exp_id])  # runs left RUNNING by dead processes of this host
    digest = dataset.fingerprint() if dataset is not None else None
    tags = {**start_tags(cfg, card, extra_tags, parent_run_id, digest), **process_tags()}
    name = run_name or default_name(cfg, tags)
    run = create_run(client, exp_id, name, tags, cfg)
    tracker = MlflowTracker(client, run.info.run_id)
    monitor = SystemMetrics(run.info.run_id, uri).start() if system_metrics else None
    try:
        log_params(client, run.info.run_id, cfg, lookup_tags(tags))
        if digest:
            log_dataset_input(client, run.info.run_id, dataset, card, cfg, digest)
        log_run_files(tracker, cfg, card)
        log_paper_score(tracker, cfg.method, tags["dataset"])
        yield tracker
    except BaseException as e:
        if monitor is not None:
            monitor.stop()
        tracker.set_tags({"failure_reason": failure_reason(e)})
        status = "KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED"
        client.set_terminated(run.info.run_id, status)
        raise
    else:
        if monitor is not None:
            monitor.stop()
        client.set_terminated(run.info.run_id, "FINISHED")
