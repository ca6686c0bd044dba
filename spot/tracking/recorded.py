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
tags it ``record_id`` last: importing again skips the records already there, so an interrupted
import resumes without duplicating runs (a run it was writing is deleted; one a SIGKILL left
RUNNING is closed as KILLED by the next import and has no ``record_id``). Records still
``RUNNING`` (the run goes on, or its process was killed) are skipped and listed. Reading a
record parses JSON and copies files; nothing in it is executed.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
import uuid
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from spot import SpotError
from spot import config as config_lib
from spot.tracking import record as rec

FORMAT = 1
RECORD_FILE = "record.json"
METRICS_FILE = "metrics.jsonl"
ARTIFACTS_DIR = "artifacts"
RECORD_TAG = "record_id"
"""The tag an imported run carries: the record it came from (what a second import looks for)."""
STATUSES = ("RUNNING", "FINISHED", "FAILED", "KILLED")


def _now_ms() -> int:
    return int(time.time() * 1000)


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(rec.json_safe(data), indent=1, sort_keys=True))
    tmp.replace(path)


class RecordTracker:
    """A :class:`spot.tracking.record.Tracker` writing one run's record folder (module docstring)."""

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
        self.head["status"], self.head["end_time"] = status, _now_ms()
        self._metrics.close()
        self.save()

    def _points(self, points: Sequence[tuple[str, float, int]]) -> None:
        now = _now_ms()
        for key, value, step in points:
            line = {"key": key, "value": value, "step": int(step), "timestamp": now}
            self._metrics.write(json.dumps(line) + "\n")
        self._metrics.flush()

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        self._points([(k, v, step or 0) for k, v in rec.finite_metrics(metrics).items()])

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        self._points(
            [
                (name, v, int(s))
                for s, value in zip(steps, values, strict=True)
                for v in rec.finite_metrics({name: value}).values()
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
        self._artifact_path(name).write_text(json.dumps(rec.json_safe(data), indent=2))

    def log_text(self, text: str, name: str) -> None:
        self._artifact_path(name).write_text(text)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.head["tags"].update({k: str(v) for k, v in tags.items()})
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
    tags = rec.start_tags(cfg, card, extra_tags, parent_run_id, digest)
    record_id = uuid.uuid4().hex
    head = {
        "format": FORMAT,
        "record_id": record_id,
        "experiment": cfg.tracking.experiment,
        "run_name": run_name or f"{cfg.method}-{tags['dataset']}-s{cfg.seed}",
        "status": "RUNNING",
        "start_time": _now_ms(),
        "end_time": None,
        "tags": tags,
        "params": {k: str(list(v) if isinstance(v, tuple) else v) for k, v in rec.active_params(cfg).items()},
    }
    tracker = RecordTracker(root / record_id, head)
    try:
        rec.log_run_files(tracker, cfg, card)
        yield tracker
    except BaseException as e:
        tracker.head["tags"]["failure_reason"] = f"{type(e).__name__}: {e}"[:4000]
        tracker.close("KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED")
        raise
    else:
        tracker.close("FINISHED")


# --------------------------------------------------------------------------- reading and importing
def read_record(folder: Path) -> dict[str, Any]:
    """The checked ``record.json`` of a record folder (:class:`SpotError` naming the file and field)."""
    path = Path(folder) / RECORD_FILE
    try:
        head = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise SpotError(f"{path}: cannot read the record ({e})") from None
    except json.JSONDecodeError as e:
        raise SpotError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(head, dict):
        raise SpotError(f"{path}: expected a JSON object, got {type(head).__name__}")
    expect: dict[str, tuple[type, ...]] = {
        "format": (int,),
        "record_id": (str,),
        "experiment": (str,),
        "run_name": (str,),
        "status": (str,),
        "start_time": (int,),
        "end_time": (int, type(None)),
        "tags": (dict,),
        "params": (dict,),
    }
    for key, types in expect.items():
        if key not in head:
            raise SpotError(f"{path}: field {key!r} is missing")
        if not isinstance(head[key], types) or isinstance(head[key], bool):
            names = " or ".join("null" if t is type(None) else t.__name__ for t in types)
            raise SpotError(f"{path}: field {key!r} should be {names}, got {head[key]!r:.60}")
    if head["format"] != FORMAT:
        raise SpotError(f"{path}: record format {head['format']}, this spot reads format {FORMAT}")
    if head["record_id"] != Path(folder).name:
        raise SpotError(f"{path}: record_id {head['record_id']!r} is not its folder's name {Path(folder).name!r}")
    if head["status"] not in STATUSES:
        raise SpotError(f"{path}: status {head['status']!r}, expected one of {', '.join(STATUSES)}")
    for key in ("tags", "params"):
        bad = [k for k, v in head[key].items() if not isinstance(v, str)]
        if bad:
            raise SpotError(f"{path}: {key} values must be strings; {key}[{bad[0]!r}] is {head[key][bad[0]]!r:.60}")
    return head


def read_metrics(folder: Path) -> list[tuple[str, float, int, int]]:
    """``(key, value, step, timestamp)`` of every metric point of a record; a last line cut short
    by a killed process is ignored, any other bad line is a :class:`SpotError`."""
    path = Path(folder) / METRICS_FILE
    if not path.exists():
        return []
    lines = path.read_text(encoding="utf-8").split("\n")
    points = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            p = json.loads(line)
            points.append((str(p["key"]), float(p["value"]), int(p["step"]), int(p["timestamp"])))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            if i == len(lines) and not path.read_bytes().endswith(b"\n"):
                break  # the line being written when the process died
            raise SpotError(f"{path}: line {i} is not a metric point {{key, value, step, timestamp}} ({e})") from None
    return points


def find_records(root: Path) -> list[Path]:
    """The record folders under ``root`` (itself, or its sub-folders holding a ``record.json``)."""
    root = Path(root)
    if not root.is_dir():
        raise SpotError(f"records folder {root} does not exist")
    if (root / RECORD_FILE).exists():
        return [root]
    return sorted(p.parent for p in root.glob(f"*/{RECORD_FILE}"))


def _imported(client: Any, exp_id: str, record_id: str) -> str | None:
    from spot.tracking.queries import first_run

    run = first_run(client, exp_id, {RECORD_TAG: record_id})
    return run.info.run_id if run is not None else None


def import_records(
    root: str | Path, tracking_uri: str | None = None, experiment: str | None = None
) -> list[dict[str, str]]:
    """Log the finished records under ``root`` into MLflow (module docstring). ``experiment``
    replaces each record's own experiment name. Returns one ``{record_id, run_id, action}`` per
    record, action ``imported``, ``already imported`` or ``skipped: ...``."""
    from mlflow.entities import Metric, Param, RunTag
    from mlflow.tracking import MlflowClient

    from spot.tracking.processes import close_dead_runs, process_tags
    from spot.tracking.store import experiment_id, resolve_uri

    folders = find_records(Path(root))
    if not folders:
        raise SpotError(f"records folder {root}: no record (a {RECORD_FILE} in it or in its sub-folders)")
    heads = [(folder, read_record(folder)) for folder in folders]  # every record checked before any import
    for folder, _ in heads:
        read_metrics(folder)
    uri = resolve_uri(tracking_uri)
    client = MlflowClient(uri)
    out = []
    for folder, head in heads:
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
        tags = {k: v for k, v in head["tags"].items() if k != RECORD_TAG}
        run = client.create_run(
            exp_id, start_time=head["start_time"], run_name=head["run_name"], tags={**tags, **process_tags()}
        )
        run_id = run.info.run_id
        try:
            params = [Param(k, v) for k, v in head["params"].items()]
            for i in range(0, len(params), 100):
                client.log_batch(run_id, params=params[i : i + 100])
            metrics = [Metric(k, v, t, s) for k, v, s, t in read_metrics(folder)]
            for i in range(0, len(metrics), 1000):
                client.log_batch(run_id, metrics=metrics[i : i + 1000])
            artifacts = folder / ARTIFACTS_DIR
            if artifacts.is_dir() and any(artifacts.iterdir()):
                client.log_artifacts(run_id, str(artifacts))
            tags_last = [RunTag(RECORD_TAG, rid), RunTag("imported_from", str(folder.resolve()))]
            client.log_batch(run_id, tags=tags_last)
            client.set_terminated(run_id, head["status"], end_time=head["end_time"] or head["start_time"])
        except BaseException:  # a half-imported run is removed; the next import logs the record whole
            client.delete_run(run_id)
            raise
        out.append({"record_id": rid, "run_id": run_id, "action": "imported"})
    return out


def records_summary(root: str | Path) -> list[dict[str, Any]]:
    """One line per record: id, experiment, run name, status and its last ``eval/score_final``."""
    rows = []
    for folder in find_records(Path(root)):
        head = read_record(folder)
        final = [v for k, v, _, _ in read_metrics(folder) if k == "eval/score_final"]
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
