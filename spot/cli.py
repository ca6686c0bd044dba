"""The ``spot`` command. Thin: parses arguments and calls into the library.

User errors (:class:`spot.SpotError`) print one line ``error: ...`` and exit with code 2; no
traceback. Run ``spot <command> --help`` for each command's options.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from spot import NonFiniteError, SpotError


# --------------------------------------------------------------------------- data
def _data_list(args: argparse.Namespace) -> None:
    from spot.data import registry

    print(f"{'name':28s} {'family':11s} description")
    for e in registry.REGISTRY.values():
        print(f"{e.name:28s} {e.family:11s} {e.description}")
    print(f"\nsizes: {', '.join(registry.SIZES)}   cache dir: {registry.data_dir()} (set SPOT_DATA_DIR)")
    built = registry.cached()
    if built:
        print("\nbuilt:")
        for b in built:
            print(f"  {b['name']} size={b['size']} seed={b['seed']} transitions={b['transitions']}  {b['path']}")


def _data_build(args: argparse.Namespace) -> None:
    from spot.data import registry

    path = registry.build(args.name, args.size, args.seed, force=args.force)
    card = registry.read_card(path)
    print(f"built {path}")
    print(json.dumps({k: card[k] for k in card if k not in ("name",)}, indent=2, default=str))


def _data_info(args: argparse.Namespace) -> None:
    from spot.data import registry

    as_path = Path(args.name)
    if not as_path.exists():
        registry.entry(args.name)  # unknown names fail here, before any build
        path = registry.dataset_path(args.name, args.size, args.seed)
        if not path.exists():
            raise SpotError(
                f"dataset '{args.name}' (size {args.size}, seed {args.seed}) is not built yet; "
                f"run: spot data build {args.name} --size {args.size} --seed {args.seed}"
            )
        args.name = str(path)
    ds, card = registry.load(args.name, source="file")
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
        print(f"{'minari:<dataset id>':36s} {'':5s} {'':>12s}  {'tofu':22s} a Minari dataset through "
              "minari.download_dataset (extra 'minari')")
        print("\nchecksum from: lfs-oid = a mirror's published Git LFS id; git-commit = the file in a "
              "pinned git commit; third-party = recorded by an independent project; tofu = trust on "
              f"first use (recorded in the lock file, default ./{fetch.DEFAULT_LOCK})")
        print(f"destination: {args.dest or fetch.default_dest()}   registry: "
              f"{fetch.registry_path(args.registry) or 'spot/data/sources.json (package)'}")
        return
    if not args.name:
        raise SpotError("spot data fetch needs a NAME (or --list)")
    if args.name.startswith(fetch.MINARI_PREFIX):
        folder, digest, status = fetch.fetch_minari(args.name[len(fetch.MINARI_PREFIX):], lock=args.lock)
        lock = args.lock or fetch.default_lock()
        what = ("TOFU: Minari publishes no checksums; recorded the folder digest in"
                if status == "recorded" else "matches the folder digest in")
        print(f"fetched {args.name} -> {folder}\n  {what} {lock}: {digest}")
        return
    result = fetch.fetch(args.name, args.dest, mirrors=args.mirror, registry=args.registry,
                         lock=args.lock, progress=not args.quiet)
    src = result.source
    print(f"fetched {src.name} -> {(args.dest and Path(args.dest)) or fetch.default_dest()}")
    for f in result.files:
        print(f"  {f.status:10s} {f.path}  {f.size:,} B  sha256 {f.sha256}")
        if f.status == "recorded":
            print(f"             TOFU: no published checksum; this first download's sum is now in "
                  f"{result.lock}: commit it, later downloads must match")
        else:
            print(f"             verified against: {fetch._trust_words(f.trust)}")
    if src.kind in ("d4rl", "robomimic"):
        print(f"use it: data.name={result.files[0].path}")
        if src.labels:
            print(f"human labels: spot data fetch {src.labels}, then labels.source=human "
                  "labels.path=<its folder>")
    elif src.kind == "pt-labels":
        print(f"use it: labels.source=human labels.path={result.files[0].path.parent} "
              f"(with the data of {src.labels_for})")


# --------------------------------------------------------------------------- labels
# `spot labels make` flags -> the config keys they set (None: not given, the resolved config decides).
_LABEL_FLAGS = {"num_queries": "labels.num_queries", "segment_length": "labels.segment_length",
                "teacher": "labels.teacher", "score": "labels.score", "discount": "labels.discount",
                "tie_threshold": "labels.tie_threshold", "mistake_rate": "labels.mistake_rate",
                "allow_cross_episode": "labels.allow_cross_episode", "label_seed": "labels.seed",
                "size": "data.size", "seed": "data.build_seed"}


def _labels_make(args: argparse.Namespace) -> None:
    """The queries `spot run` would make with the same config: the labels settings are resolved like
    a run's (defaults < method < budget < suite preset < --config file < overrides and flags)."""
    from spot import config, stages
    from spot.data import registry

    flags = [f"{key}={getattr(args, name)}" for name, key in _LABEL_FLAGS.items() if getattr(args, name) is not None]
    cfg = config.load(args.config_file, [f"data.name={args.dataset}", *args.overrides, *flags])
    ds, _ = registry.load(cfg.data.name, cfg.data.size, cfg.data.build_seed, source=cfg.data.source)
    prefs = stages.make_preferences(cfg, ds)
    prefs.save_npz(args.out)
    lc = cfg.labels
    print(f"wrote {len(prefs)} queries (segment length {prefs.segment_length}) to {args.out}")
    print(f"settings (method={cfg.method}, budget={cfg.budget}): source={lc.source} teacher={lc.teacher} "
          f"score={lc.score} discount={lc.discount} tie_threshold={lc.tie_threshold} "
          f"mistake_rate={lc.mistake_rate} allow_cross_episode={lc.allow_cross_episode} seed={lc.seed}")
    _print_label_stats(prefs)


def _print_label_stats(prefs) -> None:
    import numpy as np

    y = prefs.labels
    print(f"labels: seg1 preferred {int(np.sum(y == 0))}, seg2 preferred {int(np.sum(y == 1))}, "
          f"ties {int(np.sum(y == 0.5))}")


def _labels_info(args: argparse.Namespace) -> None:
    from spot.data import labels, registry

    path = Path(args.path)
    prefs = labels.read_pt_labels(path) if path.is_dir() else labels.Preferences.load_npz(path)
    print(f"{path}: {len(prefs)} queries, segment length {prefs.segment_length}, source {prefs.source}")
    _print_label_stats(prefs)
    if args.dataset:
        ds, _ = registry.load(args.dataset, args.size, args.seed)
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
def _run(args: argparse.Namespace) -> None:
    from spot import config, pipeline

    cfg = config.load(args.config, args.overrides)
    final = pipeline.run(cfg, progress=not args.quiet)
    print(f"run {final['run_id']}: {cfg.method} on {cfg.data.name} (seed {cfg.seed})")
    for key in sorted(final):
        if key != "run_id":
            print(f"  {key:24s} {final[key]:.3f}")


# --------------------------------------------------------------------------- bench
def _bench(args: argparse.Namespace) -> None:
    from spot import bench

    kwargs = {"small": args.small}
    if args.what == "iql":
        kwargs["seeds"], kwargs["order"] = args.seeds, args.order
    if args.what == "pt":
        kwargs["dtype"] = args.dtype
    if args.what == "relabel":
        kwargs["mode"] = args.mode
    print(bench.format_result(args.what, bench.BENCHES[args.what](**kwargs)))


# --------------------------------------------------------------------------- sweep
def _sweep(args: argparse.Namespace) -> int:
    from spot import sweep

    rows = sweep.run_sweep(args.file, smoke=args.smoke, resume=args.resume, retry_errored=args.retry_errored,
                           address=args.address, max_concurrent=args.max_concurrent,
                           tracking_uri=args.tracking_uri, storage=args.storage)
    return 0 if all(r.status == "FINISHED" for r in rows) else 1  # the summary lists what failed


# --------------------------------------------------------------------------- tables, figures
def _tables(args: argparse.Namespace) -> None:
    from spot import tables

    if args.results:
        from spot import results

        runs = results.read(args.results)
        if args.experiment:
            runs = runs[runs["experiment"].isin(args.experiment)]
    else:
        experiments = args.experiment or tables.default_experiments(args.table, args.tracking_uri)
        runs = tables.load_runs(args.tracking_uri, experiments, args.sweep_id)
    table = tables.build_table(runs, args.table, args.metric, ddof=args.ddof, allow_mixed=args.allow_mixed)
    text = tables.format_table(table, args.format)
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")


def _results_export(args: argparse.Namespace) -> None:
    from spot import results, tables

    runs = tables.load_runs(args.tracking_uri, args.experiment, args.sweep_id)
    if runs.empty:
        raise SpotError(f"no runs in experiments {args.experiment} of {args.tracking_uri or 'the default store'}")
    path = results.export(runs, args.out)
    print(f"wrote {path} ({len(runs)} runs)")


def _report(args: argparse.Namespace) -> None:
    from spot import report, results, tables

    if args.results:
        runs = results.read(args.results)
    else:
        runs = results.to_frame(tables.load_runs(args.tracking_uri, None, args.sweep_id))
    use = {}
    for item in args.use or []:
        claim, sep, name = item.partition("=")
        if not sep or claim not in report.EXPERIMENTS:
            raise SpotError(f"--use {item!r}: expected CLAIM=EXPERIMENT with CLAIM one of {sorted(report.EXPERIMENTS)}")
        use[claim] = (name,)
    text = report.format_rows(report.build(runs, use))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")


def _figures(args: argparse.Namespace) -> None:
    from spot import figures, tables

    if args.figure == "fig2":
        runs = tables.load_runs(args.tracking_uri, args.experiment, args.sweep_id)
        bins = figures.extrapolation_bins(runs, args.tracking_uri, dataset=args.dataset, source=args.source)
        print(figures.summarize_extrapolation(bins, ddof=args.ddof).to_string(index=False))
        print(f"wrote {figures.plot_fig2(bins, args.out, ddof=args.ddof)}")
        return
    if args.cvae:
        if not args.dataset:
            raise SpotError("--cvae needs --dataset (the transitions to generate subgoals for)")
        from spot.data import registry

        params = figures.load_cvae(args.cvae)
        ds, _ = registry.load(args.dataset, args.size, args.data_seed, progress=False)
    if args.figure == "fig3":
        if args.pairs:
            if not args.env:
                raise SpotError("--pairs needs --env (e.g. Hopper-v5 or hopper-medium-expert)")
            obs, goal = figures.pairs_from_file(args.pairs)
        elif args.cvae and args.index:
            obs, goal = figures.pairs_from_cvae(params, ds.observations, ds.actions, args.index)
        else:
            raise SpotError("fig3 needs --pairs FILE.npy --env ENV, or --cvae FILE --dataset NAME --index I [I ...]")
        path = figures.render_state_and_subgoal(args.env or args.dataset, obs, goal, args.out,
                                                width=args.width, height=args.height)
    elif args.run_id:
        path = figures.fetch_artifact(args.run_id, figures.FIG4_ARTIFACT, args.out, args.tracking_uri)
    elif args.cvae:
        path = figures.projection_from_cvae(params, ds.observations, ds.actions, args.out)
    else:
        raise SpotError("fig4 needs --run-id ID, or --cvae FILE --dataset NAME")
    print(f"wrote {path}")


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from spot.config import IQL_ORDERS, IQLConfig

    p = argparse.ArgumentParser(prog="spot", description="Offline preference-based RL: SPOT and baselines.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    data = sub.add_parser("data", help="list, build and inspect datasets").add_subparsers(dest="sub", required=True, metavar="SUB")
    d = data.add_parser("list", help="registered datasets and what is built")
    d.set_defaults(fn=_data_list)
    d = data.add_parser("build", help="build a dataset with its local recipe (once; cached)")
    d.add_argument("name")
    d.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--force", action="store_true", help="rebuild even if cached")
    d.set_defaults(fn=_data_build)
    d = data.add_parser("info", help="summary and card of a built dataset or an hdf5 file")
    d.add_argument("name", help="registered name or path")
    d.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(fn=_data_info)
    d = data.add_parser(
        "fetch", help="download the paper's real data files (D4RL, robomimic, PT labels), verified",
        description="Download a registered source's files to DEST with resume and mirror fallback; "
                    "each file's size and sha256 are verified before it is put in place. "
                    "Example: spot data fetch d4rl/hopper-medium-replay-v2")
    d.add_argument("name", nargs="?", help="registry name (see --list) or minari:<dataset id>")
    d.add_argument("--list", action="store_true", help="list the registered sources and exit")
    d.add_argument("--dest", help="destination folder (default: $SPOT_DATA_DIR/real)")
    d.add_argument("--mirror", action="append", default=[], metavar="URL",
                   help="base URL tried first, as URL/<file path> (repeatable)")
    d.add_argument("--registry", metavar="FILE",
                   help="another sources registry in the same JSON format, e.g. a private mirror "
                        "or a test server (default: $SPOT_FETCH_REGISTRY, else the package's)")
    d.add_argument("--lock", metavar="FILE",
                   help="trust-on-first-use lock file (default: $SPOT_DATA_LOCK, else ./spot-data.lock.json)")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(fn=_data_fetch)

    lab = sub.add_parser("labels", help="make and inspect preference queries").add_subparsers(dest="sub", required=True, metavar="SUB")
    d = lab.add_parser("make", help="the preference queries `spot run` would make on a dataset -> .npz",
                       description="Resolves the labels settings like `spot run` (method, budget and suite "
                                   "presets, --config, KEY=VALUE overrides); the flags are shorthands for "
                                   "labels.* keys and win over the overrides.")
    d.add_argument("dataset", help="data.name: a registered name or a dataset file")
    d.add_argument("overrides", nargs="*", help="a.b=value config overrides, e.g. method=ipl budget=paper")
    d.add_argument("--out", required=True, help="output .npz")
    d.add_argument("--config", dest="config_file", help="YAML run config (as for `spot run`)")
    d.add_argument("--size", choices=("tiny", "small", "paper"), help="data.size (default: the budget's)")
    d.add_argument("--seed", type=int, help="data.build_seed, the dataset build seed")
    d.add_argument("--num-queries", type=int, help="labels.num_queries")
    d.add_argument("--segment-length", type=int, help="labels.segment_length")
    d.add_argument("--teacher", choices=("sum", "discounted"), help="labels.teacher")
    d.add_argument("--score", choices=("reward", "dense"),
                   help="labels.score: sum the dataset's reward or its dense reward infos/dense_reward (robosuite recipes)")
    d.add_argument("--discount", type=float, help="labels.discount")
    d.add_argument("--tie-threshold", type=float, help="labels.tie_threshold (negative: no ties)")
    d.add_argument("--mistake-rate", type=float, help="labels.mistake_rate")
    d.add_argument("--allow-cross-episode", action="store_true", default=None, help="labels.allow_cross_episode=true")
    d.add_argument("--label-seed", type=int, help="labels.seed")
    d.set_defaults(fn=_labels_make)
    d = lab.add_parser("info", help="inspect a .npz query file or a PT human-label folder")
    d.add_argument("path")
    d.add_argument("--dataset", help="check that every segment fits this dataset")
    d.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(fn=_labels_info)

    d = sub.add_parser("run", help="one run (one seed) end to end, logged to MLflow")
    d.add_argument("config", nargs="?", help="YAML run config (see configs/)")
    d.add_argument("overrides", nargs="*", help="a.b=value overrides, e.g. method=pt iql.steps=5000")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(fn=_run)

    d = sub.add_parser("bench", help="throughput, compile time and peak memory of a stage (paper sizes)")
    d.add_argument("what", choices=("iql", "pt", "relabel", "cvae"))
    d.add_argument("--small", action="store_true", help="small sizes: a quick check in seconds")
    d.add_argument("--seeds", type=int, default=1, help="iql: seeds as a vmap axis")
    d.add_argument("--order", default=IQLConfig.order, choices=IQL_ORDERS, help="iql: update order (iql.order)")
    d.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="pt: compute dtype")
    d.add_argument("--mode", default="chunked", choices=("chunked", "sliding"), help="relabel: mode")
    d.set_defaults(fn=_bench)

    d = sub.add_parser("sweep", help="run a sweep file (sweeps/*.yaml) with Ray Tune, logged to MLflow",
                       description="Exit code 0 when every (config, seed) run finished, 1 otherwise. See docs/sweeps.md.")
    d.add_argument("file", help="sweep YAML file")
    d.add_argument("--smoke", action="store_true", help="apply the file's smoke block (experiment <name>-smoke)")
    d.add_argument("--resume", action="store_true", help="continue the last launch of this sweep")
    d.add_argument("--retry-errored", action="store_true", help="with --resume: run failed trials again")
    d.add_argument("--address", help="Ray cluster address (default: local Ray on all CPUs)")
    d.add_argument("--max-concurrent", type=int, help="trials at once (default: the file's max_concurrent)")
    d.add_argument("--tracking-uri", help="MLflow URI (default: a loopback server on ./spot_runs/mlflow.db)")
    d.add_argument("--storage", default="spot_runs/ray", help="Ray Tune storage folder (default: %(default)s)")
    d.set_defaults(fn=_sweep)

    cfg = sub.add_parser("config", help="show resolved run configs and valid keys").add_subparsers(dest="sub", required=True, metavar="SUB")
    d = cfg.add_parser("show", help="print the fully resolved config")
    d.add_argument("config", nargs="?", help="YAML run config")
    d.add_argument("overrides", nargs="*", help="a.b=value overrides")
    d.set_defaults(fn=_config_show)
    d = cfg.add_parser("keys", help="every config key with type, help and valid values")
    d.set_defaults(fn=_config_keys)
    d = sub.add_parser("tables", help="a paper table from the MLflow runs, the paper's numbers beside ours")
    d.add_argument("--table", type=int, required=True, choices=(1, 2, 3, 4, 7, 8))
    d.add_argument("--experiment", action="append",
                   help="MLflow experiment (repeatable; default: the table's sweep experiment if present, else all)")
    d.add_argument("--tracking-uri", default="", help="default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db or ./mlruns/mlflow.db")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--metric", default="eval/score_final", help="score metric of tables 1-7")
    d.add_argument("--format", default="md", choices=("md", "latex", "csv"))
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over seeds: 1 = sample, 0 = population")
    d.add_argument("--allow-mixed", action="store_true", help="average cells whose runs differ in more than the seed")
    d.add_argument("--out", help="write the table to this file instead of printing it")
    d.add_argument("--results", nargs="+", help="read runs from results CSVs (files or folders) instead of MLflow")
    d.set_defaults(fn=_tables)

    res = sub.add_parser("results", help="export finished runs from MLflow to a small CSV").add_subparsers(
        dest="sub", required=True, metavar="SUB")
    d = res.add_parser("export", help="one row per run: identity, config hash, data digest, params, metrics")
    d.add_argument("--experiment", action="append", required=True, help="MLflow experiment (repeatable)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--tracking-uri", default="", help="default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db or ./mlruns/mlflow.db")
    d.add_argument("--out", required=True, help="the CSV to write, e.g. results/lab_table1.csv")
    d.set_defaults(fn=_results_export)

    d = sub.add_parser("report", help="the paper's claims: effect, 95%% CI, n and verdict per claim")
    d.add_argument("--results", nargs="+", help="results CSVs (files or folders); default: read MLflow")
    d.add_argument("--tracking-uri", default="", help="default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db or ./mlruns/mlflow.db")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--use", action="append", metavar="CLAIM=EXPERIMENT",
                   help="read a claim's runs from this experiment (claims 1-6, C for the controls)")
    d.add_argument("--out", help="write the report (Markdown) to this file instead of printing it")
    d.set_defaults(fn=_report)

    figs = sub.add_parser("figures", help="the paper's figures 2, 3 and 4 from runs").add_subparsers(
        dest="figure", required=True, metavar="FIGURE")
    d = figs.add_parser("fig2", help="extrapolation error vs cos(s, g), PT vs SPOT, in-distribution vs OOD")
    d.add_argument("--experiment", action="append", help="MLflow experiment (repeatable; default: all)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag sweep_id)")
    d.add_argument("--dataset", help="the paper's dataset name, if the runs span several")
    d.add_argument("--source", choices=("recipe", "file"), help="dataset source, if the runs span both")
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over runs: 1 = sample, 0 = population")
    d.add_argument("--out", default="fig2.png")
    d = figs.add_parser("fig3", help="locomotion states rendered beside their predicted subgoals (MuJoCo, headless)")
    d.add_argument("--pairs", help=".npy of [2, obs_dim] or [n, 2, obs_dim] (state, subgoal)")
    d.add_argument("--env", help="Hopper-v5, Walker2d-v5, HalfCheetah-v5 or a dataset name (default: --dataset)")
    d.add_argument("--index", type=int, nargs="+", help="with --cvae: dataset transitions to render")
    d.add_argument("--width", type=int, default=320)
    d.add_argument("--height", type=int, default=320)
    d.add_argument("--out", default="fig3.png")
    d = figs.add_parser("fig4", help="PCA of observations and subgoals: a run's artifact, or redrawn from a CVAE")
    d.add_argument("--run-id", help="copy this run's subgoal_projection.png")
    d.add_argument("--out", default="fig4.png")
    for d in (figs.choices["fig2"], figs.choices["fig4"]):
        d.add_argument("--tracking-uri", default="", help="default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db or ./mlruns/mlflow.db")
    for d in (figs.choices["fig3"], figs.choices["fig4"]):
        d.add_argument("--cvae", help="a CVAE stage-cache entry ($SPOT_CACHE_DIR/cvae-<hash>.npz)")
        d.add_argument("--dataset", help="with --cvae: registered dataset name or file")
        d.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
        d.add_argument("--data-seed", type=int, default=0, help="dataset build seed")
    for d in figs.choices.values():
        d.set_defaults(fn=_figures)
    return p


def main(argv: list[str] | None = None) -> int:
    from spot import runtime

    runtime.configure()  # XLA flag and MUJOCO_GL, before anything imports jax or mujoco
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
    return rc or 0


if __name__ == "__main__":
    sys.exit(main())
