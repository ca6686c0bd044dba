"""Queries on a store: filter strings, paging, finished-run lookup, orphan closing and artifact
fetching. Sweeps, tables and figures read MLflow through these.

Filter strings are built with :func:`quote` / :func:`tag_filter`: MLflow takes a value in single
or double quotes and has no escape inside them, so a value is put in the quote it does not
contain, and a value holding both is refused.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from spot import SpotError
from spot.tracking.limits import cap_reason, waiting_on
from spot.tracking.store import PAGE, SEARCH_EXPERIMENTS, sqlite_path
from spot.tracking.tagnames import alternatives

STATUSES = ("RUNNING", "SCHEDULED", "FINISHED", "FAILED", "KILLED")


def quote(value: Any) -> str:
    """``value`` as a quoted MLflow filter string literal."""
    text = str(value)
    if "'" not in text:
        return f"'{text}'"
    if '"' not in text:
        return f'"{text}"'
    raise SpotError(f"{text!r} holds both quote characters, which an MLflow filter cannot express")


def tag_filter(tags: Mapping[str, Any], status: str | None = None) -> str:
    """``tags.`k` = 'v' and ...`` (every tag equal), plus ``attributes.status`` if given."""
    parts = [f"tags.`{k}` = {quote(v)}" for k, v in tags.items()]
    if status is not None:
        if status not in STATUSES:
            raise ValueError(f"unknown run status {status!r}")
        parts.append(f"attributes.status = '{status}'")
    return " and ".join(parts)


def search_runs(client: Any, experiment_ids: Sequence[str], filter_string: str = "") -> Iterator[Any]:
    """Every run of the experiments matching ``filter_string``, through all pages."""
    ids = list(experiment_ids)
    for start in range(0, len(ids), SEARCH_EXPERIMENTS):
        token = None
        while True:
            with waiting_on(client_uri(client), "searching runs"):
                page = client.search_runs(
                    ids[start : start + SEARCH_EXPERIMENTS],
                    filter_string=filter_string,
                    max_results=PAGE,
                    page_token=token,
                )
            yield from page
            token = page.token
            if not token:
                break


def search_tagged(
    client: Any, experiment_ids: Sequence[str], tags: Mapping[str, Any], status: str | None = None
) -> Iterator[Any]:
    """Every run of the experiments with all ``tags`` (bare or stored names, :mod:`spot.tracking.tagnames`)
    and ``status``: the runs tagged under the stored names, then those of older stores tagged under
    the bare ones (MLflow's filters have no ``or``), each run once."""
    seen: set[str] = set()
    for found in alternatives(tags):
        for run in search_runs(client, experiment_ids, tag_filter(found, status)):
            if run.info.run_id not in seen:
                seen.add(run.info.run_id)
                yield run


def client_uri(client: Any) -> str:
    """The tracking URI of an MLflow client (for error messages), "" if it has none."""
    return str(getattr(client, "tracking_uri", "") or "")


def first_run(client: Any, experiment_id: str, tags: Mapping[str, Any], status: str | None = None) -> Any | None:
    """One run of the experiment with all ``tags`` (and ``status``), or None; ``tags`` by bare or
    stored name, found under either (:func:`search_tagged`)."""
    for names in alternatives(tags):
        with waiting_on(client_uri(client), "looking up a run"):
            found = client.search_runs([experiment_id], tag_filter(names, status), max_results=1)
        if found:
            return found[0]
    return None


def finished_run(client: Any, experiment_id: str, tags: Mapping[str, Any]) -> Any | None:
    """A FINISHED run with all ``tags`` (e.g. a sweep's id and trial key; bare or stored names), or None."""
    return first_run(client, experiment_id, tags, "FINISHED")


def close_orphans(
    client: Any,
    experiment_id: str,
    tags: Mapping[str, Any],
    reason: str,
    keep: Sequence[str] = (),
    deadline: float | None = None,
) -> int:
    """Mark the runs with ``tags`` (bare or stored names) still RUNNING (their process is gone), but ``keep``, as KILLED
    with ``failure_reason`` (capped); return how many.

    With ``deadline`` (a ``time.monotonic()`` value), :class:`TimeoutError` once it has passed
    before all are closed (each request is bounded by MLflow's own deadlines,
    :mod:`spot.tracking.limits`); the runs closed so far stay closed.
    """
    orphans = [r for r in search_tagged(client, [experiment_id], tags, "RUNNING") if r.info.run_id not in keep]
    for i, r in enumerate(orphans):
        if deadline is not None and time.monotonic() > deadline:
            raise TimeoutError(f"closed {i} of {len(orphans)} runs left RUNNING before the deadline")
        with waiting_on(client_uri(client), f"closing run {r.info.run_id}"):
            client.set_tag(r.info.run_id, "failure_reason", cap_reason(reason))
            client.set_terminated(r.info.run_id, "KILLED")
    return len(orphans)


# --------------------------------------------------------------------------- artifacts
def local_artifact(artifact_uri: str, artifact_path: str, tracking_uri: str) -> Path | None:
    """Where the artifact lies if its store is on this machine: ``file:`` artifact stores, and
    ``mlflow-artifacts:`` ones beside a SQLite store (read without the server); None otherwise.

    ``spot sweep`` serves ``<root>/mlflow.db`` with ``--artifacts-destination <root>/artifacts``, so
    ``mlflow-artifacts:/<path>`` lives at ``<root>/artifacts/<path>``.
    """
    parsed = urlparse(artifact_uri)
    db = sqlite_path(tracking_uri)
    if parsed.scheme in ("", "file"):
        root = Path(parsed.path)
    elif parsed.scheme == "mlflow-artifacts" and db is not None:
        root = db.parent / "artifacts" / parsed.path.lstrip("/")
    else:
        return None
    return root / artifact_path


def download_artifact(run_id: str, artifact_uri: str, artifact_path: str, tracking_uri: str, dst: str) -> Path | None:
    """A local path of one artifact of a run (downloaded to ``dst`` if its store is remote), or
    None if the run has no such artifact."""
    import mlflow.artifacts
    from mlflow.exceptions import MlflowException

    local = local_artifact(artifact_uri, artifact_path, tracking_uri)
    if local is not None:
        return local if local.is_file() else None
    try:
        return Path(
            mlflow.artifacts.download_artifacts(
                run_id=run_id, artifact_path=artifact_path, dst_path=dst, tracking_uri=tracking_uri
            )
        )
    except (MlflowException, OSError):
        return None


def artifact_uri(client: Any, run_id: str) -> str:
    """The run's artifact root; SpotError if the store has no such run."""
    from mlflow.exceptions import MlflowException

    try:
        return client.get_run(run_id).info.artifact_uri
    except MlflowException as e:
        raise SpotError(f"no run {run_id} in {client.tracking_uri}") from e
