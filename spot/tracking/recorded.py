"""Runs recorded as plain files where no MLflow store is at hand, and imported into one later.

A machine without MLflow or without a way to reach the team's store (an offline GPU node, a batch
job in a sandbox) records each run as a folder (``tracking.record=DIR``, ``spot run --record DIR``)::

    DIR/<record_id>/record.json     format, record_id, experiment, run_name, status, start_time,
                                    end_time (ms since the epoch), tags, params
    DIR/<record_id>/metrics.jsonl   one metric point per line: {"key", "value", "step", "timestamp"}
    DIR/<record_id>/artifacts/...   the run's artifacts, as MLflow would store them

The record holds exactly what :func:`spot.tracking.record.start_run` logs to MLflow (the same
tags, params and artifacts; not MLflow's system metrics or the dataset as a logged input, which
need a store). ``record.json`` is rewritten atomically at the start and at the end (status
``RUNNING``, then ``FINISHED``, ``FAILED`` or ``KILLED`` with a ``failure_reason`` tag), and each
metric point is appended as it is logged, so a killed run leaves its curve so far.

:func:`import_records` (``spot results import DIR``) logs every finished record into an MLflow
experiment as a run with the record's own start and end times, metric timestamps and steps, then
tags it ``spot.record_id`` last (the record's tags under the names of
:mod:`spot.tracking.tagnames`, also those of a record written before the bookkeeping tags moved
under ``spot.``): importing again skips the records already there, so an interrupted import
resumes without duplicating runs (a run it was writing is deleted; one a SIGKILL left RUNNING is
closed as KILLED by the next import and has no ``spot.record_id``). Records still
``RUNNING`` (the run goes on, or its process was killed) are skipped and listed. Reading a
record parses JSON and copies files; nothing in it is executed.

A record may come from anywhere, so every record is checked whole (:mod:`spot.tracking.record_checks`)
before anything is created in MLflow. Its artifacts are copied to a temporary folder before the run
is created; a run that cannot then be logged whole is deleted, so a failed import leaves no run and
the record is not marked imported.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from spot import SpotError
from spot import config as config_lib
from spot.tracking import record_checks as checks
from spot.tracking.limits import failure_reason
from spot.tracking.naming import default_name, log_paper_score
from spot.tracking.provenance import active_params, log_run_files, start_tags
from spot.tracking.record_checks import ARTIFACTS_DIR, FORMAT, METRICS_FILE, RECORD_FILE, now_ms
from spot.tracking.tagnames import normalized, stored, stored_tags
from spot.tracking.trackers import finite_metrics, json_safe

RECORD_TAG = stored("record_id")
"""The tag an imported run carries: the record it came from (what a second import looks for; runs
imported before the bookkeeping tags moved under ``spot.`` carry ``record_id``)."""


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(json_safe(data), indent=1, sort_keys=True))
    tmp.replace(path)


class RecordTracker:
    """A :class:`spot.tracking.trackers.Tracker` writing one run's record folder (module docstring)."""

    def __init__(self, folder: Path, head: dict[str, Any]) -> None:
        self.folder = Path(folder)
        self.run_id = self.folder.name
        self.head = head
        (self.folder / ARTIFACTS_DIR).mkdir(parents=True, exist_ok=True)
        self._metrics = open(self.folder / METRICS_FILE, "a", encoding="utf-8")  # noqa: SIM115 - closed by close()
        self.save()

    def save(self) -> None:
        _write_json(self.folder / RECORD_FILE, self.head)

    def close(self, status: str) -> None:
        self.head["status"], self.head["end_time"] = status, now_ms()
        self._metrics.close()
        self.save()

    def _points(self, points: Sequence[tuple[str, float, int]]) -> None:
        now = now_ms()
        for key, value, step in points:
            line = {"key": key, "value": value, "step": int(step), "timestamp": now}
            self._metrics.write(json.dumps(line) + "\n")
        self._metrics.flush()

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        self._points([(k, v, step or 0) for k, v in finite_metrics(metrics).items()])

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        self._points(
            [
                (name, v, int(s))
                for s, value in zip(steps, values, strict=True)
                for v in finite_metrics({name: value}).values()
            ]
        )

    def _artifact_path(self, name: str) -> Path:
        path = (self.folder / ARTIFACTS_DIR / name).resolve()
        if not path.is_relative_to((self.folder / ARTIFACTS_DIR).resolve()):
            raise SpotError(f"record {self.folder}: artifact name {name!r} leaves the record's artifacts folder")
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        name = Path(path).name if artifact_path is None else f"{artifact_path}/{Path(path).name}"
        shutil.copyfile(path, self._artifact_path(name))

    def log_dict(self, data: Any, name: str) -> None:
        self._artifact_path(name).write_text(json.dumps(json_safe(data), indent=2))

    def log_text(self, text: str, name: str) -> None:
        self._artifact_path(name).write_text(text)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.head["tags"].update(stored_tags(tags))
        self.save()


@contextlib.contextmanager
def start_record(
    cfg: config_lib.ExperimentConfig,
    card: dict[str, Any],
    *,
    run_name: str | None = None,
    extra_tags: dict[str, str] | None = None,
    parent_run_id: str | None = None,
    dataset: Any = None,
) -> Iterator[RecordTracker]:
    """:func:`spot.tracking.record.start_run`'s twin: a new record folder under ``cfg.tracking.record``
    with the same tags, params and artifacts; yields its :class:`RecordTracker`."""
    root = Path(cfg.tracking.record).expanduser()
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SpotError(f"tracking.record: cannot make the folder {root} ({e})") from None
    digest = dataset.fingerprint() if dataset is not None else None
    tags = start_tags(cfg, card, extra_tags, parent_run_id, digest)
    record_id = uuid.uuid4().hex
    head = {
        "format": FORMAT,
        "record_id": record_id,
        "experiment": cfg.tracking.experiment,
        "run_name": run_name or default_name(cfg, tags),
        "status": "RUNNING",
        "start_time": now_ms(),
        "end_time": None,
        "tags": stored_tags(tags),
        "params": {k: str(list(v) if isinstance(v, tuple) else v) for k, v in active_params(cfg).items()},
    }
    tracker = RecordTracker(root / record_id, head)
    try:
        log_run_files(tracker, cfg, card)
        log_paper_score(tracker, cfg.method, tags["dataset"])
        yield tracker
    except BaseException as e:
        tracker.head["tags"]["failure_reason"] = failure_reason(e)
        tracker.close("KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED")
        raise
    else:
        tracker.close("FINISHED")


def _imported(client: Any, exp_id: str, record_id: str) -> str | None:
    from spot.tracking.queries import first_run

    run = first_run(client, exp_id, {RECORD_TAG: record_id})
    return run.info.run_id if run is not None else None


def _log_record(client: Any, exp_id: str, folder: Path, head: dict[str, Any], points: list, staged: Path | None) -> str:
    """Create the run of a checked record and log it whole; a run that could not be logged whole is
    deleted (the record stays not imported: the next import logs it). Returns the run id."""
    from mlflow.entities import Metric, Param, RunTag

    from spot.tracking.processes import process_tags

    rid = head["record_id"]
    tags = {k: v for k, v in normalized(head["tags"]).items() if k != RECORD_TAG}  # a record's old names too
    run = client.create_run(
        exp_id, start_time=head["start_time"], run_name=head["run_name"], tags={**tags, **process_tags()}
    )
    run_id = run.info.run_id
    try:
        params = [Param(k, v) for k, v in head["params"].items()]
        for i in range(0, len(params), 100):
            client.log_batch(run_id, params=params[i : i + 100])
        metrics = [Metric(k, v, t, s) for k, v, s, t in points]
        for i in range(0, len(metrics), 1000):
            client.log_batch(run_id, metrics=metrics[i : i + 1000])
        if staged is not None:
            client.log_artifacts(run_id, str(staged))
        tags_last = [RunTag(RECORD_TAG, rid), RunTag(stored("imported_from"), str(folder.resolve()))]
        client.log_batch(run_id, tags=tags_last)
        client.set_terminated(run_id, head["status"], end_time=head["end_time"] or head["start_time"])
    except BaseException:  # a half-imported run is removed; the next import logs the record whole
        client.delete_run(run_id)
        raise
    return run_id


def import_records(
    root: str | Path, tracking_uri: str | None = None, experiment: str | None = None
) -> list[dict[str, str]]:
    """Log the finished records under ``root`` into MLflow (module docstring). ``experiment``
    replaces each record's own experiment name. Returns one ``{record_id, run_id, action}`` per
    record, action ``imported``, ``already imported`` or ``skipped: ...``."""
    from mlflow.tracking import MlflowClient

    from spot.tracking.processes import close_dead_runs
    from spot.tracking.store import experiment_id, resolve_uri

    folders = checks.find_records(Path(root))
    if not folders:
        raise SpotError(f"records folder {root}: no record (a {RECORD_FILE} in it or in its sub-folders)")
    checked = []  # every record checked (fields, metric points, artifact files) before anything is created
    for folder in folders:
        head = checks.read_record(folder)
        files = checks.scan_artifacts(folder) if head["status"] != "RUNNING" else []
        checked.append((folder, head, checks.read_metrics(folder), files))
    uri = resolve_uri(tracking_uri)
    client = MlflowClient(uri)
    out = []
    for folder, head, points, files in checked:
        rid = head["record_id"]
        if head["status"] == "RUNNING":
            out.append({"record_id": rid, "run_id": "", "action": "skipped: still RUNNING (running, or killed)"})
            continue
        exp_id = experiment_id(experiment or head["experiment"], uri)
        close_dead_runs(client, [exp_id], report=False)  # runs of an import killed on this host
        found = _imported(client, exp_id, rid)
        if found:
            out.append({"record_id": rid, "run_id": found, "action": "already imported"})
            continue
        with tempfile.TemporaryDirectory(prefix="spot-import-") as tmp:
            staged = Path(tmp) / ARTIFACTS_DIR if files else None
            if staged is not None:  # copied (links refused, sizes capped) before the run is created
                checks.copy_artifacts(folder, files, staged)
            run_id = _log_record(client, exp_id, folder, head, points, staged)
        out.append({"record_id": rid, "run_id": run_id, "action": "imported"})
    return out


def records_summary(root: str | Path) -> list[dict[str, Any]]:
    """One line per record: id, experiment, run name, status and its last ``eval/score_final``."""
    rows = []
    for folder in checks.find_records(Path(root)):
        head = checks.read_record(folder)
        final = [v for k, v, _, _ in checks.read_metrics(folder) if k == "eval/score_final"]
        rows.append(
            {
                "record_id": head["record_id"],
                "experiment": head["experiment"],
                "run_name": head["run_name"],
                "status": head["status"],
                "score_final": final[-1] if final else None,
            }
        )
    return rows
