"""The ``spot`` command. Thin: parses arguments and calls into the library.

User errors (:class:`spot.SpotError`) print one line ``error: ...`` and exit with code 2; no
traceback. Run ``spot <command> --help`` for each command's options, defaults and an example.
One name per concept across commands: ``--tracking-uri`` (the MLflow store), ``--data-seed`` (the
dataset build seed, ``data.build_seed``; ``--seed`` is its old name), ``--quiet`` (no progress
bars) wherever a command draws them.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from spot import NonFiniteError, SpotError
from spot.data import registry


# --------------------------------------------------------------------------- data
def _data_list(args: argparse.Namespace) -> None:
    print(f"{'name':28s} {'family':11s} description")
    for e in registry.REGISTRY.values():
        print(f"{e.name:28s} {e.family:11s} {e.description}")
    sizes = ", ".join(registry.SIZES).replace("paper-fast", "paper-fast (hopper-*, walker2d-* only)")
    print(f"\nsizes: {sizes}   cache dir: {registry.data_dir()} (set SPOT_DATA_DIR)")
    built = registry.cached()
    if built:
        print("\nbuilt:")
        for b in built:
            print(
                f"  {b['name']} size={b['size']} seed={b['seed']} transitions={b['transitions']}  {b['path']}"
                + ("" if b["status"] == "ok" else f"  [{b['status']}]")
            )


def _data_build(args: argparse.Namespace) -> None:
    path = registry.build(args.name, args.size, args.data_seed, force=args.force, progress=not args.quiet)
    card = registry.read_card(path)
    print(f"built {path}")
    print(json.dumps({k: card[k] for k in card if k not in ("name",)}, indent=2, default=str))


def _data_info(args: argparse.Namespace) -> None:
    as_path = Path(args.name)
    if not as_path.exists():
        registry.entry(args.name)  # unknown names fail here, before any build
        path = registry.dataset_path(args.name, args.size, args.data_seed)
        if not path.exists():
            raise SpotError(
                f"dataset '{args.name}' (size {args.size}, seed {args.data_seed}) is not built yet; "
                f"run: spot data build {args.name} --size {args.size} --data-seed {args.data_seed}"
            )
        args.name = str(path)
    ds, card = registry.load(args.name, source="file", progress=not args.quiet)
    print(json.dumps({"summary": ds.summary(), "card": card}, indent=2, default=str))


def _data_fetch(args: argparse.Namespace) -> None:
    from spot.data import fetch

    if args.list:
        sources = fetch.load_registry(args.registry)
        print(f"{'name':36s} {'files':>5s} {'bytes':>12s}  {'checksum from':22s} description")
        for s in sources.values():
            sizes = [f.size for f in s.files]
            total = f"{sum(sizes):,}" if None not in sizes else "?"
            trust = ",".join(sorted({f.trust for f in s.files}))
            print(f"{s.name:36s} {len(s.files):5d} {total:>12s}  {trust:22s} {s.description}")
        print(
            f"{'minari:<dataset id>':36s} {'':5s} {'':>12s}  {'tofu':22s} a Minari dataset through "
            "minari.download_dataset (extra 'minari')"
        )
        print(
            "\nchecksum from: lfs-oid = a mirror's published Git LFS id; git-commit = the file in a "
            "pinned git commit; third-party = recorded by an independent project; tofu = trust on "
            f"first use (recorded in the lock file, default ./{fetch.DEFAULT_LOCK})"
        )
        print(
            f"destination: {args.dest or fetch.default_dest()}   registry: "
            f"{fetch.registry_path(args.registry) or 'spot/data/sources.json (package)'}"
        )
        return
    if not args.name:
        raise SpotError("spot data fetch needs a NAME (or --list)")
    if args.name.startswith(fetch.MINARI_PREFIX):
        folder, digest, status = fetch.fetch_minari(args.name[len(fetch.MINARI_PREFIX) :], lock=args.lock)
        lock = args.lock or fetch.default_lock()
        what = (
            "TOFU: Minari publishes no checksums; recorded the folder digest in"
            if status == "recorded"
            else "matches the folder digest in"
        )
        print(f"fetched {args.name} -> {folder}\n  {what} {lock}: {digest}")
        return
    result = fetch.fetch(
        args.name, args.dest, mirrors=args.mirror, registry=args.registry, lock=args.lock, progress=not args.quiet
    )
    src = result.source
    print(f"fetched {src.name} -> {(args.dest and Path(args.dest)) or fetch.default_dest()}")
    for f in result.files:
        print(f"  {f.status:10s} {f.path}  {f.size:,} B  sha256 {f.sha256}")
        if f.status == "recorded":
            print(
                f"             TOFU: no published checksum; this first download's sum is now in "
                f"{result.lock}: commit it, later downloads must match"
            )
        else:
            print(f"             verified against: {fetch._trust_words(f.trust)}")
    if src.kind in ("d4rl", "robomimic"):
        print(f"use it: data.name={result.files[0].path}")
        if src.labels:
            print(f"human labels: spot data fetch {src.labels}, then labels.source=human labels.path=<its folder>")
    elif src.kind == "pt-labels":
        print(
            f"use it: labels.source=human labels.path={result.files[0].path.parent} (with the data of {src.labels_for})"
        )


# --------------------------------------------------------------------------- labels
# `spot labels make` flags -> the config keys they set (None: not given, the resolved config decides).
_LABEL_FLAGS = {
    "num_queries": "labels.num_queries",
    "segment_length": "labels.segment_length",
    "teacher": "labels.teacher",
    "score": "labels.score",
    "discount": "labels.discount",
    "tie_threshold": "labels.tie_threshold",
    "mistake_rate": "labels.mistake_rate",
    "allow_cross_episode": "labels.allow_cross_episode",
    "label_seed": "labels.seed",
    "size": "data.size",
    "data_seed": "data.build_seed",
}


def _labels_make(args: argparse.Namespace) -> None:
    """The queries `spot run` would make with the same config: the labels settings are resolved like
    a run's (defaults < method < budget < suite preset < --config file < overrides and flags)."""
    from spot import config, stages

    flags = [f"{key}={getattr(args, name)}" for name, key in _LABEL_FLAGS.items() if getattr(args, name) is not None]
    cfg = config.load(args.config_file, [f"data.name={args.dataset}", *args.overrides, *flags])
    ds, card = registry.load(
        cfg.data.name, cfg.data.size, cfg.data.build_seed, source=cfg.data.source, progress=not args.quiet
    )
    prefs = stages.make_preferences(cfg, ds, card)
    prefs.save_npz(args.out)
    lc = cfg.labels
    print(f"wrote {len(prefs)} queries (segment length {prefs.segment_length}) to {args.out}")
    print(
        f"settings (method={cfg.method}, budget={cfg.budget}): source={lc.source} teacher={lc.teacher} "
        f"score={lc.score} discount={lc.discount} tie_threshold={lc.tie_threshold} "
        f"mistake_rate={lc.mistake_rate} allow_cross_episode={lc.allow_cross_episode} seed={lc.seed}"
    )
    _print_label_stats(prefs)


def _print_label_stats(prefs) -> None:
    import numpy as np

    y = prefs.labels
    print(
        f"labels: seg1 preferred {int(np.sum(y == 0))}, seg2 preferred {int(np.sum(y == 1))}, "
        f"ties {int(np.sum(y == 0.5))}"
    )


def _labels_info(args: argparse.Namespace) -> None:
    from spot.data import labels, registry

    path = Path(args.path)
    prefs = labels.read_pt_labels(path) if path.is_dir() else labels.Preferences.load_npz(path)
    print(f"{path}: {len(prefs)} queries, segment length {prefs.segment_length}, source {prefs.source}")
    _print_label_stats(prefs)
    if args.dataset:
        ds, _ = registry.load(args.dataset, args.size, args.data_seed, progress=not args.quiet)
        labels.check_against(prefs, ds)
        print(f"all segments fit dataset '{ds.name}' ({len(ds)} transitions)")


# --------------------------------------------------------------------------- config
def _config_show(args: argparse.Namespace) -> None:
    from spot import config

    print(config.to_yaml(config.load(args.config, args.overrides)), end="")


def _config_keys(args: argparse.Namespace) -> None:
    from spot import config

    for key in config.valid_keys():
        tp, meta = config.field_info(key)
        extra = ""
        if meta.get("choices"):
            extra = f" one of {list(meta['choices'])}"
        elif meta.get("range"):
            extra = f" in [{meta['range'][0]}, {meta['range'][1]}]"
        print(f"{key:26s} {getattr(tp, '__name__', str(tp)):8s} {meta.get('help', '')}{extra}")


# --------------------------------------------------------------------------- run
def _seed_list(text: str) -> list[int]:
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integer seeds, e.g. 0,1,2, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"expected distinct comma-separated seeds, e.g. 0,1,2, got {text!r}")
    return seeds


def _method_list(text: str) -> list[str]:
    from spot.config import METHODS

    methods = [x.strip() for x in text.split(",") if x.strip()]
    bad = [m for m in methods if m not in METHODS]
    if not methods or bad or len(set(methods)) != len(methods):
        raise argparse.ArgumentTypeError(
            f"expected distinct comma-separated methods of {', '.join(METHODS)}, e.g. oracle,pt,spot, got {text!r}"
        )
    return methods


def _terminate_as_interrupt(signum: int, frame: Any) -> None:
    """SIGTERM during ``spot run``: end the run as Ctrl-C does (its MLflow run or record KILLED).
    Python acts on it between jitted chunks, as on Ctrl-C."""
    raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")


def _run(args: argparse.Namespace) -> None:
    from spot import config, multiseed, pipeline, tracking

    overrides = [*args.overrides, *([f"tracking.uri={args.tracking_uri}"] if args.tracking_uri else [])]
    overrides += [f"tracking.record={args.record}"] if args.record else []
    cfg = config.load(args.config, overrides)
    methods = [config.load(args.config, [*overrides, f"method={m}"]) for m in args.methods] if args.methods else [cfg]
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt) if main_thread else None
    try:
        if args.seeds or args.methods:
            cfgs = [config.replace(c, seed=s) for c in methods for s in (args.seeds or [c.seed])]
            finals = multiseed.run(cfgs, progress=not args.quiet)
        else:
            cfgs, finals = [cfg], [pipeline.run(cfg, progress=not args.quiet)]
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    for c, final in zip(cfgs, finals, strict=True):
        print(f"run {final['run_id']}: {c.method} on {c.data.name} (seed {c.seed})")
        for key in sorted(final):
            if key != "run_id":
                print(f"  {key:24s} {final[key]:.3f}")
    if cfg.tracking.record:
        print(f"recorded under {cfg.tracking.record}; log into MLflow with: spot results import {cfg.tracking.record}")
        return
    from mlflow.tracking import MlflowClient

    uri = tracking.resolve_uri(cfg.tracking.uri)
    exp_id = MlflowClient(uri).get_run(finals[0]["run_id"]).info.experiment_id
    for final in finals:
        print("\n".join(tracking.where_logged(uri, exp_id, final["run_id"])))


def _eval(args: argparse.Namespace) -> None:
    from spot import pipeline

    res = pipeline.evaluate_run(args.run_id, args.tracking_uri, args.episodes)
    n, seed = res["episodes"], res["eval_seed"]
    print(
        f"run {res['run_id']}: {res['method']} policy after {res['steps']} updates on {res['env']}, "
        f"{n} episodes (env seeds {seed}..{seed + n - 1})"
    )
    print(f"  {'score_mean':24s} {res['score_mean']:.3f}")
    print(f"  {'score_std':24s} {res['score_std']:.3f}")
    print(f"  {'return_mean':24s} {res['return_mean']:.3f}")
    print(f"  {'length_mean':24s} {res['length_mean']:.1f}")
    logged = res["logged_score_final"]
    if logged is None:
        print("  the run logged no eval/score_final")
    elif abs(logged - res["score_mean"]) <= 1e-9 * max(1.0, abs(logged)):
        print(f"  reproduces the logged eval/score_final {logged:.3f}")
    else:
        print(
            f"  logged eval/score_final {logged:.3f} (differs: other episodes{' count' if args.episodes else ''}, "
            "or another machine's floating point)"
        )


# --------------------------------------------------------------------------- bench
def _bench(args: argparse.Namespace) -> int | None:
    from spot import bench

    for flag, value in (("--env", args.env), ("--size", args.size)):
        if value and args.what != "sac":
            raise SpotError(f"spot bench {args.what}: {flag} goes with 'spot bench sac'")
    if args.episodes and args.what != "eval":
        raise SpotError(f"spot bench {args.what}: --episodes goes with 'spot bench eval'")
    if args.what == "sweep":
        if not args.file:
            raise SpotError("spot bench sweep needs the sweep file: spot bench sweep FILE [--smoke]")
        return bench.bench_sweep(args.file, smoke=args.smoke)
    if args.file or args.smoke:
        raise SpotError(f"spot bench {args.what}: a sweep file and --smoke go with 'spot bench sweep'")
    kwargs = {"small": args.small}
    if args.what == "iql":
        kwargs["seeds"], kwargs["order"] = args.seeds, args.order
    if args.what == "pt":
        kwargs["dtype"], kwargs["seeds"] = args.dtype, args.seeds
    if args.what == "eval":
        kwargs["seeds"], kwargs["episodes"] = args.seeds, args.episodes or 10
    if args.seeds != 1 and args.what not in ("iql", "pt", "eval"):
        raise SpotError(f"spot bench {args.what}: --seeds (seeds as a vmap axis) goes with iql, pt and eval")
    if args.what == "relabel":
        kwargs["mode"] = args.mode
    if args.what == "sac":
        kwargs["env"], kwargs["size"] = args.env, args.size
    print(bench.format_result(args.what, bench.BENCHES[args.what](**kwargs)))


# --------------------------------------------------------------------------- sweep
def _sweep(args: argparse.Namespace) -> int:
    from spot import sweep

    if args.status:
        return _sweep_status(args)
    if args.dry_run:
        spec = sweep.load(args.file, smoke=args.smoke)
        trials = spec.trials()
        print(
            f"sweep '{spec.experiment}' ({spec.path}): {len(trials)} trials, {len(spec.runs())} runs, "
            f"seed_mode {spec.seed_mode}, resources per trial {spec.resources}"
        )
        for i, t in enumerate(trials):
            print(f"  {i:4d}  {t.label}  seeds={list(t.seeds)}")
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


# --------------------------------------------------------------------------- tables, figures
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


def _report(args: argparse.Namespace) -> None:
    from spot.results import claims, export, load, report, table_format

    if args.out:
        table_format.check_out(args.out)  # before reading any run
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
        runs = export.to_frame(load.load_runs(args.tracking_uri, None, args.sweep_id))
    text = report.format_report(report.build(runs, claims_file, args.high_mode))
    if args.out:
        table_format.write_out(args.out, text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")


def _figures(args: argparse.Namespace) -> None:
    from spot import figures
    from spot.results import load

    figures.image_format(args.out)  # an unknown extension fails before any work
    if args.figure == "fig2":
        runs = load.load_runs(args.tracking_uri, args.experiment, args.sweep_id)
        bins = figures.extrapolation_bins(runs, args.tracking_uri, dataset=args.dataset, source=args.source)
        print(figures.summarize_extrapolation(bins, ddof=args.ddof).to_string(index=False))
        print(f"wrote {figures.plot_fig2(bins, args.out, ddof=args.ddof)}")
        return
    if args.cvae:
        if not args.dataset:
            raise SpotError("--cvae needs --dataset (the transitions to generate subgoals for)")
        params = figures.load_cvae(args.cvae)
        ds, _ = registry.load(args.dataset, args.size, args.data_seed, progress=False)
    if args.figure == "fig3":
        if args.pairs:
            if not args.env:
                raise SpotError("--pairs needs --env (e.g. Hopper-v5 or hopper-medium-expert)")
            obs, goal = figures.pairs_from_file(args.pairs)
        elif args.run_id and args.index:  # the run's CVAE on the run's dataset (or --dataset)
            params, cfg, head = figures.cvae_from_run(args.run_id, args.tracking_uri)
            if args.dataset:
                ds, _ = registry.load(args.dataset, args.size, args.data_seed, progress=False)
            else:
                ds, _ = registry.load(
                    cfg.data.name, cfg.data.size, cfg.data.build_seed, source=cfg.data.source, progress=False
                )
                args.dataset = head.get("dataset") or cfg.data.name
            obs, goal = figures.pairs_from_cvae(params, ds.observations, ds.actions, args.index)
        elif args.cvae and args.index:
            obs, goal = figures.pairs_from_cvae(params, ds.observations, ds.actions, args.index)
        else:
            raise SpotError(
                "fig3 needs --pairs FILE.npy --env ENV, --run-id ID --index I [I ...], "
                "or --cvae FILE --dataset NAME --index I [I ...]"
            )
        path = figures.render_state_and_subgoal(
            args.env or args.dataset, obs, goal, args.out, width=args.width, height=args.height
        )
    elif args.run_id:
        path = figures.fetch_artifact(args.run_id, figures.FIG4_ARTIFACT, args.out, args.tracking_uri)
    elif args.cvae:
        path = figures.projection_from_cvae(params, ds.observations, ds.actions, args.out)
    else:
        raise SpotError("fig4 needs --run-id ID, or --cvae FILE --dataset NAME")
    print(f"wrote {path}")


# --------------------------------------------------------------------------- parser
class _Formatter(argparse.HelpFormatter):
    """Wraps one-paragraph descriptions, keeps the line breaks of the examples, and adds
    ``(default: X)`` to every option with a default worth showing (not None, False or an empty
    list; not where the help names the default)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if "\n" in text:
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            default is None
            or default is False
            or default is argparse.SUPPRESS
            or default in ("", [])
            or "default" in text
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        return f"{text} (default: %(default)s)"


def _parser(sub: Any, name: str, help: str, examples: str, **kw: Any) -> argparse.ArgumentParser:
    """A subcommand with the shared formatter and ``examples`` (one per line) as its epilog."""
    lines = "\n".join(f"  {line}" for line in examples.strip().splitlines())
    return sub.add_parser(
        name,
        help=help,
        description=kw.pop("description", help[0].upper() + help[1:] + "."),
        epilog=f"example{'s' if len(examples.strip().splitlines()) > 1 else ''}:\n{lines}",
        formatter_class=_Formatter,
        **kw,
    )


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer (>= 1), got {value}")
    return value


def _data_seed(d: argparse.ArgumentParser, default: int | None = 0, what: str = "dataset build seed") -> None:
    """``--data-seed`` (``data.build_seed``), with ``--seed`` kept as its old name."""
    d.add_argument(
        "--data-seed",
        "--seed",
        dest="data_seed",
        type=int,
        default=default,
        help=f"{what} (data.build_seed; --seed is the old name)",
    )


def _quiet(d: argparse.ArgumentParser) -> None:
    d.add_argument("--quiet", action="store_true", help="no progress bars")


_URI_HELP = "MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db or ./mlruns/mlflow.db)"
_SIZES = registry.SIZES


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    from spot import __version__

    try:
        return f"spot {version('spot-pbrl')}"
    except PackageNotFoundError:
        return f"spot {__version__} (not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="spot",
        description="Offline preference-based RL: SPOT and baselines.",
        formatter_class=_Formatter,
        epilog="examples:\n  spot sweep sweeps/quickstart.yaml --smoke\n  spot run configs/quickstart.yaml method=pt\n"
        "  spot tables --table 1\n\nEvery command has --help with its options, defaults and an example.",
    )
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    for add in (_add_data, _add_labels, _add_run, _add_bench, _add_sweep, _add_tables, _add_figures):
        add(sub)
    return p


def _add_data(sub: Any) -> None:
    """The data: list, build, info, fetch commands."""
    data = sub.add_parser("data", help="list, build, inspect and fetch datasets").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = _parser(data, "list", "registered datasets and what is built", "spot data list")
    d.set_defaults(fn=_data_list)
    d = _parser(
        data,
        "build",
        "build a dataset with its local recipe (once; cached)",
        "spot data build hopper-medium-replay --size small --data-seed 0",
    )
    d.add_argument("name", help="registered dataset name (spot data list)")
    d.add_argument("--size", default="small", choices=_SIZES, help="dataset size")
    _data_seed(d)
    d.add_argument("--force", action="store_true", help="rebuild even if cached")
    _quiet(d)
    d.set_defaults(fn=_data_build)
    d = _parser(
        data,
        "info",
        "summary and card of a built dataset or an hdf5 file",
        "spot data info hopper-medium-replay --size tiny",
    )
    d.add_argument("name", help="registered name or path")
    d.add_argument("--size", default="small", choices=_SIZES, help="dataset size (registered names)")
    _data_seed(d)
    _quiet(d)
    d.set_defaults(fn=_data_info)
    d = _parser(
        data,
        "fetch",
        "download the paper's real data files (D4RL, robomimic, PT labels), verified",
        "spot data fetch --list\nspot data fetch d4rl/hopper-medium-replay-v2",
        description="Download a registered source's files to DEST with resume and mirror fallback; "
        "each file's size and sha256 are verified before it is put in place.",
    )
    d.add_argument("name", nargs="?", help="registry name (see --list) or minari:<dataset id>")
    d.add_argument("--list", action="store_true", help="list the registered sources and exit")
    d.add_argument("--dest", help="destination folder (default: $SPOT_DATA_DIR/real)")
    d.add_argument(
        "--mirror",
        action="append",
        default=[],
        metavar="URL",
        help="base URL tried first, as URL/<file path> (repeatable)",
    )
    d.add_argument(
        "--registry",
        metavar="FILE",
        help="another sources registry in the same JSON format, e.g. a private mirror "
        "or a test server (default: $SPOT_FETCH_REGISTRY, else the package's)",
    )
    d.add_argument(
        "--lock",
        metavar="FILE",
        help="trust-on-first-use lock file (default: $SPOT_DATA_LOCK, else ./spot-data.lock.json)",
    )
    _quiet(d)
    d.set_defaults(fn=_data_fetch)


def _add_labels(sub: Any) -> None:
    """The labels: make, info commands."""
    lab = sub.add_parser("labels", help="make and inspect preference queries").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = _parser(
        lab,
        "make",
        "the preference queries `spot run` would make on a dataset -> .npz",
        "spot labels make drawer-open --out queries.npz --size tiny method=ipl",
        description="Resolves the labels settings like `spot run` (method, budget and suite "
        "presets, --config, KEY=VALUE overrides); the flags are shorthands for "
        "labels.* keys and win over the overrides.",
    )
    d.add_argument("dataset", help="data.name: a registered name or a dataset file")
    d.add_argument("overrides", nargs="*", help="a.b=value config overrides, e.g. method=ipl budget=paper")
    d.add_argument("--out", required=True, help="output .npz")
    d.add_argument("--config", dest="config_file", help="YAML run config (as for `spot run`)")
    d.add_argument("--size", choices=_SIZES, help="data.size (default: the budget's)")
    _data_seed(d, None, "dataset build seed (default: the config's)")
    d.add_argument("--num-queries", type=int, help="labels.num_queries")
    d.add_argument("--segment-length", type=int, help="labels.segment_length")
    d.add_argument("--teacher", choices=("sum", "discounted"), help="labels.teacher")
    d.add_argument(
        "--score",
        choices=("reward", "dense"),
        help="labels.score: sum the dataset's reward or its dense reward infos/dense_reward (robosuite recipes)",
    )
    d.add_argument("--discount", type=float, help="labels.discount")
    d.add_argument("--tie-threshold", type=float, help="labels.tie_threshold (negative: no ties)")
    d.add_argument("--mistake-rate", type=float, help="labels.mistake_rate")
    d.add_argument("--allow-cross-episode", action="store_true", default=None, help="labels.allow_cross_episode=true")
    d.add_argument("--label-seed", type=int, help="labels.seed")
    _quiet(d)
    d.set_defaults(fn=_labels_make)
    d = _parser(
        lab,
        "info",
        "inspect a .npz query file or a PT human-label folder",
        "spot labels info queries.npz --dataset drawer-open --size tiny",
    )
    d.add_argument("path", help=".npz query file or PT human-label folder")
    d.add_argument("--dataset", help="check that every segment fits this dataset")
    d.add_argument("--size", default="small", choices=_SIZES, help="with --dataset: its size")
    _data_seed(d)
    _quiet(d)
    d.set_defaults(fn=_labels_info)


def _add_run(sub: Any) -> None:
    """The run, eval commands."""
    d = _parser(
        sub,
        "run",
        "one run (one seed) end to end, logged to MLflow",
        "spot run configs/quickstart.yaml method=spot seed=1\n"
        "spot run method=pt budget=tiny data.name=drawer-open --tracking-uri http://127.0.0.1:5000\n"
        "spot run budget=paper --methods oracle,pt,spot --seeds 0,1,2 --record /scratch/records",
        description="One run (one seed) end to end, logged to MLflow. It ends with where it logged, "
        "the mlflow ui command and a link to the run. With --seeds and --methods, several runs as one program "
        "(IQL vmapped over them: a GPU's throughput); with --record, recorded as files for 'spot results import'.",
    )
    d.add_argument("config", nargs="?", help="YAML run config (see configs/)")
    d.add_argument("overrides", nargs="*", help="a.b=value overrides, e.g. method=pt iql.steps=5000")
    d.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI, same as the override tracking.uri=URI (default: "
        "tracking.uri, else $MLFLOW_TRACKING_URI, else ./mlruns/mlflow.db)",
    )
    d.add_argument(
        "--seeds",
        type=_seed_list,
        metavar="S1,S2,...",
        help="run these seeds of the config as one program, IQL vmapped over them (a run per seed; the config's "
        "seed is ignored); methods trained by IQL only",
    )
    d.add_argument(
        "--methods",
        type=_method_list,
        metavar="M1,M2,...",
        help="run these methods of the config (each with --seeds) as one program, IQL vmapped over all of them "
        "(a run each); their data.*, iql.* and eval.* must agree",
    )
    d.add_argument(
        "--record",
        metavar="FOLDER",
        help="record the runs as files in FOLDER instead of MLflow (same as tracking.record=FOLDER; a machine "
        "without MLflow); log them into a store later with 'spot results import FOLDER'",
    )
    _quiet(d)
    d.set_defaults(fn=_run)

    d = _parser(
        sub,
        "eval",
        "evaluate a logged run's saved policy again",
        "spot eval 3f9c2a61d0b84e7f9a6c1e2d4b5a7c90 --episodes 10 --tracking-uri sqlite:///spot_runs/mlflow.db",
        description="Download a run's policy (models/policy) and config, rebuild its evaluation env "
        "and evaluate the policy's mean action on the run's evaluation seeds. With the "
        "run's last-evaluation episodes (eval.final_episodes, else eval.episodes) this reproduces its "
        "eval/score_final.",
    )
    d.add_argument("run_id", help="MLflow run id")
    d.add_argument(
        "--episodes", type=_positive_int, help="episodes (default: the run's eval.final_episodes, else eval.episodes)"
    )
    d.add_argument("--tracking-uri", help=_URI_HELP)
    d.set_defaults(fn=_eval)


def _add_bench(sub: Any) -> None:
    """The bench command."""
    from spot.config import IQL_ORDERS, IQLConfig

    d = _parser(
        sub,
        "bench",
        "throughput, compile time and peak memory of a stage (paper sizes)",
        "spot bench iql --small\nspot bench iql --seeds 5 --order sequential\nspot bench pt --small --seeds 2\n"
        "spot bench sac --env hopper --size paper-fast\nspot bench eval\nspot bench sweep sweeps/quickstart.yaml",
    )
    d.add_argument("what", choices=("iql", "pt", "relabel", "cvae", "sac", "eval", "sweep"), help="a stage, or a sweep")
    d.add_argument("file", nargs="?", help="sweep: the sweep file (runs it; prints each trial's time by phase)")
    d.add_argument("--smoke", action="store_true", help="sweep: the file's smoke block")
    d.add_argument("--small", action="store_true", help="small sizes: a quick check in seconds")
    d.add_argument("--seeds", type=_positive_int, default=1, help="iql, pt: seeds as a vmap axis; eval: runs")
    d.add_argument("--episodes", type=_positive_int, help="eval: episodes per run, batched vs sequential (default 10)")
    d.add_argument("--order", default=IQLConfig.order, choices=IQL_ORDERS, help="iql: update order (iql.order)")
    d.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="pt: compute dtype")
    d.add_argument("--mode", default="chunked", choices=("chunked", "sliding"), help="relabel: mode")
    d.add_argument("--env", choices=("hopper", "walker2d"), help="sac: the locomotion recipe's env (default: walker2d)")
    d.add_argument("--size", choices=("paper", "paper-fast"), help="sac: the recipe's size (default: paper)")
    d.set_defaults(fn=_bench)


def _add_sweep(sub: Any) -> None:
    """The sweep, config commands."""
    d = _parser(
        sub,
        "sweep",
        "run a sweep file (sweeps/*.yaml) with Ray Tune, logged to MLflow",
        "spot sweep sweeps/quickstart.yaml --smoke\nspot sweep sweeps/paper/table1.yaml --address auto --max-concurrent 8",
        description="Run a sweep file with Ray Tune, one MLflow run per (config, seed). Exit code 0 "
        "when every run finished, 1 otherwise. See docs/sweeps.md.",
    )
    d.add_argument("file", help="sweep YAML file")
    d.add_argument("--smoke", action="store_true", help="apply the file's smoke block (experiment <name>-smoke)")
    d.add_argument("--resume", action="store_true", help="continue the last launch of this sweep")
    d.add_argument("--retry-errored", action="store_true", help="with --resume: run failed trials again")
    d.add_argument("--address", help="Ray cluster address (default: local Ray on all CPUs)")
    d.add_argument(
        "--max-concurrent", type=_positive_int, help="trials at once, >= 1 (default: the file's max_concurrent)"
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
    d.add_argument("--dry-run", action="store_true", help="list the trials (axes, seeds) and exit; launches nothing")
    d.add_argument(
        "--status",
        action="store_true",
        help="where the last launch stands, from MLflow: each (config, seed)'s status, final score, or latest "
        "evaluation while it runs; launches nothing; exit code 0 when every run finished, 3 while the launch "
        "or a run is still going, 1 when it ended with runs not finished",
    )
    d.set_defaults(fn=_sweep)

    cfg = sub.add_parser("config", help="show resolved run configs and valid keys").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = _parser(cfg, "show", "print the fully resolved config", "spot config show configs/quickstart.yaml method=pt")
    d.add_argument("config", nargs="?", help="YAML run config")
    d.add_argument("overrides", nargs="*", help="a.b=value overrides")
    d.set_defaults(fn=_config_show)
    d = _parser(cfg, "keys", "every config key with type, help and valid values", "spot config keys | grep '^iql'")
    d.set_defaults(fn=_config_keys)


def _add_tables(sub: Any) -> None:
    """The tables, results, report commands."""
    from spot.results import table_format, tables

    d = _parser(
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
    d.add_argument("--table", type=int, required=True, choices=tables.TABLES, help="paper table")
    d.add_argument(
        "--experiment",
        action="append",
        help="MLflow experiment (repeatable; default: the table's sweep experiment if present, else all)",
    )
    d.add_argument("--tracking-uri", help=_URI_HELP)
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--metric", default="eval/score_final", help="score metric of tables 1-7")
    d.add_argument("--format", default="md", choices=table_format.FORMATS, help="output format")
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over seeds: 1 = sample, 0 = population")
    d.add_argument("--allow-mixed", action="store_true", help="average cells whose runs differ in more than the seed")
    d.add_argument("--out", help="write the table to this file instead of printing it")
    d.add_argument("--results", nargs="+", help="read runs from results CSVs (files or folders) instead of MLflow")
    d.set_defaults(fn=_tables)

    res = sub.add_parser("results", help="export runs from MLflow to a small CSV; import recorded runs").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = _parser(
        res,
        "export",
        "one row per run: identity, config hash, data digest, params, metrics, evaluation curve",
        "spot results export --experiment table1 --out experiments/my-study/results/table1.csv",
    )
    d.add_argument("--experiment", action="append", required=True, help="MLflow experiment (repeatable)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--tracking-uri", help=_URI_HELP)
    d.add_argument("--out", required=True, help="the CSV to write, e.g. experiments/<study>/results/<experiment>.csv")
    d.set_defaults(fn=_results_export)

    d = _parser(
        res,
        "import",
        "log runs recorded as files (spot run --record) into MLflow; again skips those already there",
        "spot results import /data/gpu-records --tracking-uri sqlite:///runs/mlflow.db",
    )
    d.add_argument("folder", help="a folder of records (or one record's folder)")
    d.add_argument("--experiment", help="the MLflow experiment for every record (default: each record's own)")
    d.add_argument("--tracking-uri", help=_URI_HELP)
    d.set_defaults(fn=_results_import)
    _add_report(sub)


def _add_report(sub: Any) -> None:
    """The report command."""
    d = _parser(
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
    d.add_argument("--tracking-uri", help=_URI_HELP)
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
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
    d.set_defaults(fn=_report)


def _add_figures(sub: Any) -> None:
    """The figures: fig2, fig3, fig4 commands."""
    figs = sub.add_parser("figures", help="the paper's figures 2, 3 and 4 from runs").add_subparsers(
        dest="figure", required=True, metavar="FIGURE"
    )
    d = _parser(
        figs,
        "fig2",
        "extrapolation error vs cos(s, g), PT vs SPOT, in-distribution vs OOD",
        "spot figures fig2 --experiment table1 --out fig2.pdf",
    )
    d.add_argument("--experiment", action="append", help="MLflow experiment (repeatable; default: all)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--dataset", help="the paper's dataset name, if the runs span several")
    d.add_argument("--source", choices=("recipe", "file"), help="dataset source, if the runs span both")
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over runs: 1 = sample, 0 = population")
    d.add_argument(
        "--out", default="fig2.png", help="output file; its extension picks the format (.png, .pdf, .svg...)"
    )
    d = _parser(
        figs,
        "fig3",
        "locomotion states rendered beside their predicted subgoals (MuJoCo, headless)",
        "spot figures fig3 --run-id 3f9c2a61d0b84e7f9a6c1e2d4b5a7c90 --index 120 480\n"
        "spot figures fig3 --pairs pairs.npy --env Hopper-v5",
    )
    d.add_argument("--pairs", help=".npy of [2, obs_dim] or [n, 2, obs_dim] (state, subgoal)")
    d.add_argument("--run-id", help="use this run's CVAE (its models/cvae artifact) on the run's dataset")
    d.add_argument("--env", help="Hopper-v5, Walker2d-v5, HalfCheetah-v5 or a dataset name (default: --dataset)")
    d.add_argument("--index", type=int, nargs="+", help="with --run-id or --cvae: dataset transitions to render")
    d.add_argument("--width", type=_positive_int, default=320, help="pixels per image")
    d.add_argument("--height", type=_positive_int, default=320, help="pixels per image")
    d.add_argument("--out", default="fig3.png", help="output file; its extension picks the format")
    d = _parser(
        figs,
        "fig4",
        "PCA of observations and subgoals: a run's artifact, or redrawn from a CVAE",
        "spot figures fig4 --run-id 3f9c2a61d0b84e7f9a6c1e2d4b5a7c90 --out fig4.pdf",
    )
    d.add_argument("--run-id", help="this run's subgoal_projection.png, written in --out's format")
    d.add_argument("--out", default="fig4.png", help="output file; its extension picks the format")
    for d in figs.choices.values():
        d.add_argument("--tracking-uri", help=_URI_HELP)
    for d in (figs.choices["fig3"], figs.choices["fig4"]):
        d.add_argument("--cvae", help="a CVAE stage-cache entry ($SPOT_CACHE_DIR/cvae-<hash>.npz)")
        d.add_argument("--dataset", help="with --cvae (or to override the run's): registered dataset name or file")
        d.add_argument("--size", default="small", choices=_SIZES, help="with --dataset: its size")
        _data_seed(d)
    for d in figs.choices.values():
        d.set_defaults(fn=_figures)


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (poll reports an error on it)."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
    except (AttributeError, OSError, ValueError):  # no real descriptor, or no poll() on this platform
        return False
    poller.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def main(argv: list[str] | None = None) -> int:
    from spot import runtime

    try:
        runtime.configure()  # XLA flags and MUJOCO_GL, before anything imports jax or mujoco
    except SpotError as e:  # SPOT_JAX_CACHE / SPOT_FAST_COMPILE neither on nor off
        print(f"error: {e}", file=sys.stderr)
        return 2
    from spot.tracking.record import COMMAND_ENV

    # the command line, recorded as each run's mlflow.source.name (sweep trials inherit it)
    os.environ[COMMAND_ENV] = shlex.join(["spot", *(sys.argv[1:] if argv is None else argv)])
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # KEY=VALUE overrides may come after options (`spot labels make NAME --size tiny labels.seed=1`).
    if extra and hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = [*args.overrides, *extra]
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    # `spot config show key=value` without a file: the first positional is an override.
    if getattr(args, "config", None) and "=" in args.config:
        args.overrides = [args.config, *args.overrides]
        args.config = None
    try:
        from spot import stages

        stages.load_plugins()  # methods other packages register (docs/design.md, "Adding a method")
        rc = args.fn(args)
    except SpotError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except NonFiniteError as e:
        print(f"error: run failed: {e} (the MLflow run is marked FAILED)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        if not _stdout_closed():  # a socket or a child's pipe (MLflow, Ray): a real failure
            raise
        # `spot ... | head`: the reader left; stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the final flush must not raise again
        return 141  # 128 + SIGPIPE, the shell's status for a command killed by a closed pipe
    return rc or 0


if __name__ == "__main__":
    sys.exit(main())
