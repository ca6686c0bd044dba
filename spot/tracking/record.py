"""What every run records, and how a failed run is marked.

Every run logs the full resolved config as params (flat dotted keys), tags naming the method,
dataset, dataset source, label source, seed, budget, git commit and package versions, and the
config YAML as an artifact. The pipeline writes through the :class:`Tracker` interface;
:class:`MlflowTracker` is its MLflow implementation, :class:`MemoryTracker` an in-memory one.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import math
import subprocess
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from spot import config as config_lib
from spot.tracking.store import experiment_id, resolve_uri

PACKAGES = ("spot-pbrl", "jax", "jaxlib", "flax", "optax", "numpy", "mujoco", "gymnasium",
            "metaworld", "robosuite", "mlflow", "ray", "h5py")


@functools.cache
def git_commit() -> str:
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        commit = out.stdout.strip() or "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@functools.cache
def package_versions() -> dict[str, str]:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def run_tags(cfg: config_lib.ExperimentConfig, card: dict[str, Any], extra: dict[str, str] | None = None) -> dict[str, str]:
    tags = {
        "method": cfg.method,
        "dataset": str(card.get("name", cfg.data.name)),
        "dataset_source": str(card.get("source", "unknown")),
        "dataset_size": str(card.get("size", "file")),
        "label_source": cfg.labels.source if cfg.reward.kind != "none" else "none",
        "seed": str(cfg.seed),
        "budget": cfg.budget,
        "git_commit": git_commit(),
    }
    tags.update({f"version.{k}": v for k, v in package_versions().items()})
    tags.update(extra or {})
    return tags


# --------------------------------------------------------------------------- the tracker interface
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

    def log_artifact(self, path: Path) -> None:
        """A file, stored under its own name."""

    def log_dict(self, data: Any, name: str) -> None:
        """A JSON (``.json``) or YAML (``.yaml``) artifact."""

    def log_text(self, text: str, name: str) -> None:
        """A text artifact."""

    def set_tags(self, tags: Mapping[str, str]) -> None:
        """String tags."""


class MemoryTracker:
    """A :class:`Tracker` that keeps metrics, artifacts and tags in dicts (tests, dry runs).

    ``metrics[name]`` is a list of ``(step, value)``; run-level values have step ``None``;
    ``artifacts[name]`` holds the bytes of a logged file, or the logged dict/text.
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

    def log_artifact(self, path: Path) -> None:
        self.artifacts[Path(path).name] = Path(path).read_bytes()

    def log_dict(self, data: Any, name: str) -> None:
        self.artifacts[name] = data

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
            batch = [Metric(k, v, now, step) for k, v, step in points[i:i + self.BATCH]]
            self.client.log_batch(self.run_id, metrics=batch)

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        points = [(k, v, step or 0) for k, v in finite_metrics(metrics).items()]
        if points:
            self._send(points)

    def log_series(self, name: str, steps: Sequence[int], values: Sequence[Any]) -> None:
        points = [(name, v, int(s)) for s, value in zip(steps, values, strict=True)
                  for v in finite_metrics({name: value}).values()]
        if points:
            self._send(points)

    def log_artifact(self, path: Path) -> None:
        self.client.log_artifact(self.run_id, str(path))

    def log_dict(self, data: Any, name: str) -> None:
        self.client.log_dict(self.run_id, data, name)

    def log_text(self, text: str, name: str) -> None:
        self.client.log_text(self.run_id, text, name)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        from mlflow.entities import RunTag

        self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


def log_params(client: Any, run_id: str, cfg: config_lib.ExperimentConfig) -> None:
    """The full resolved config as params (flat dotted keys), in batches of MLflow's limit."""
    from mlflow.entities import Param

    flat = config_lib.to_flat(cfg)
    params = [Param(k, str(list(v) if isinstance(v, tuple) else v)) for k, v in flat.items()]
    for i in range(0, len(params), 100):  # MLflow's limit of params per batch
        client.log_batch(run_id, params=params[i:i + 100])


@contextlib.contextmanager
def start_run(cfg: config_lib.ExperimentConfig, card: dict[str, Any], *, run_name: str | None = None,
              extra_tags: dict[str, str] | None = None,
              parent_run_id: str | None = None) -> Iterator[MlflowTracker]:
    """Open an MLflow run for ``cfg`` and yield its :class:`MlflowTracker`.

    The run gets the tags of :func:`run_tags`, the full resolved config as params, and the config
    YAML, dataset card and package versions as artifacts. It ends FINISHED, or FAILED (KILLED on
    Ctrl-C) with a ``failure_reason`` tag when the body raises.
    """
    from mlflow.tracking import MlflowClient

    uri = resolve_uri(cfg.tracking.uri)
    client = MlflowClient(uri)
    exp_id = experiment_id(cfg.tracking.experiment, uri)
    tags = run_tags(cfg, card, extra_tags)
    tags["mlflow.source.name"] = "spot"
    tags["mlflow.source.git.commit"] = tags["git_commit"]
    if parent_run_id:
        tags["mlflow.parentRunId"] = parent_run_id
    name = run_name or f"{cfg.method}-{tags['dataset']}-s{cfg.seed}"
    run = client.create_run(exp_id, run_name=name, tags=tags)
    tracker = MlflowTracker(client, run.info.run_id)
    try:
        log_params(client, run.info.run_id, cfg)
        tracker.log_text(config_lib.to_yaml(cfg), "config.yaml")
        tracker.log_dict(card, "dataset_card.json")
        tracker.log_dict(package_versions(), "package_versions.json")
        yield tracker
    except BaseException as e:
        tracker.set_tags({"failure_reason": f"{type(e).__name__}: {e}"[:4000]})
        status = "KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED"
        client.set_terminated(run.info.run_id, status)
        raise
    else:
        client.set_terminated(run.info.run_id, "FINISHED")
