"""Where a launch may log: the tracking-URI and ``--tracking-host`` checks of ``spot sweep``, and
the address trials reach a served store at.

A sweep logs to a SQLite store spot serves (:mod:`spot.sweep.tracking_store`), an ``http(s)://``
tracking server, or a database MLflow supports; a file store cannot take concurrent trials.
"""

from __future__ import annotations

import contextlib
import socket

from spot import SpotError

LOOPBACK = "127.0.0.1"
_SWEEP_SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql", "databricks", "databricks-uc")


def check_tracking_uri(uri: str) -> str:
    """``uri`` if a sweep can log there (``""``: the default store); SpotError otherwise."""
    from spot import tracking
    from spot.sweep import mlflow_server

    if uri and mlflow_server.is_local_store(uri) and not uri.startswith("sqlite:"):
        raise SpotError(
            f"tracking URI '{uri}': file stores cannot take concurrent trials; give "
            "sqlite:///path.db (spot serves it) or http(s)://host:port of a tracking server"
        )
    scheme = uri.split("://", 1)[0].split("+", 1)[0].lower() if "://" in uri else ""
    if uri and (scheme not in _SWEEP_SCHEMES or (scheme == "sqlite" and tracking.sqlite_path(uri) is None)):
        raise SpotError(
            f"tracking URI '{uri}': a sweep logs to sqlite:///path.db (spot serves it), an "
            "http(s)://host:port tracking server, or a database MLflow supports "
            "(postgresql://, mysql://, mssql://) or databricks://"
        )
    return uri


def check_tracking_host(host: str | None, address: str | None, tracking_uri: str | None) -> None:
    """``--tracking-host`` is for the server spot starts for a cluster sweep."""
    from spot import tracking

    if host is None:
        return
    if not address:
        raise SpotError(
            f"--tracking-host {host}: only for a cluster sweep (--address); a local sweep's server stays on loopback"
        )
    uri = tracking.given_uri(tracking_uri)
    if uri and not uri.startswith("sqlite:"):
        raise SpotError(
            f"--tracking-host {host}: spot starts no server for --tracking-uri {uri}; give one or the other"
        )
    if not host.strip() or any(c in host for c in "/ :[]"):
        raise SpotError(f"--tracking-host {host!r}: expected an IPv4 address or host name, e.g. 0.0.0.0")


def advertised_host(host: str, address: str | None) -> str:
    """The address trials reach a server bound to ``host`` at: ``host`` itself, or for ``0.0.0.0``
    this machine's address on the route to the Ray head (``address``)."""
    if host != "0.0.0.0":
        return host
    peer, sep, port = (address or "").rpartition(":")
    with contextlib.suppress(OSError):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # no packet is sent
            s.connect((peer if sep and port.isdigit() else "10.255.255.255", int(port) if port.isdigit() else 1))
            return s.getsockname()[0]
    return socket.gethostbyname(socket.gethostname())
