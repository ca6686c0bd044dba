"""The :class:`Tracker` interface the pipeline writes a run through, and its implementations.

:class:`MlflowTracker` writes to one MLflow run, :class:`MemoryTracker` keeps everything in
memory (tests, dry runs); :class:`spot.tracking.recorded.RecordTracker` writes a record folder.
Metrics are floats without ``None`` and non-finite values (:func:`finite_metrics`); JSON artifacts
are valid JSON (:func:`json_safe`: NaN and infinities become null).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable


def json_safe(data: Any) -> Any:
    """``data`` with NaN and infinities as None (JSON has no NaN; ``json.dumps`` would write a bare
    ``NaN`` that strict readers refuse), numpy scalars and arrays as Python values."""
    if isinstance(data, Mapping):
        return {k: json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_safe(v) for v in data]
    if hasattr(data, "tolist") and not isinstance(data, (str, bytes)):  # numpy arrays and scalars
        return json_safe(data.tolist())
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def finite_metrics(metrics: Mapping[str, Any]) -> dict[str, float]:
    """``metrics`` as floats, without ``None`` and non-finite values (MLflow rejects NaN in JSON
    stores and a NaN metric says nothing a missing one does not)."""
    out = {}
    for k, v in metrics.items():
        if v is None:
            continue
        f = float(v)
        if math.isfinite(f):
            out[k] = f
    return out


@runtime_checkable
class Tracker(Protocol):
    """What the pipeline records about a run. Stage code talks to this, never to a global run.

    :class:`MlflowTracker` is the implementation runs use; :class:`MemoryTracker` keeps everything
    in memory (tests, dry runs).
    """

    run_id: str

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        """Scalars at ``step`` (None: a run-level value); non-finite values are dropped."""

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        """One metric over steps (e.g. a learning curve); non-finite points are dropped."""

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        """A file, stored under its own name (in the artifact folder ``artifact_path`` if given)."""

    def log_dict(self, data: Any, name: str) -> None:
        """A JSON (``.json``, NaN and infinities as null) or YAML (``.yaml``) artifact."""

    def log_text(self, text: str, name: str) -> None:
        """A text artifact."""

    def set_tags(self, tags: Mapping[str, str]) -> None:
        """String tags, named by their bare names (``cache.reward``); MLflow and record folders store
        the bookkeeping ones under ``spot.`` (:mod:`spot.tracking.tagnames`), :class:`MemoryTracker`
        keeps the names given."""


class MemoryTracker:
    """A :class:`Tracker` that keeps metrics, artifacts and tags in dicts (tests, dry runs).

    ``metrics[name]`` is a list of ``(step, value)``; run-level values have step ``None``;
    ``artifacts[name]`` holds the bytes of a logged file (``name`` is ``<artifact_path>/<file>``
    when a folder is given), or the logged dict (as :func:`json_safe` makes it) or text.
    """

    def __init__(self, run_id: str = "memory") -> None:
        self.run_id = run_id
        self.metrics: dict[str, list[tuple[int | None, float]]] = {}
        self.artifacts: dict[str, Any] = {}
        self.tags: dict[str, str] = {}

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        for k, v in finite_metrics(metrics).items():
            self.metrics.setdefault(k, []).append((step, v))

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        for step, value in zip(steps, values, strict=True):
            self.log_metrics({name: value}, step=int(step))

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        name = Path(path).name if artifact_path is None else f"{artifact_path}/{Path(path).name}"
        self.artifacts[name] = Path(path).read_bytes()

    def log_dict(self, data: Any, name: str) -> None:
        self.artifacts[name] = json_safe(data)

    def log_text(self, text: str, name: str) -> None:
        self.artifacts[name] = text

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.tags.update({k: str(v) for k, v in tags.items()})

    def last(self, name: str) -> float:
        """The last value logged for ``name`` (KeyError if none)."""
        return self.metrics[name][-1][1]


class MlflowTracker:
    """A :class:`Tracker` writing to one MLflow run through an ``MlflowClient`` (no active run).

    Metrics are sent in batches (``log_batch``, at most 1000 per request).
    """

    BATCH = 1000

    def __init__(self, client: Any, run_id: str) -> None:
        self.client = client
        self.run_id = run_id

    def _send(self, points: list[tuple[str, float, int]]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        for i in range(0, len(points), self.BATCH):
            batch = [Metric(k, v, now, step) for k, v, step in points[i : i + self.BATCH]]
            self.client.log_batch(self.run_id, metrics=batch)

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        points = [(k, v, step or 0) for k, v in finite_metrics(metrics).items()]
        if points:
            self._send(points)

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        points = [
            (name, v, int(s))
            for s, value in zip(steps, values, strict=True)
            for v in finite_metrics({name: value}).values()
        ]
        if points:
            self._send(points)

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        self.client.log_artifact(self.run_id, str(path), artifact_path)

    def log_dict(self, data: Any, name: str) -> None:
        self.client.log_dict(self.run_id, json_safe(data), name)

    def log_text(self, text: str, name: str) -> None:
        self.client.log_text(self.run_id, text, name)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        from mlflow.entities import RunTag

        from spot.tracking.tagnames import stored_tags

        self.client.log_batch(self.run_id, tags=[RunTag(k, v) for k, v in stored_tags(tags).items()])
