"""``spot run`` (one run, or several seeds and methods as one program) and ``spot eval``."""

from __future__ import annotations

import argparse
import signal
import threading
from typing import Any

from spot.cli.common import URI_HELP, add_quiet, positive_int, subcommand


def add(sub: Any) -> None:
    """The run, eval commands."""
    _add_run(sub)
    _add_eval(sub)


# --------------------------------------------------------------------------- run
def _add_run(sub: Any) -> None:
    d = subcommand(
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
        "tracking.uri, else $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db)",
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
    add_quiet(d)
    d.set_defaults(fn=_run)


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
    from spot import config, pipeline, tracking
    from spot.run import multiseed

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


# --------------------------------------------------------------------------- eval
def _add_eval(sub: Any) -> None:
    d = subcommand(
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
        "--episodes", type=positive_int, help="episodes (default: the run's eval.final_episodes, else eval.episodes)"
    )
    d.add_argument("--tracking-uri", help=URI_HELP)
    d.set_defaults(fn=_eval)


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
