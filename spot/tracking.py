"""Everything MLflow: where runs go, what every run records, and how a failed run is marked.

Every run logs the full resolved config as params (flat dotted keys), tags naming the method,
dataset, dataset source, label source, seed, budget, git commit and package versions, and the
config YAML as an artifact. With no tracking URI the store is ``sqlite:///<cwd>/mlruns/mlflow.db``
with artifacts under ``<cwd>/mlruns/artifacts`` (one process writes it; sweeps use a server).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.metadata
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from spot import config as config_lib

PACKAGES = ("spot-pbrl", "jax", "jaxlib", "flax", "optax", "numpy", "mujoco", "gymnasium",
            "metaworld", "robosuite", "mlflow", "ray", "h5py")


def default_uri() -> str:
    root = Path.cwd() / "mlruns"
    root.mkdir(exist_ok=True)
    return f"sqlite:///{root / 'mlflow.db'}"


def resolve_uri(uri: str) -> str:
    return uri or os.environ.get("MLFLOW_TRACKING_URI", "") or default_uri()


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


def experiment_id(name: str, uri: str) -> str:
    """Get or create the experiment (with an explicit artifact location for local stores)."""
    import mlflow

    mlflow.set_tracking_uri(uri)
    exp = mlflow.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    location = None
    if uri.startswith("sqlite:///"):
        location = (Path(uri[len("sqlite:///"):]).parent / "artifacts").resolve().as_uri()
    try:
        return mlflow.create_experiment(name, artifact_location=location)
    except Exception:  # noqa: BLE001 - created concurrently by another process
        exp = mlflow.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


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


@contextlib.contextmanager
def start_run(cfg: config_lib.ExperimentConfig, card: dict[str, Any], *, run_name: str | None = None,
              extra_tags: dict[str, str] | None = None, parent_run_id: str | None = None) -> Iterator[Any]:
    """Start an MLflow run with params, tags and the config artifact; mark FAILED on exceptions."""
    import mlflow

    uri = resolve_uri(cfg.tracking.uri)
    exp_id = experiment_id(cfg.tracking.experiment, uri)
    tags = run_tags(cfg, card, extra_tags)
    if parent_run_id:
        tags["mlflow.parentRunId"] = parent_run_id
    run = mlflow.start_run(experiment_id=exp_id, run_name=run_name or f"{cfg.method}-{tags['dataset']}-s{cfg.seed}", tags=tags)
    try:
        mlflow.log_params({k: (list(v) if isinstance(v, tuple) else v) for k, v in config_lib.to_flat(cfg).items()})
        mlflow.log_text(config_lib.to_yaml(cfg), "config.yaml")
        mlflow.log_dict(card, "dataset_card.json")
        mlflow.log_dict(package_versions(), "package_versions.json")
        yield run
    except BaseException as e:
        reason = f"{type(e).__name__}: {e}"
        mlflow.set_tag("failure_reason", reason[:4000])
        mlflow.end_run(status="FAILED" if not isinstance(e, KeyboardInterrupt) else "KILLED")
        raise
    else:
        mlflow.end_run(status="FINISHED")
