"""What every run records, and how a failed run is marked.

Every run logs its resolved config as params (flat dotted keys; the model sections of other
methods, ``mr.*``, ``pt.*``, ``hpl.*``, ``ipl.*``, are left out: :func:`active_params`), tags
naming the method, dataset, dataset source, label source, seed, budget, git commit, package
versions and the dataset fingerprint (``data_digest``), and MLflow's own fields: a description
(``mlflow.note.content``: method, dataset, budget, sweep, the command line and a ``spot run``
command that reproduces the config), ``mlflow.source.name`` (the command), ``mlflow.source.type``,
``mlflow.source.git.commit``, the dataset as a logged input (:func:`log_dataset_input`) and
MLflow's system metrics (``system/*``, :class:`SystemMetrics`). Artifacts: the config YAML, the
dataset card, package versions and the environment (``environment.json``, ``requirements.txt``).
JSON artifacts are valid JSON (:func:`json_safe`: NaN and infinities become null).

The pipeline writes through the :class:`Tracker` interface; :class:`MlflowTracker` is its MLflow
implementation, :class:`MemoryTracker` an in-memory one. A run that fails inside :func:`start_run`
ends FAILED with a ``failure_reason``; :func:`record_failure` gives an attempt that failed before
its run opened (config, dataset) a FAILED run of its own.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from spot import config as config_lib
from spot import phases, runtime
from spot.tracking.limits import failure_reason, waiting_on
from spot.tracking.locking import prepare_store
from spot.tracking.processes import close_dead_runs, process_tags
from spot.tracking.queries import client_uri, first_run
from spot.tracking.store import experiment_id, resolve_uri

PACKAGES = (
    "spot-pbrl",
    "jax",
    "jaxlib",
    "flax",
    "optax",
    "numpy",
    "mujoco",
    "gymnasium",
    "metaworld",
    "robosuite",
    "mlflow",
    "ray",
    "h5py",
)


GIT_COMMIT_ENV = "SPOT_GIT_COMMIT"
"""Names the commit of a copy of the code whose own ``.git`` cannot say it (a working tree copied
to a GPU node or a container, without ``.git`` or with an older one); when set, it wins."""


@functools.cache
def git_commit() -> str:
    """``$SPOT_GIT_COMMIT`` when set; else ``git rev-parse HEAD`` of spot's checkout (``-dirty``
    with uncommitted changes to tracked files), ``unknown`` outside a checkout."""
    here = Path(__file__).resolve().parent
    given = os.environ.get(GIT_COMMIT_ENV, "").strip()
    if given:
        return given
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        if out.returncode != 0 or not out.stdout.strip():
            return "unknown"
        commit = out.stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def commit_hash() -> str | None:
    """The bare commit hash of :func:`git_commit` (no ``-dirty``), or None outside a git checkout."""
    commit = git_commit().removesuffix("-dirty")
    return None if commit == "unknown" else commit


@functools.cache
def package_versions() -> dict[str, str]:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def run_tags(
    cfg: config_lib.ExperimentConfig, card: dict[str, Any], extra: dict[str, str] | None = None
) -> dict[str, str]:
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


# --------------------------------------------------------------------------- MLflow's own fields
COMMAND_ENV = "SPOT_COMMAND"
"""Environment variable holding the ``spot`` command line (set by :func:`spot.cli.main`; inherited
by the processes a sweep starts on this machine, whose own ``sys.argv`` is Ray's worker)."""

# The model sections only one reward.kind reads; a run logs the one of its kind (all for a kind
# registered by a plugin, which may read any of them).
MODEL_SECTIONS = ("mr", "pt", "hpl", "ipl")


def command_line() -> str:
    """The command that started this process: ``$SPOT_COMMAND``, else ``sys.argv``."""
    return os.environ.get(COMMAND_ENV) or shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])


def active_params(cfg: config_lib.ExperimentConfig) -> dict[str, Any]:
    """The flat config without the model sections of other methods (``mr.*``, ``pt.*``, ``hpl.*``,
    ``ipl.*`` but the run's own ``reward.kind``); the full config is the ``config.yaml`` artifact."""
    kind = cfg.reward.kind
    drop = set(MODEL_SECTIONS) - {kind} if kind in (*MODEL_SECTIONS, "none") else set()
    return {k: v for k, v in config_lib.to_flat(cfg).items() if k.split(".", 1)[0] not in drop}


def _override_text(key: str, value: Any) -> str:
    text = json.dumps(list(value)) if isinstance(value, (tuple, list)) else str(value)
    return shlex.quote(f"{key}={text}")


def reproduce_command(cfg: config_lib.ExperimentConfig) -> str:
    """A ``spot run`` command line whose config resolves to ``cfg`` (tracking keys aside): the
    method, budget, variant, dataset and seed, and every key that differs from what those presets
    give."""
    anchors = {"method": cfg.method, "budget": cfg.budget, "variant": cfg.variant, "data.name": cfg.data.name}
    preset = config_lib.to_flat(config_lib.resolve(anchors))
    flat = config_lib.to_flat(cfg)
    keys = [
        *anchors,
        "seed",
        *(
            k
            for k in flat
            if k not in anchors and k != "seed" and not k.startswith("tracking.") and flat[k] != preset[k]
        ),
    ]
    return "spot run " + " ".join(_override_text(k, flat[k]) for k in keys)


def description(cfg: config_lib.ExperimentConfig, tags: Mapping[str, str], command: str) -> str:
    """The run's description (``mlflow.note.content``, Markdown)."""
    lines = [
        f"**{cfg.method}** on **{tags.get('dataset', cfg.data.name)}** "
        f"({tags.get('dataset_source', '?')}, size {tags.get('dataset_size', '?')}), "
        f"budget **{cfg.budget}**, seed {cfg.seed}, variant {cfg.variant}"
    ]
    if tags.get("sweep_id"):
        axes = ", ".join(f"{k[len('axis.') :]}={v}" for k, v in tags.items() if k.startswith("axis."))
        lines.append(
            f"sweep **{tags.get('sweep_name', '?')}** (launch `{tags['sweep_id']}`)"
            + (f", trial {axes}" if axes else "")
        )
    lines.append(f"command: `{command}`")
    lines.append(f"reproduce this config: `{reproduce_command(cfg)}`")
    if tags.get("data_digest"):
        lines.append(f"dataset fingerprint (SHA-256 of its arrays): `{tags['data_digest']}`")
    return "\n\n".join(lines)


def environment() -> dict[str, Any]:
    """Python, platform, CPU, accelerators, the XLA/JAX/threading environment variables and every
    installed distribution's version (``environment.json``)."""
    cpu_model = platform.processor()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    devices: Any = "jax not imported"
    if "jax" in sys.modules:
        try:
            devices = [f"{d.platform}:{getattr(d, 'device_kind', '')}" for d in sys.modules["jax"].devices()]
        except Exception as e:  # noqa: BLE001 - no backend: say so in the record
            devices = f"unavailable ({type(e).__name__}: {e})"
    env_keys = sorted(
        k
        for k in os.environ
        if k.startswith(("XLA_", "JAX_", "TF_", "CUDA_", "MUJOCO_", "SPOT_"))
        or k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "PYOPENGL_PLATFORM")
    )
    return {
        "python": sys.version,
        "executable": sys.executable,
        "platform": platform.platform(),
        "cpu": {
            "model": cpu_model,
            "count": os.cpu_count(),
            "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        },
        "devices": devices,
        "env": {k: os.environ[k] for k in env_keys},
        "git_commit": git_commit(),
        "command": command_line(),
        "packages": installed_distributions(),
    }


@functools.cache  # 0.4-1 s a call; the packages do not change while a process runs
def installed_distributions() -> dict[str, str]:
    """``{name: version}`` of every installed distribution (what ``pip freeze`` lists)."""
    out = {}
    for dist in importlib.metadata.distributions():
        name = dist.metadata["Name"]
        if name:
            out[name] = dist.version
    return dict(sorted(out.items(), key=lambda kv: kv[0].lower()))


def requirements_text(packages: Mapping[str, str]) -> str:
    """``name==version`` lines, ``pip freeze``'s format."""
    return "".join(f"{name}=={version}\n" for name, version in packages.items())


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

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        """A file, stored under its own name (in the artifact folder ``artifact_path`` if given)."""

    def log_dict(self, data: Any, name: str) -> None:
        """A JSON (``.json``, NaN and infinities as null) or YAML (``.yaml``) artifact."""

    def log_text(self, text: str, name: str) -> None:
        """A text artifact."""

    def set_tags(self, tags: Mapping[str, str]) -> None:
        """String tags."""


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

        self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


LOOKUP_TAGS = ("trial_key", "attempt")
"""The tags sweeps find a run by (finished-run lookups on resume, failure records). A run is
created without them; they arrive in the same ``log_batch`` as the last of its params
(:func:`create_run`), so a process killed in between leaves a run that no lookup finds (closed
later as a dead process's run), never one that is found without its params."""


def create_run(
    client: Any, experiment_id: str, name: str, tags: dict[str, str], cfg: config_lib.ExperimentConfig
) -> Any:
    """``client.create_run`` with ``tags`` except :data:`LOOKUP_TAGS`; returns the run. Follow it
    with :func:`log_params` and :func:`lookup_tags` of the same ``tags``."""
    return client.create_run(experiment_id, run_name=name, tags={k: v for k, v in tags.items() if k not in LOOKUP_TAGS})


def lookup_tags(tags: dict[str, str]) -> dict[str, str]:
    """The :data:`LOOKUP_TAGS` among ``tags`` (they go with the params: :func:`log_params`)."""
    return {k: tags[k] for k in LOOKUP_TAGS if k in tags}


def log_params(client: Any, run_id: str, cfg: config_lib.ExperimentConfig, tags: dict[str, str] | None = None) -> None:
    """The resolved config as params (flat dotted keys, :func:`active_params`), in batches of
    MLflow's limit; ``tags`` go in the last batch (one request: the store writes both or neither)."""
    from mlflow.entities import Param, RunTag

    flat = active_params(cfg)
    params = [Param(k, str(list(v) if isinstance(v, tuple) else v)) for k, v in flat.items()]
    starts = list(range(0, len(params), 100)) or [0]  # MLflow's limit of params per batch
    for i in starts:
        last = i == starts[-1]
        run_tags_ = [RunTag(k, str(v)) for k, v in (tags or {}).items()] if last else []
        client.log_batch(run_id, params=params[i : i + 100], tags=run_tags_)


def mlflow_tags(cfg: config_lib.ExperimentConfig, tags: dict[str, str]) -> dict[str, str]:
    """MLflow's own run fields as tags: description, source name and type, git commit."""
    command = command_line()
    if COMMAND_ENV not in os.environ and Path(sys.argv[0]).name == "default_worker.py" and tags.get("sweep_name"):
        command = f"spot sweep (a trial of sweep {tags['sweep_name']}; Ray worker)"  # a cluster's worker
    out = {
        "mlflow.note.content": description(cfg, tags, command),
        "mlflow.source.name": command,
        "mlflow.source.type": "LOCAL",
    }
    commit = commit_hash()
    if commit:
        out["mlflow.source.git.commit"] = commit
    return out


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
    if first_run(client, experiment_id, {"attempt": tags["attempt"]}) is not None:
        return None
    all_tags = run_tags(cfg, {"name": cfg.data.name}, tags)
    all_tags.update(mlflow_tags(cfg, all_tags))
    all_tags["failure_reason"] = failure_reason(error)
    if parent_run_id:
        all_tags["mlflow.parentRunId"] = parent_run_id
    with waiting_on(client_uri(client), "recording a failed run"):
        run = create_run(client, experiment_id, f"{cfg.method}-{cfg.data.name}-s{cfg.seed}", all_tags, cfg)
        log_params(client, run.info.run_id, cfg, lookup_tags(all_tags))
        client.set_terminated(run.info.run_id, "FAILED")
    return run.info.run_id


def start_tags(
    cfg: config_lib.ExperimentConfig,
    card: dict[str, Any],
    extra_tags: dict[str, str] | None,
    parent_run_id: str | None,
    digest: str | None,
) -> dict[str, str]:
    """The tags a run starts with, logged to MLflow or recorded as files: :func:`run_tags`, the
    dataset's fingerprint as ``data_digest``, MLflow's own fields (:func:`mlflow_tags`) and the
    parent run."""
    tags = run_tags(cfg, card, extra_tags)
    if digest:
        tags["data_digest"] = digest
    tags.update(mlflow_tags(cfg, tags))
    if parent_run_id:
        tags["mlflow.parentRunId"] = parent_run_id
    return tags


def log_run_files(tracker: Tracker, cfg: config_lib.ExperimentConfig, card: dict[str, Any]) -> None:
    """The files every run starts with: the config YAML, the dataset card, package versions and the
    environment (``environment.json``, ``requirements.txt``)."""
    tracker.log_text(config_lib.to_yaml(cfg), "config.yaml")
    tracker.log_dict(card, "dataset_card.json")
    tracker.log_dict(package_versions(), "package_versions.json")
    env = environment()
    tracker.log_dict(env, "environment.json")
    tracker.log_text(requirements_text(env["packages"]), "requirements.txt")


RUN_TEMP_PREFIX = "spot-run-"


def run_temp_root() -> Path:
    """Where runs stage their artifact files before logging them: ``$SPOT_CACHE_DIR/tmp``."""
    from spot import cache

    return cache.cache_dir() / "tmp"


def clean_run_temp(root: Path | None = None) -> list[Path]:
    """Remove ``spot-run-<pid>-*`` folders under ``root`` whose process no longer runs (killed runs);
    returns them. Folders of another host's processes (a shared cache dir) are kept while younger
    than a day."""
    import re
    import shutil

    root = run_temp_root() if root is None else root
    removed = []
    if not root.is_dir():
        return removed
    for folder in root.iterdir():
        m = re.fullmatch(rf"{RUN_TEMP_PREFIX}(\d+)-.*", folder.name)
        if m is None or not folder.is_dir() or int(m[1]) == os.getpid():
            continue
        if runtime.pid_alive(int(m[1])):
            continue
        try:
            if time.time() - folder.stat().st_mtime < 86400 and not _local_pid_folder(folder):
                continue
        except FileNotFoundError:
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def _local_pid_folder(folder: Path) -> bool:
    """Whether ``folder`` was made on this host (its ``.host`` file names it)."""
    try:
        return (folder / ".host").read_text().strip() == platform.node()
    except OSError:
        return False


def run_temp_dir() -> Path:
    """A new ``$SPOT_CACHE_DIR/tmp/spot-run-<pid>-*`` folder for one run's artifact files (the run
    removes it when it ends, :func:`remove_run_temp`; a killed run's is removed by the next run)."""
    import tempfile

    from spot import store

    root = store.writable_dir(run_temp_root(), "$SPOT_CACHE_DIR")  # a file or read-only: one clear error
    clean_run_temp(root)
    folder = Path(tempfile.mkdtemp(prefix=f"{RUN_TEMP_PREFIX}{os.getpid()}-", dir=root))
    (folder / ".host").write_text(platform.node())
    return folder


def remove_run_temp(folder: Path) -> None:
    """Remove a folder made by :func:`run_temp_dir` (its files were logged to the run)."""
    import shutil

    if folder.name.startswith(RUN_TEMP_PREFIX):
        shutil.rmtree(folder, ignore_errors=True)


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
    name = run_name or f"{cfg.method}-{tags['dataset']}-s{cfg.seed}"
    run = create_run(client, exp_id, name, tags, cfg)
    tracker = MlflowTracker(client, run.info.run_id)
    monitor = SystemMetrics(run.info.run_id, uri).start() if system_metrics else None
    try:
        log_params(client, run.info.run_id, cfg, lookup_tags(tags))
        if digest:
            log_dataset_input(client, run.info.run_id, dataset, card, cfg, digest)
        log_run_files(tracker, cfg, card)
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
