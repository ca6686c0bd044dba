"""``spot ui``: MLflow's UI on the store the other commands use, started with the venv's own mlflow."""

from __future__ import annotations

import argparse
import time
from typing import Any

from spot import SpotError
from spot.cli.common import URI_HELP, positive_int, subcommand

MAX_LINKS = 20  # experiments listed with a link each


def add(sub: Any) -> None:
    """The ui command."""
    d = subcommand(
        sub,
        "ui",
        "serve the MLflow UI on the runs' store and print the links to its runs tables",
        "spot ui\nspot ui --tracking-uri sqlite:///spot_runs/mlflow.db --port 5001 --open",
        description="Serve MLflow's UI on the store spot run, spot sweep and spot tables use (./spot_runs/mlflow.db "
        "unless --tracking-uri or $MLFLOW_TRACKING_URI names another), with the venv's own mlflow on "
        "127.0.0.1: one worker, job execution off. Prints the UI's address and each experiment's runs "
        "table, then serves until Ctrl-C. A tracking server given by URI is not started again: its links "
        "are printed.",
    )
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.add_argument("--port", type=positive_int, default=5000, help="port on 127.0.0.1 (another if it is taken)")
    d.add_argument("--open", action="store_true", help="open the first link in the web browser")
    d.set_defaults(fn=_ui)


def links(base: str, client: Any) -> list[str]:
    """``<name>: <runs table link>`` of the store's experiments that have runs (at most :data:`MAX_LINKS`)."""
    from spot import tracking

    out = []
    for exp_id, name in sorted(tracking.store.all_experiments(client).items(), key=lambda kv: kv[1]):
        if len(out) == MAX_LINKS:
            out.append(f"(more experiments: see {base})")
            break
        if client.search_runs([exp_id], max_results=1):
            out.append(f"{name}: {tracking.runs_url(exp_id, base=base)}")
    return out


def _show(base: str, client: Any, open_browser: bool) -> None:
    lines = links(base, client)
    print(f"MLflow UI: {base}", flush=True)
    for line in lines or ["(no runs in this store yet)"]:
        print(f"  {line}", flush=True)
    if open_browser:
        import webbrowser

        webbrowser.open(lines[0].split(": ", 1)[1] if lines and ": http" in lines[0] else base)


def _ui(args: argparse.Namespace) -> int:
    from mlflow.tracking import MlflowClient

    from spot import tracking
    from spot.sweep.mlflow_server import MlflowServer

    uri = tracking.resolve_uri(args.tracking_uri, read=True)
    if uri.startswith(("http://", "https://")):
        tracking.store.check_reachable(uri)
        _show(uri.rstrip("/"), MlflowClient(uri), args.open)
        return 0
    db = tracking.sqlite_path(uri)
    if db is None:
        raise SpotError(
            f"--tracking-uri {uri}: spot ui serves a SQLite store (sqlite:///path.db) or prints the links "
            "of a running server (http(s)://host:port); for another database run 'mlflow server' on it"
        )
    folder = db.resolve().parent
    server = MlflowServer(uri, folder / "artifacts", port=args.port, log_path=folder / "mlflow-ui.log")
    print(f"starting the MLflow UI on {uri} (its log: {server.log_path})", flush=True)
    with server:
        _show(server.uri, MlflowClient(server.uri), args.open)
        print("serving until Ctrl-C", flush=True)
        try:
            while not server.died():
                time.sleep(1.0)
        except KeyboardInterrupt:
            return 0
    raise SpotError(f"{server.died()} (its log: {server.log_path})")
