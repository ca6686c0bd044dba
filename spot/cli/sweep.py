"""``spot sweep``: run a sweep file with Ray Tune (``--dry-run``: what a launch would run, a grid's
trials or a search's setup; ``--status``: where its last launch stands)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from spot import SpotError
from spot.cli.common import add_quiet, positive_int, subcommand


def add(sub: Any) -> None:
    """The sweep command."""
    d = subcommand(
        sub,
        "sweep",
        "run a sweep file (sweeps/*.yaml) with Ray Tune, logged to MLflow",
        "spot sweep sweeps/quickstart.yaml --smoke\n"
        "spot sweep sweeps/paper/table1.yaml --address auto --max-concurrent 8",
        description="Run a sweep file with Ray Tune, one MLflow run per (config, seed). Exit code 0 "
        "when every run finished, 1 otherwise. See docs/sweeps.md.",
    )
    d.add_argument("file", help="sweep YAML file")
    d.add_argument("--smoke", action="store_true", help="apply the file's smoke block (experiment <name>-smoke)")
    d.add_argument("--resume", action="store_true", help="continue the last launch of this sweep")
    d.add_argument("--retry-errored", action="store_true", help="with --resume: run failed trials again")
    d.add_argument("--address", help="Ray cluster address (default: local Ray on all CPUs)")
    d.add_argument(
        "--max-concurrent", type=positive_int, help="trials at once, >= 1 (default: the file's max_concurrent)"
    )
    d.add_argument("--tracking-uri", help="MLflow tracking URI (default: a loopback server on ./spot_runs/mlflow.db)")
    d.add_argument("--storage", default="spot_runs/ray", help="Ray Tune storage folder")
    d.add_argument(
        "--store",
        help="store every node shares datasets and stage entries through: a folder on a shared filesystem "
        "or s3://bucket/prefix (default: the file's store:, else $SPOT_STORE, else local folders)",
    )
    d.add_argument(
        "--tracking-host",
        help="with --address: bind the MLflow server spot starts to this address (e.g. 0.0.0.0) so trials on "
        "other nodes reach it; unauthenticated, see docs/sweeps.md (default: 127.0.0.1)",
    )
    d.add_argument(
        "--dry-run",
        action="store_true",
        help="show what a launch would run and exit; launches nothing: the trial and run counts, then a grid's "
        "trials (axes, seeds) or a search's searcher, num_samples, searched keys' domains and fixed part (base, "
        "seeds); with a scheduler, its metric, mode, options and ASHA's rungs",
    )
    add_quiet(d)  # the datasets the driver builds, the configs' check; Tune's status table stays
    d.add_argument(
        "--status",
        action="store_true",
        help="where the last launch stands, from MLflow: each (config, seed)'s status, final score, or latest "
        "evaluation while it runs; launches nothing; exit code 0 when every run finished, 3 while the launch "
        "or a run is still going, 1 when it ended with runs not finished",
    )
    d.set_defaults(fn=_sweep)


def _sweep(args: argparse.Namespace) -> int:
    from spot import sweep

    if args.status:
        return _sweep_status(args)
    if args.dry_run:
        from spot.sweep import dryrun

        for line in dryrun.lines(sweep.load(args.file, smoke=args.smoke, progress=False if args.quiet else None)):
            print(line)  # a grid's trials, or a search's searcher, space and counts; a scheduler's limits
        return 0
    try:
        rows = sweep.run_sweep(
            args.file,
            smoke=args.smoke,
            resume=args.resume,
            retry_errored=args.retry_errored,
            address=args.address,
            max_concurrent=args.max_concurrent,
            tracking_uri=args.tracking_uri,
            storage=args.storage,
            store=args.store,
            tracking_host=args.tracking_host,
            quiet=args.quiet,
        )
    except sweep.Interrupted as e:
        print(f"interrupted: {e}", file=sys.stderr)
        return e.exit_code  # 143 for SIGTERM, 130 for SIGINT
    return 0 if all(r.status == "FINISHED" for r in rows) else 1  # the summary lists what failed


def _sweep_status(args: argparse.Namespace) -> int:
    from spot import sweep, tracking
    from spot.sweep import status

    given = [
        f"--{k.replace('_', '-')}"
        for k in ("resume", "retry_errored", "dry_run", "address", "max_concurrent", "store", "tracking_host")
        if getattr(args, k)
    ]
    if given:
        raise SpotError(f"--status launches nothing: it does not take {', '.join(given)}")
    spec = sweep.load(args.file, smoke=args.smoke)
    uri = tracking.given_uri(args.tracking_uri) or f"sqlite:///{tracking.SWEEP_STORE.resolve()}"
    st = status.sweep_status(spec, uri, args.storage)
    if not st.sweep_id:
        print(f"sweep '{spec.experiment}': its first launch is starting ({st.launcher}); no run yet")
        return st.exit_code
    running = f"a launch is running ({st.launcher})" if st.launcher else "no launch running"
    print(f"sweep '{spec.experiment}', last launch {st.sweep_id} ({uri}); {running}:")
    if st.previous:
        print("(a new launch is starting: until it opens its parent run, these are the previous launch's runs)")
    print(status.format_status(st, spec.axis_keys))
    return st.exit_code
