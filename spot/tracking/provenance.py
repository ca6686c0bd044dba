"""What every run records about itself: tags, params, MLflow's own fields and the environment.

Every run logs its resolved config as params (flat dotted keys; the model sections of other
methods, ``mr.*``, ``pt.*``, ``hpl.*``, ``ipl.*``, are left out: :func:`active_params`), tags
naming the method, dataset, dataset source, label source, seed, budget, git commit, package
versions and the dataset fingerprint (``data_digest``: :func:`start_tags`; named here by their bare
names, stored in MLflow under ``spot.`` but for the first-class ``method``, ``dataset``, ``seed``,
``variant`` and ``axis.*``: :mod:`spot.tracking.tagnames`), and MLflow's own
fields (:func:`mlflow_tags`): a description (``mlflow.note.content``: method, dataset, budget,
sweep, the command line and a ``spot run`` command that reproduces the config),
``mlflow.source.name`` (the command), ``mlflow.source.type``, ``mlflow.source.git.commit``.
Artifacts (:func:`log_run_files`): the config YAML, the dataset card, package versions and the
environment (``environment.json``, ``requirements.txt``). The same tags, params and files go to
MLflow (:func:`spot.tracking.record.start_run`) or into a record folder
(:func:`spot.tracking.recorded.start_record`).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import json
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from spot import config as config_lib
from spot.tracking.trackers import Tracker

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
        "variant": cfg.variant,
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


TAG_CHARS = 8000  # MLflow's limit on a tag value
NOTE_COMMAND_CHARS = 2000  # of each command in the description, so that it stays under TAG_CHARS


def _clip(text: str, keep: int = NOTE_COMMAND_CHARS) -> str:
    """``text`` cut to ``keep`` characters with a note of what was cut (a command line can be long)."""
    cut = len(text) - keep
    return text if cut <= 0 else f"{text[:keep]} … ({cut} more characters)"


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
    lines.append(f"command: `{_clip(command)}`")
    lines.append(f"reproduce this config: `{_clip(reproduce_command(cfg))}`")
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


def mlflow_tags(cfg: config_lib.ExperimentConfig, tags: dict[str, str]) -> dict[str, str]:
    """MLflow's own run fields as tags: description, source name and type, git commit."""
    command = command_line()
    if COMMAND_ENV not in os.environ and Path(sys.argv[0]).name == "default_worker.py" and tags.get("sweep_name"):
        command = f"spot sweep (a trial of sweep {tags['sweep_name']}; Ray worker)"  # a cluster's worker
    out = {
        "mlflow.note.content": description(cfg, tags, command),
        "mlflow.source.name": _clip(command, TAG_CHARS - 40),
        "mlflow.source.type": "LOCAL",
    }
    commit = commit_hash()
    if commit:
        out["mlflow.source.git.commit"] = commit
    return out


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
