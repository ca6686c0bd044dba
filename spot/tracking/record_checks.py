"""What a run record must be before ``spot results import`` logs it (:mod:`spot.tracking.recorded`).

A record folder (``record.json``, ``metrics.jsonl``, ``artifacts/``: the layout in
:mod:`spot.tracking.recorded`) may come from anywhere, so every record is checked whole before
anything is created in MLflow, and any fault is one :class:`SpotError` naming the file and field:
``record.json`` and ``metrics.jsonl`` are regular files within :data:`MAX_RECORD_BYTES` and
:data:`MAX_METRICS_BYTES`; names and values keep MLflow's limits (``mlflow.utils.validation``); of
MLflow's own ``mlflow.*`` tags only :data:`MLFLOW_TAGS` (what spot's recorder writes) are taken;
metric values are finite numbers, steps 0..2^63-1, and every time lies between 2000 and tomorrow,
the start not after the end. Artifacts are regular files strictly inside ``artifacts/``
(:func:`scan_artifacts`): a symbolic link (to a file, a folder or a device), a FIFO, a socket or a
device is refused, never opened; each file is within :data:`MAX_ARTIFACT_BYTES` and all within
:data:`MAX_ARTIFACTS_BYTES`. :func:`copy_artifacts` opens them without following links and enforces
the limits again while copying (a file may have grown since it was listed). Reading a record parses
JSON and copies files; nothing in it is executed.
"""

from __future__ import annotations

import json
import math
import os
import stat
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spot import SpotError

FORMAT = 1
RECORD_FILE = "record.json"
METRICS_FILE = "metrics.jsonl"
ARTIFACTS_DIR = "artifacts"
STATUSES = ("RUNNING", "FINISHED", "FAILED", "KILLED")


def now_ms() -> int:
    return int(time.time() * 1000)


# --------------------------------------------------------------------------- limits of a record
MAX_RECORD_BYTES = 16 << 20
"""The largest ``record.json`` read (16 MiB: a real one is a few KiB)."""
MAX_METRICS_BYTES = 256 << 20
"""The largest ``metrics.jsonl`` read (256 MiB, about three million points)."""
MAX_ARTIFACT_BYTES = 1 << 30
"""The largest artifact file an import copies (1 GiB), checked from ``lstat`` and again while copying."""
MAX_ARTIFACTS_BYTES = 4 << 30
"""The most artifact bytes one record may hold (4 GiB), checked the same way."""
MAX_ARTIFACT_FILES = 10_000
MAX_ARTIFACT_DEPTH = 32
MIN_TIME_MS = 946_684_800_000
"""2000-01-01T00:00:00Z in ms: no record is older; a smaller time is a unit mistake or forged."""
FUTURE_MS = 86_400_000
"""How far past this machine's clock a record's time may be (one day: the recording machine's
clock may differ from this one's)."""
MAX_STEP = 2**63 - 1
"""MLflow's step is a 64-bit integer."""
MLFLOW_TAGS = ("mlflow.note.content", "mlflow.source.name", "mlflow.source.type", "mlflow.source.git.commit")
"""The ``mlflow.*`` tags a record may carry: those :func:`spot.tracking.provenance.mlflow_tags` writes.
MLflow's other fields (``mlflow.parentRunId``, ``mlflow.user``, ``mlflow.runName``, ...) are refused:
the importer sets them, a record does not (a sweep, whose trials have a parent, may not record)."""
_CHUNK = 1 << 20


def _short(text: str) -> str:
    """``repr`` of a name or value, cut to 60 characters (a 100k-character name stays one short line)."""
    return repr(text) if len(text) <= 60 else f"{text[:60]!r}... ({len(text)} characters)"


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return name
    return "a special file"


def _read_file(path: Path, cap: int) -> bytes:
    """The bytes of ``path``, a regular file of at most ``cap`` bytes (never follows a link or opens
    a FIFO: ``O_NOFOLLOW | O_NONBLOCK``, then ``fstat``)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        raise
    except OSError as e:
        kind = _kind(os.lstat(path).st_mode) if os.path.lexists(path) else ""
        raise SpotError(f"{path}: cannot read it ({kind or e.strerror}; expected a regular file)") from None
    with os.fdopen(fd, "rb") as f:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise SpotError(f"{path}: is {_kind(mode)}, expected a regular file")
        data = f.read(cap + 1)
    if len(data) > cap:
        raise SpotError(f"{path}: larger than {cap} bytes, the most a record's file may hold")
    return data


def _validation() -> Any:
    import mlflow.utils.validation as validation

    return validation


def _check_name(where: str, name: str) -> None:
    """``name`` as MLflow takes a metric, param or tag name (its own rules and length limit)."""
    v = _validation()
    if len(name) > v.MAX_ENTITY_KEY_LENGTH:
        raise SpotError(f"{where} {_short(name)} is longer than MLflow's {v.MAX_ENTITY_KEY_LENGTH} characters")
    if not v.validate_param_and_metric_name(name) or v.path_not_unique(name):
        raise SpotError(
            f"{where} {_short(name)}: MLflow's names are non-empty, use letters, digits and _ - . : / and "
            "space, and are normalized relative paths"
        )


def _check_time(where: str, value: Any) -> None:
    latest = now_ms() + FUTURE_MS
    if not isinstance(value, int) or isinstance(value, bool) or not MIN_TIME_MS <= value <= latest:
        raise SpotError(
            f"{where} is {str(value)[:40]}, expected ms since the epoch between 2000-01-01 and tomorrow "
            f"({MIN_TIME_MS}..{latest})"
        )


def _check_head(path: Path, head: dict[str, Any]) -> None:
    """Times, names, tags and params of a parsed ``record.json`` within what MLflow and spot take."""
    v = _validation()
    for key in ("start_time", "end_time"):
        if head[key] is not None:
            _check_time(f"{path}: field {key!r}", head[key])
    if head["end_time"] is not None and head["end_time"] < head["start_time"]:
        raise SpotError(f"{path}: end_time {head['end_time']} is before start_time {head['start_time']}")
    if len(head["run_name"]) > v.MAX_ENTITY_KEY_LENGTH:
        raise SpotError(
            f"{path}: run_name {_short(head['run_name'])} is longer than {v.MAX_ENTITY_KEY_LENGTH} characters"
        )
    if not head["experiment"].strip() or len(head["experiment"]) > v.MAX_EXPERIMENT_NAME_LENGTH:
        raise SpotError(
            f"{path}: experiment {_short(head['experiment'])}: expected 1 to {v.MAX_EXPERIMENT_NAME_LENGTH} characters"
        )
    for key, limit in (("tags", v.MAX_TAG_VAL_LENGTH), ("params", v.MAX_PARAM_VAL_LENGTH)):
        for name, value in head[key].items():
            _check_name(f"{path}: {key} key", name)
            if len(value) > limit:
                raise SpotError(f"{path}: {key}[{name!r}] has {len(value)} characters, MLflow's limit is {limit}")
    reserved = [k for k in head["tags"] if k.lower().startswith("mlflow.") and k not in MLFLOW_TAGS]
    if reserved:
        raise SpotError(
            f"{path}: tag {reserved[0]!r} is MLflow's own field, which a record may not set "
            f"(of the mlflow.* tags it may carry only {', '.join(MLFLOW_TAGS)})"
        )


# --------------------------------------------------------------------------- reading a record
def read_record(folder: Path) -> dict[str, Any]:
    """The checked ``record.json`` of a record folder (:class:`SpotError` naming the file and field)."""
    path = Path(folder) / RECORD_FILE
    try:
        head = json.loads(_read_file(path, MAX_RECORD_BYTES).decode("utf-8"))
    except OSError as e:
        raise SpotError(f"{path}: cannot read the record ({e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise SpotError(f"{path}: not valid JSON ({str(e)[:200]})") from None
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
        raise SpotError(f"{path}: record_id {_short(head['record_id'])} is not its folder's name {Path(folder).name!r}")
    if head["status"] not in STATUSES:
        raise SpotError(f"{path}: status {_short(head['status'])}, expected one of {', '.join(STATUSES)}")
    for key in ("tags", "params"):
        bad = [k for k, v in head[key].items() if not isinstance(v, str)]
        if bad:
            raise SpotError(f"{path}: {key} values must be strings; {key}[{bad[0]!r}] is {head[key][bad[0]]!r:.60}")
    _check_head(path, head)
    return head


def _point(where: str, p: Any) -> tuple[str, float, int, int]:
    """One checked metric point: an MLflow name, a finite number, a step 0..2^63-1, a sane time."""
    if not isinstance(p, dict) or not {"key", "value", "step", "timestamp"} <= set(p) or not isinstance(p["key"], str):
        raise SpotError(f"{where} is not a metric point {{key, value, step, timestamp}}")
    key, value, step = p["key"], p["value"], p["step"]
    _check_name(f"{where}: metric key", key)
    try:
        number = float(value) if isinstance(value, int | float) and not isinstance(value, bool) else math.nan
    except OverflowError:
        number = math.nan
    if not math.isfinite(number):
        raise SpotError(f"{where}: metric {key!r} has value {str(value)[:40]!r}, expected a finite number")
    if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step <= MAX_STEP:
        raise SpotError(f"{where}: metric {key!r} has step {str(step)[:40]!r}, expected an integer 0..{MAX_STEP}")
    _check_time(f"{where}: metric {key!r} timestamp", p["timestamp"])
    return key, number, step, p["timestamp"]


def read_metrics(folder: Path) -> list[tuple[str, float, int, int]]:
    """``(key, value, step, timestamp)`` of every metric point of a record; a last line cut short
    by a killed process is ignored, any other bad line is a :class:`SpotError`."""
    path = Path(folder) / METRICS_FILE
    try:
        data = _read_file(path, MAX_METRICS_BYTES)
    except FileNotFoundError:
        return []
    except OSError as e:
        raise SpotError(f"{path}: cannot read the metrics ({e})") from None
    lines = data.decode("utf-8", errors="replace").split("\n")
    points = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            p = json.loads(line)
        except (json.JSONDecodeError, RecursionError) as e:
            if i == len(lines):
                break  # no newline after it: the line being written when the process died
            raise SpotError(
                f"{path}: line {i} is not a metric point {{key, value, step, timestamp}} ({str(e)[:100]})"
            ) from None
        points.append(_point(f"{path}: line {i}", p))
    return points


def find_records(root: Path) -> list[Path]:
    """The record folders under ``root`` (itself, or its sub-folders holding a ``record.json``);
    a sub-folder that is a symbolic link is refused (an import copies only what is inside)."""
    root = Path(root)
    if not root.is_dir():
        raise SpotError(f"records folder {root} does not exist")
    if os.path.lexists(root / RECORD_FILE):
        return [root]
    folders = sorted(p.parent for p in root.glob(f"*/{RECORD_FILE}"))
    for folder in folders:
        if folder.is_symlink():
            raise SpotError(f"record {folder}: is a symbolic link; a record folder must be a folder inside {root}")
    return folders


def scan_artifacts(folder: Path) -> list[str]:
    """The artifacts of a record, as paths relative to its ``artifacts/`` folder: regular files only
    (a link, FIFO, socket or device is a :class:`SpotError` naming it), within
    :data:`MAX_ARTIFACT_BYTES` each and :data:`MAX_ARTIFACTS_BYTES` in all. Reads no file."""
    top = Path(folder) / ARTIFACTS_DIR
    try:
        mode = os.lstat(top).st_mode
    except FileNotFoundError:
        return []
    if not stat.S_ISDIR(mode):
        raise SpotError(f"record {folder}: {ARTIFACTS_DIR} is {_kind(mode)}, expected a folder")
    files: list[str] = []
    total, stack = 0, [("", 0)]
    while stack:
        prefix, depth = stack.pop()
        try:
            with os.scandir(top / prefix) as it:
                entries = sorted(((e.name, e.stat(follow_symlinks=False)) for e in it), key=lambda x: x[0])
        except OSError as e:
            raise SpotError(f"record {folder}: cannot list artifacts {prefix or '.'!r} ({e.strerror})") from None
        for name, st in entries:
            rel = f"{prefix}{name}"
            if stat.S_ISDIR(st.st_mode):
                if depth + 1 >= MAX_ARTIFACT_DEPTH:
                    raise SpotError(
                        f"record {folder}: artifact folder {_short(rel)} is nested deeper than {MAX_ARTIFACT_DEPTH}"
                    )
                stack.append((f"{rel}/", depth + 1))
                continue
            if not stat.S_ISREG(st.st_mode):
                raise SpotError(
                    f"record {folder}: artifact {_short(rel)} is {_kind(st.st_mode)}; only regular files "
                    "inside the record's artifacts folder are imported"
                )
            total += st.st_size
            files.append(rel)
            for over, what in (
                (st.st_size > MAX_ARTIFACT_BYTES, f"is {st.st_size} bytes, over {MAX_ARTIFACT_BYTES} bytes a file"),
                (total > MAX_ARTIFACTS_BYTES, f"brings the artifacts over {MAX_ARTIFACTS_BYTES} bytes a record"),
                (len(files) > MAX_ARTIFACT_FILES, f"brings the artifacts over {MAX_ARTIFACT_FILES} files a record"),
            ):
                if over:
                    raise SpotError(f"record {folder}: artifact {_short(rel)} {what}")
    return sorted(files)


def _open_artifact(folder: Path, rel: str) -> int:
    """A descriptor of artifact ``rel`` opened without following a link at any level."""
    fd = os.open(Path(folder) / ARTIFACTS_DIR, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    try:
        *parts, name = rel.split("/")
        for part in parts:
            inner = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW, dir_fd=fd)
            os.close(fd)
            fd = inner
        return os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=fd)
    finally:
        os.close(fd)


def copy_artifacts(folder: Path, files: Sequence[str], dest: Path) -> None:
    """Copy the artifacts ``files`` (:func:`scan_artifacts`) of a record into ``dest``, each opened
    without following links and checked a regular file, the size limits enforced while copying (a
    file may have grown, or been replaced, since it was listed)."""
    total = 0
    for rel in files:
        try:
            fd = _open_artifact(folder, rel)
        except OSError as e:
            raise SpotError(
                f"record {folder}: artifact {_short(rel)} cannot be opened as a regular file inside the record "
                f"({e.strerror})"
            ) from None
        with os.fdopen(fd, "rb") as src:
            mode = os.fstat(fd).st_mode
            if not stat.S_ISREG(mode):
                raise SpotError(
                    f"record {folder}: artifact {_short(rel)} is {_kind(mode)}; only regular files are imported"
                )
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            size = 0
            with open(target, "wb") as out:
                while chunk := src.read(_CHUNK):
                    size, total = size + len(chunk), total + len(chunk)
                    if size > MAX_ARTIFACT_BYTES or total > MAX_ARTIFACTS_BYTES:
                        raise SpotError(
                            f"record {folder}: artifact {_short(rel)} grew past the limit of {MAX_ARTIFACT_BYTES} "
                            f"bytes a file or {MAX_ARTIFACTS_BYTES} bytes a record while it was copied"
                        )
                    out.write(chunk)
