"""Where runs go: the one tracking-URI resolver, experiments, and the local stores.

One default store per folder: ``<cwd>/spot_runs/mlflow.db`` (artifacts under
``<cwd>/spot_runs/artifacts``) when no URI is given. ``spot run`` writes it directly, ``spot sweep``
serves it through a loopback server (:mod:`spot.sweep.mlflow_server`), and ``spot tables``,
``spot report``, ``spot figures``, ``spot eval`` and ``spot ui`` read it. A folder from before (where
``spot run`` wrote ``./mlruns/mlflow.db``) is still read when it has no ``spot_runs/mlflow.db``.
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.tracking.limits import waiting_on
from spot.tracking.locking import prepare_store, sqlite_path
from spot.tracking.naming import EXPERIMENT_KIND, EXPERIMENT_KIND_TAG

SWEEP_STORE = Path("spot_runs") / "mlflow.db"
"""The default store of every command (``spot run``, ``spot sweep``, the readers), relative to the
working folder."""
RUN_STORE = SWEEP_STORE
"""``spot run``'s default store: the same one (an alias kept for importers)."""
OLD_RUN_STORE = Path("mlruns") / "mlflow.db"
"""Where ``spot run`` wrote before the stores were one; read when the default store is absent."""
LOCAL_STORES = (SWEEP_STORE, OLD_RUN_STORE)
SEARCH_EXPERIMENTS = 50  # experiments per search request (the API takes a bounded list)
PAGE = 1000  # runs or experiments per page


def given_uri(uri: str | None = None) -> str:
    """``uri``, else ``$MLFLOW_TRACKING_URI``, else ``""`` (no store named)."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI", "")


def resolve_uri(uri: str | None = None, *, read: bool = False) -> str:
    """The tracking URI to use: ``uri``, else ``$MLFLOW_TRACKING_URI``, else the local store.

    Writing (``spot run``): the local store is ``./spot_runs/mlflow.db`` (its folder is created).
    Reading (``read=True``: tables, report, figures, eval, ui): ``./spot_runs/mlflow.db``; in a
    folder from before without it, ``./mlruns/mlflow.db`` (with a one-line note); with both, the
    default one, and a note naming the other. A SQLite store that is read must exist.
    """
    uri = given_uri(uri)
    if uri:
        check_uri(uri)
    if not read:
        if uri:
            return uri
        SWEEP_STORE.parent.mkdir(exist_ok=True)
        return f"sqlite:///{SWEEP_STORE.resolve()}"
    if not uri:
        return f"sqlite:///{default_store()}"
    db = sqlite_path(uri)
    if db is not None and not db.exists():
        raise SpotError(f"no MLflow store at {db} (tracking URI {uri})")
    return uri


def default_store() -> Path:
    """The store a reading command uses with no URI given (:func:`resolve_uri`)."""
    new, old = SWEEP_STORE.resolve(), OLD_RUN_STORE.resolve()
    if not new.exists() and not old.exists():
        raise SpotError(f"no MLflow store here ({SWEEP_STORE}); pass --tracking-uri (or set MLFLOW_TRACKING_URI)")
    if not new.exists():
        print(f"note: reading {old} (spot run's store before spot_runs/mlflow.db)", file=sys.stderr, flush=True)
        return old
    if old.exists():
        print(
            f"note: reading {new}; {old} (an older spot run's store) is not read: --tracking-uri sqlite:///{old}",
            file=sys.stderr,
            flush=True,
        )
    return new


def check_reachable(uri: str, timeout: float = 10.0) -> None:
    """Raise SpotError within about ``timeout`` s if nothing answers HTTP at ``uri`` (MLflow's own
    client would retry for minutes). Any HTTP answer counts, an error status included."""
    try:
        with urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=timeout):
            return
    except urllib.error.HTTPError:
        return  # it answers (behind authentication, or a proxy without /health)
    except (urllib.error.URLError, OSError, ValueError) as e:
        reason = getattr(e, "reason", e)
        raise SpotError(
            f"tracking server {uri} does not answer ({reason}); start it, or pass another --tracking-uri"
        ) from None


_ANSWERED: set[str] = set()  # tracking servers that answered in this process


def check_server(uri: str) -> None:
    """For an ``http(s)://`` tracking URI: :class:`SpotError` within about 10 s if the server does not
    answer (MLflow's client retries for minutes before a traceback). Checked once per process."""
    if not uri.startswith(("http://", "https://")) or uri in _ANSWERED:
        return
    check_reachable(uri)
    _ANSWERED.add(uri)


SCHEMES = ("", "file", "sqlite", "http", "https", "postgresql", "mysql", "mssql", "databricks", "databricks-uc", "uc")
"""The tracking URI schemes MLflow's client accepts (its UnsupportedModelRegistryStoreURIException list)."""


def check_uri(uri: str) -> None:
    """:class:`SpotError` for a tracking URI MLflow cannot use (which it reports with a traceback,
    after a run's data has loaded): an unknown scheme, a folder or ``file:`` URI (MLflow's file store,
    which MLflow refuses unless ``MLFLOW_ALLOW_FILE_STORE=true``), or a ``sqlite:`` URI not of the
    form ``sqlite:///relative.db`` / ``sqlite:////absolute.db``."""
    import re

    scheme = m[1].lower() if (m := re.match(r"([A-Za-z][A-Za-z0-9+.-]*):", uri)) and len(m[1]) > 1 else ""
    if scheme.split("+")[0] not in SCHEMES:
        raise SpotError(
            f"tracking URI '{uri}': scheme '{scheme}' is not one MLflow stores runs in; expected "
            "sqlite:///path.db, http(s)://host:port or postgresql/mysql/mssql://... (a folder only with "
            "MLFLOW_ALLOW_FILE_STORE=true)"
        )
    allow = os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").strip().lower() in ("1", "true", "yes")
    if scheme in ("", "file") and not allow:
        raise SpotError(
            f"tracking URI '{uri}': a folder (MLflow's file store) is refused by this MLflow unless "
            "MLFLOW_ALLOW_FILE_STORE=true; use sqlite:///path.db (or a tracking server)"
        )
    if scheme == "sqlite" and (sqlite_path(uri) is None or not str(sqlite_path(uri)).strip("/")):
        raise SpotError(f"tracking URI '{uri}': expected sqlite:///relative/path.db or sqlite:////absolute/path.db")


def reader(uri: str | None = None) -> Any:
    """An ``MlflowClient`` on the store :func:`resolve_uri` picks for reading."""
    from mlflow.tracking import MlflowClient

    resolved = resolve_uri(uri, read=True)
    check_server(resolved)
    return MlflowClient(tracking_uri=resolved)


def experiment_id(name: str, uri: str) -> str:
    """Get or create the experiment (with an explicit artifact location for local stores), tagged as
    an ML experiment (:data:`spot.tracking.naming.EXPERIMENT_KIND`: MLflow's UI opens it in its
    model-training workspace)."""
    from mlflow.tracking import MlflowClient

    check_server(uri)  # an http(s) server that does not answer: a clear error, not minutes of retries
    prepare_store(uri)  # a new SQLite store is created and migrated by one process at a time
    client = MlflowClient(uri)
    # a server that answers /health and then stalls: a clear error once the deadlines pass (limits)
    with waiting_on(uri, f"looking up experiment {name!r}"):
        exp = client.get_experiment_by_name(name)
    if exp is not None:
        if EXPERIMENT_KIND_TAG not in exp.tags:  # made before spot set it: an ML experiment all the same
            with waiting_on(uri, f"tagging experiment {name!r}"):
                client.set_experiment_tag(exp.experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
        return exp.experiment_id
    db = sqlite_path(uri)
    location = (db.parent / "artifacts").resolve().as_uri() if db is not None else None
    with waiting_on(uri, f"creating experiment {name!r}"):
        try:
            return client.create_experiment(
                name, artifact_location=location, tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND}
            )
        except Exception:  # noqa: BLE001 - created concurrently by another process
            exp = client.get_experiment_by_name(name)
            if exp is None:
                raise
            return exp.experiment_id


def all_experiments(client: Any) -> dict[str, str]:
    """``{experiment id: name}`` of every experiment in the store (all pages)."""
    out, token = {}, None
    while True:
        with waiting_on(getattr(client, "tracking_uri", ""), "listing the experiments"):
            page = client.search_experiments(max_results=PAGE, page_token=token)
        out.update({e.experiment_id: e.name for e in page})
        token = page.token
        if not token:
            return out


def experiments(client: Any, names: Sequence[str] | None = None) -> dict[str, str]:
    """``{experiment id: name}`` of the named experiments (all if ``names`` is empty).

    Raises SpotError naming the known experiments if one does not exist.
    """
    if not names:
        return all_experiments(client)
    out = {}
    for name in names:
        with waiting_on(getattr(client, "tracking_uri", ""), f"looking up experiment {name!r}"):
            exp = client.get_experiment_by_name(name)
        if exp is None:
            known = sorted(all_experiments(client).values())
            raise SpotError(f"no MLflow experiment named {name!r}; known: {', '.join(known) or 'none'}")
        out[exp.experiment_id] = exp.name
    return out


def has_experiment(client: Any, name: str) -> bool:
    return client.get_experiment_by_name(name) is not None
