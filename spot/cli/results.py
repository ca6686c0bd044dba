"""``spot tables`` (a paper table), ``spot results export|import`` and ``spot report`` (claims
answered from runs)."""

from __future__ import annotations

import argparse
from typing import Any

from spot import SpotError
from spot.cli.common import FORMATS, TABLES, URI_HELP, subcommand


def add(sub: Any) -> None:
    """The tables, results, report commands."""
    _add_tables(sub)
    _add_results(sub)
    _add_report(sub)


# --------------------------------------------------------------------------- tables
def _add_tables(sub: Any) -> None:
    d = subcommand(
        sub,
        "tables",
        "a paper table from the runs (MLflow, results CSVs or a study folder), the paper's numbers beside ours",
        "spot tables --table 1\nspot tables --table 3 --experiment table3_shaping --format latex --out t3.tex\n"
        "spot tables --table 1 experiments/lab-hopper-medium-replay",
    )
    d.add_argument(
        "study",
        nargs="?",
        metavar="STUDY_DIR",
        help="a study folder: the runs its claims.yaml names for this table (its 'tables' entry, else its 'results')",
    )
    d.add_argument("--table", type=int, required=True, choices=TABLES, help="paper table")
    d.add_argument(
        "--experiment",
        action="append",
        help="MLflow experiment (repeatable; default: the table's sweep experiment if present, else all)",
    )
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag spot.sweep_id)")
    d.add_argument("--metric", default="eval/score_final", help="score metric of tables 1-7")
    d.add_argument("--format", default="md", choices=FORMATS, help="output format")
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over seeds: 1 = sample, 0 = population")
    d.add_argument("--allow-mixed", action="store_true", help="average cells whose runs differ in more than the seed")
    d.add_argument("--out", help="write the table to this file instead of printing it")
    d.add_argument("--results", nargs="+", help="read runs from results CSVs (files or folders) instead of MLflow")
    d.set_defaults(fn=_tables)


def _tables(args: argparse.Namespace) -> None:
    from spot.results import load, table_format, tables

    if args.out:
        table_format.check_out(args.out)  # before reading any run
    results, experiments = _table_runs(args)
    if results:
        runs = load.load(results, experiments=experiments)
    else:
        experiments = experiments or tables.default_experiments(args.table, args.tracking_uri)
        from spot.tracking.processes import close_dead_runs_in

        close_dead_runs_in(args.tracking_uri, experiments)  # runs of dead processes are not "running"
        runs = load.load(None, args.tracking_uri, experiments, args.sweep_id)
    table = tables.build_table(runs, args.table, args.metric, ddof=args.ddof, allow_mixed=args.allow_mixed)
    text = table_format.format_table(table, args.format)
    if args.table == 1 and args.format == "md":
        text += table_format.across_datasets(runs, args.metric)
    if args.out:
        table_format.write_out(args.out, text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")


def _table_runs(args: argparse.Namespace) -> tuple[list[Any] | None, list[str] | None]:
    """``(results files or None for MLflow, experiments or None)`` of ``spot tables``: ``--results``,
    or a study folder's claims file (its ``tables`` entry for the table, else its ``results``)."""
    from spot.results import claims

    if not args.study:
        return args.results, args.experiment
    if args.results:
        raise SpotError(f"spot tables: give a study folder ({args.study}) or --results, not both")
    study = claims.load(claims.study_file(args.study))
    source = study.tables.get(args.table, {})
    results = list(source.get("results") or study.results)
    if not results:
        raise SpotError(f"study folder {args.study}: its claims file names no results (for table {args.table} or all)")
    return results, args.experiment or list(source.get("experiments", ())) or None


# --------------------------------------------------------------------------- results export, import
def _add_results(sub: Any) -> None:
    res = sub.add_parser("results", help="export runs from MLflow to a small CSV; import recorded runs").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = subcommand(
        res,
        "export",
        "one row per run: identity, config hash, data digest, params, metrics, evaluation curve",
        "spot results export --experiment table1 --out experiments/my-study/results/table1.csv",
    )
    d.add_argument("--experiment", action="append", required=True, help="MLflow experiment (repeatable)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag spot.sweep_id)")
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.add_argument("--out", required=True, help="the CSV to write, e.g. experiments/<study>/results/<experiment>.csv")
    d.set_defaults(fn=_results_export)

    d = subcommand(
        res,
        "import",
        "log runs recorded as files (spot run --record) into MLflow; again skips those already there",
        "spot results import /data/gpu-records --tracking-uri sqlite:///runs/mlflow.db",
    )
    d.add_argument("folder", help="a folder of records (or one record's folder)")
    d.add_argument("--experiment", help="the MLflow experiment for every record (default: each record's own)")
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.set_defaults(fn=_results_import)


def _results_export(args: argparse.Namespace) -> None:
    from spot import tracking
    from spot.results import export, load

    runs = load.load_runs(args.tracking_uri, args.experiment, args.sweep_id)
    if runs.empty:
        raise SpotError(f"no runs in experiments {args.experiment} of {args.tracking_uri or 'the default store'}")
    path = export.export(export.add_curves(runs, tracking.reader(args.tracking_uri)), args.out)
    print(f"wrote {path} ({len(runs)} runs)")


def _results_import(args: argparse.Namespace) -> None:
    from spot.tracking import recorded

    done = recorded.import_records(args.folder, args.tracking_uri, args.experiment)
    for item in done:
        print(f"{item['record_id']}: {item['action']}" + (f" as run {item['run_id']}" if item["run_id"] else ""))
    n = sum(item["action"] == "imported" for item in done)
    print(f"{n} of {len(done)} records imported")


# --------------------------------------------------------------------------- report
def _add_report(sub: Any) -> None:
    d = subcommand(
        sub,
        "report",
        "claims answered from runs: effect, 95%% CI, n and verdict per claim (the paper's, or a claims file's)",
        "spot report experiments/lab-hopper-full-replay --out report.md\nspot report --claims my_claims.yaml",
    )
    d.add_argument(
        "study", nargs="?", metavar="STUDY_DIR", help="a study folder: its claims.yaml and the runs it names"
    )
    d.add_argument(
        "--claims",
        metavar="FILE",
        help="a claims file (docs/tables.md; its results relative to it); default: the paper's claims over MLflow",
    )
    d.add_argument("--results", nargs="+", help="results CSVs (files or folders) instead of the claims file's")
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag spot.sweep_id)")
    d.add_argument(
        "--use",
        action="append",
        metavar="SET=EXPERIMENT",
        help="read a set of the claims file from these experiments instead ('a+b': two together)",
    )
    d.add_argument(
        "--high-mode",
        type=float,
        default=50.0,
        metavar="SCORE",
        help="count the periodic evaluations scoring at least SCORE, per arm, from the exported curves (default 50)",
    )
    d.add_argument("--out", help="write the report (Markdown) to this file instead of printing it")
    d.add_argument(
        "--html",
        metavar="FILE",
        help="also write one self-contained HTML page: the figures (claims, curves, profile) and the tables",
    )
    d.set_defaults(fn=_report)


def _report(args: argparse.Namespace) -> None:
    from spot.results import report, table_format

    if args.out:
        table_format.check_out(args.out)  # before reading any run
    if args.html:
        table_format.check_out(args.html)
    claims_file, runs = report_inputs(args, curves=bool(args.html))
    built = report.build(runs, claims_file, args.high_mode)
    if args.html:
        from spot.results import figures_report

        title = f"spot report: {args.study or args.claims or 'the paper claims'}"
        table_format.write_out(args.html, figures_report.html_page(runs, built, title))
        print(f"wrote {args.html}")
    text = report.format_report(built)
    if args.out:
        table_format.write_out(args.out, text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")


def report_inputs(args: argparse.Namespace, curves: bool = False) -> tuple[Any, Any]:
    """``(claims file, runs)`` of ``spot report`` (and ``spot figures claims``): a study folder or
    ``--claims FILE`` (with ``--use``), and its results, ``--results`` or the MLflow store (each
    run's eval/score history too with ``curves``, as a results CSV holds it)."""
    from spot.results import claims, export, load

    if args.study and args.claims:
        raise SpotError(f"spot report: give a study folder ({args.study}) or --claims FILE, not both")
    use = {}
    for item in args.use or []:
        key, sep, names = item.partition("=")
        if not sep or not key or not names:
            raise SpotError(f"--use {item!r}: expected SET=EXPERIMENT[+EXPERIMENT...], SET a set of the claims file")
        use[key] = tuple(names.split("+"))
    claims_file = claims.load(claims.study_file(args.study) if args.study else args.claims, use)
    results = args.results or list(claims_file.results)
    if results:
        runs = load.read(results)
    else:  # the claims file names no results: the MLflow store
        from spot import tracking

        runs = load.load_runs(args.tracking_uri, None, args.sweep_id)
        runs = export.to_frame(export.add_curves(runs, tracking.reader(args.tracking_uri)) if curves else runs)
    return claims_file, runs
