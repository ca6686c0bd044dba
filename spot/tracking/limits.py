"""Bounds on what spot waits for from MLflow and writes into it.

* **HTTP deadlines.** MLflow's client waits ``MLFLOW_HTTP_REQUEST_TIMEOUT`` seconds (120 by
  default) for each answer of a tracking server and tries ``MLFLOW_HTTP_REQUEST_MAX_RETRIES`` (7)
  more times with growing pauses, so a server that accepts connections and never answers keeps a
  command silent for about 20 minutes. spot's processes use 30 s and 2 retries unless the
  environment sets these variables (:func:`set_http_deadlines`, called when :mod:`spot.tracking` is
  imported; sweep trials inherit them), so a request that gets no answer ends within about 95 s,
  and one to a server that refuses connections within about 5 s.
* **One line for a request that got no answer.** :func:`unreachable` turns MLflow's error for such
  a request (a traceback with urllib3's retry text) into a :class:`TrackingUnreachable` naming the
  server, the request, what spot was doing and the deadlines; :func:`waiting_on` raises it for the
  calls in its block.
* **failure_reason.** :func:`failure_reason` is an error as a run's ``failure_reason`` tag, capped
  at :data:`REASON_CHARS` characters with a note of how many were left out (an error that lists a
  folder's contents would otherwise put the whole listing in the tag).
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from urllib.parse import urlsplit

from spot import SpotError

HTTP_DEADLINES = {"MLFLOW_HTTP_REQUEST_TIMEOUT": "30", "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2"}
"""spot's defaults for MLflow's HTTP client: seconds to wait for each answer, retries after the first try."""
REASON_CHARS = 1000
"""The longest ``failure_reason`` tag spot writes (before the note of what was left out)."""


def set_http_deadlines() -> None:
    """Set :data:`HTTP_DEADLINES` in this process's environment where it does not set them (an
    empty value counts as unset); MLflow reads them at every request."""
    for key, value in HTTP_DEADLINES.items():
        if not os.environ.get(key, "").strip():
            os.environ[key] = value


def http_deadlines() -> dict[str, str]:
    """The deadline variables as MLflow's client will read them now."""
    return {k: os.environ.get(k, "").strip() or v for k, v in HTTP_DEADLINES.items()}


class TrackingUnreachable(SpotError):  # noqa: N818 - a SpotError, named for what happened
    """A request to an MLflow tracking server got no answer within its deadlines."""


def _request_error(error: BaseException) -> BaseException | None:
    """The ``requests`` (or urllib3) connection or timeout error behind ``error``, if any."""
    import requests

    seen: set[int] = set()
    todo: list[BaseException | None] = [error]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, (requests.exceptions.ConnectionError, requests.exceptions.Timeout)):
            return e
        todo += [e.__cause__, e.__context__]
    return None


def _what_failed(cause: BaseException) -> str:
    """``no answer within N s`` or ``connection refused``, or the error's own last words."""
    text = str(cause)
    timeout = re.search(r"read timeout=(\d+(?:\.\d+)?)", text)
    if timeout or "timed out" in text.lower():
        limit = timeout[1] if timeout else http_deadlines()["MLFLOW_HTTP_REQUEST_TIMEOUT"]
        return f"no answer within {float(limit):g} s"
    for words in ("Connection refused", "Name or service not known", "No route to host", "Connection reset"):
        if words.lower() in text.lower():
            return words[0].lower() + words[1:]
    return re.sub(r"\s+", " ", text)[:200]


def unreachable(error: BaseException, uri: str = "", doing: str = "") -> TrackingUnreachable | None:
    """``error`` as a :class:`TrackingUnreachable` if it is MLflow's (or ``requests``') error for an
    HTTP request that got no answer (refused, reset or timed out after every retry); else None.

    Args:
      error: what an MLflow client call raised.
      uri: the tracking URI the call went to (else taken from the request's URL).
      doing: what spot was doing, e.g. ``"looking up experiment 'e'"``.
    """
    if isinstance(error, TrackingUnreachable):
        return error
    cause = _request_error(error)
    if cause is None:
        return None
    url = re.search(r"API request to (\S+) failed", str(error))
    parts = urlsplit(url[1]) if url else None
    server = uri or (f"{parts.scheme}://{parts.netloc}" if parts else "")
    deadlines = http_deadlines()
    try:
        tries = int(deadlines["MLFLOW_HTTP_REQUEST_MAX_RETRIES"]) + 1
    except ValueError:
        tries = 0
    asked = f" to {parts.path}" if parts and parts.path else ""
    return TrackingUnreachable(
        f"tracking server {server or '(unknown)'} did not answer{f' while spot was {doing}' if doing else ''}: "
        f"{_what_failed(cause)}{asked}"
        + (f", {tries} tr{'y' if tries == 1 else 'ies'}" if tries else "")
        + " (MLFLOW_HTTP_REQUEST_TIMEOUT="
        + deadlines["MLFLOW_HTTP_REQUEST_TIMEOUT"]
        + " s, MLFLOW_HTTP_REQUEST_MAX_RETRIES="
        + deadlines["MLFLOW_HTTP_REQUEST_MAX_RETRIES"]
        + "); check that the server runs and answers, or pass another --tracking-uri"
    )


@contextlib.contextmanager
def waiting_on(uri: str, doing: str) -> Iterator[None]:
    """Within the block, an MLflow request that gets no answer raises :class:`TrackingUnreachable`
    naming ``uri`` and ``doing`` (other errors pass unchanged)."""
    try:
        yield
    except Exception as e:
        err = unreachable(e, uri if uri.startswith(("http://", "https://")) else "", doing)
        if err is None:
            raise
        raise err from None


def cap_reason(text: str, limit: int = REASON_CHARS) -> str:
    """``text`` cut to ``limit`` characters, with ``… (N more chars)`` where it was cut."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text) - limit} more chars)"


def failure_reason(error: BaseException, limit: int = REASON_CHARS) -> str:
    """``error`` as a ``failure_reason`` tag: ``Type: message``, capped (:func:`cap_reason`)."""
    return cap_reason(f"{type(error).__name__}: {error}", limit)
