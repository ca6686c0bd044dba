"""``spot figures``: the paper's figures 2, 3 and 4 from runs, and pictures of results: evaluation
curves over seeds (``curves``), the claims' effects (``claims``) and a performance profile
(``profile``), from MLflow or results CSVs."""

from __future__ import annotations

import argparse
from typing import Any

from spot import SpotError
from spot.cli.common import SIZES, URI_HELP, add_data_seed, positive_int, subcommand


def add(sub: Any) -> None:
    """The figures: fig2, fig3, fig4, curves, claims, profile commands."""
    figs = sub.add_parser(
        "figures", help="the paper's figures 2, 3 and 4; curves, claims and profile pictures of results"
    ).add_subparsers(dest="figure", required=True, metavar="FIGURE")
    d = subcommand(
        figs,
        "fig2",
        "extrapolation error vs cos(s, g), PT vs SPOT, in-distribution vs OOD",
        "spot figures fig2 --experiment table1 --out fig2.pdf",
    )
    d.add_argument("--experiment", action="append", help="MLflow experiment (repeatable; default: all)")
    d.add_argument("--sweep-id", help="only the runs of this sweep (tag spot.sweep_id)")
    d.add_argument("--dataset", help="the paper's dataset name, if the runs span several")
    d.add_argument("--source", choices=("recipe", "file"), help="dataset source, if the runs span both")
    d.add_argument("--ddof", type=int, default=1, choices=(0, 1), help="std over runs: 1 = sample, 0 = population")
    d.add_argument(
        "--out", default="fig2.png", help="output file; its extension picks the format (.png, .pdf, .svg...)"
    )
    _add_fig3(figs)
    d = subcommand(
        figs,
        "fig4",
        "PCA of observations and subgoals: a run's artifact, or redrawn from a CVAE",
        "spot figures fig4 --run-id 3f9c2a61d0b84e7f9a6c1e2d4b5a7c90 --out fig4.pdf",
    )
    d.add_argument("--run-id", help="this run's subgoal_projection.png, written in --out's format")
    d.add_argument("--out", default="fig4.png", help="output file; its extension picks the format")
    _add_results_figures(figs)
    for d in figs.choices.values():
        d.add_argument("--tracking-uri", help=URI_HELP)
    for d in (figs.choices["fig3"], figs.choices["fig4"]):
        d.add_argument("--cvae", help="a CVAE stage-cache entry ($SPOT_CACHE_DIR/cvae-<hash>.npz)")
        d.add_argument("--dataset", help="with --cvae (or to override the run's): registered dataset name or file")
        d.add_argument("--size", default="small", choices=SIZES, help="with --dataset: its size")
        add_data_seed(d)
    for name in ("fig2", "fig3", "fig4"):
        figs.choices[name].set_defaults(fn=_figures)


def _add_fig3(figs: Any) -> None:
    d = subcommand(
        figs,
        "fig3",
        "locomotion states rendered beside their predicted subgoals (MuJoCo, headless)",
        "spot figures fig3 --run-id 3f9c2a61d0b84e7f9a6c1e2d4b5a7c90 --index 120 480\n"
        "spot figures fig3 --pairs pairs.npy --env Hopper-v5",
    )
    d.add_argument("--pairs", help=".npy of [2, obs_dim] or [n, 2, obs_dim] (state, subgoal)")
    d.add_argument("--run-id", help="use this run's CVAE (its models/cvae artifact) on the run's dataset")
    d.add_argument("--env", help="Hopper-v5, Walker2d-v5, HalfCheetah-v5 or a dataset name (default: --dataset)")
    d.add_argument(
        "--index",
        type=int,
        nargs="+",
        default=[0],
        help="with --run-id or --cvae: dataset transitions to render (default: 0)",
    )
    d.add_argument("--width", type=positive_int, default=320, help="pixels per image")
    d.add_argument("--height", type=positive_int, default=320, help="pixels per image")
    d.add_argument("--out", default="fig3.png", help="output file; its extension picks the format")


def _figures(args: argparse.Namespace) -> None:
    from spot import figures
    from spot.data import registry
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
            print(f"fig3: run {args.run_id}'s CVAE, transitions {args.index}: loading the model", flush=True)
            params, cfg, head = figures.cvae_from_run(args.run_id, args.tracking_uri)
            print(f"fig3: loading dataset {args.dataset or cfg.data.name} (built first if absent)", flush=True)
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
        print(f"fig3: rendering {len(obs)} state/subgoal pair(s) in {args.env or args.dataset} (MuJoCo)", flush=True)
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


# --------------------------------------------------------------------------- pictures of results
def _add_sources(d: Any, study_help: str) -> None:
    d.add_argument("study", nargs="?", metavar="STUDY_DIR", help=study_help)
    d.add_argument("--results", nargs="+", help="results CSVs (files or folders) instead of MLflow or the study's")
    d.add_argument("--sweep-id", help="from MLflow: only the runs of this sweep (tag spot.sweep_id)")


def _add_results_figures(figs: Any) -> None:
    study = "a study folder: the results its claims.yaml names"
    for name, what, example in (
        (
            "curves",
            "evaluation curves, mean over seeds with 95%% bootstrap CI bands, per method or swept value",
            "spot figures curves --results experiments/lab-hopper-full-replay/results --out curves.png\n"
            "spot figures curves --sweep-id lam-3f9c --by shaping.weight --out curves.svg",
        ),
        (
            "profile",
            "performance profile: fraction of runs with final score > tau, over datasets (95%% CI bands)",
            "spot figures profile experiments/lab-hopper-full-replay --out profile.pdf",
        ),
    ):
        d = subcommand(figs, name, what, example)
        _add_sources(d, study)
        d.add_argument("--experiment", action="append", help="only these experiments (repeatable; default: all)")
        d.add_argument("--by", default="method", help="one line per method (default) or per value of this param")
        d.add_argument("--out", default=f"{name}.png", help="output file; its extension picks the format")
        d.set_defaults(fn=_results_figure)
    figs.choices["profile"].add_argument(
        "--metric", default="eval/score_final", help="the normalised score of each run (default eval/score_final)"
    )
    d = subcommand(
        figs,
        "claims",
        "each claim's effect with its 95%% CI (an interval plot of the rows of `spot report`)",
        "spot figures claims experiments/lab-hopper-full-replay --out claims.png\n"
        "spot figures claims --claims my_claims.yaml --out claims.pdf",
    )
    _add_sources(d, "a study folder: its claims.yaml and the runs it names")
    d.add_argument("--claims", metavar="FILE", help="a claims file (default: the paper's claims over MLflow)")
    d.add_argument("--use", action="append", metavar="SET=EXPERIMENT", help="as `spot report --use`")
    d.add_argument("--high-mode", type=float, default=50.0, metavar="SCORE", help=argparse.SUPPRESS)
    d.add_argument("--out", default="claims.png", help="output file; its extension picks the format")
    d.set_defaults(fn=_claims_figure)


def _runs(args: argparse.Namespace, curves: bool) -> Any:
    """The runs of ``curves`` or ``profile``: a study folder's results, ``--results``, else MLflow
    (with each run's eval/score history when ``curves``)."""
    from spot.results import claims, export, load

    if args.study and args.results:
        raise SpotError(f"spot figures: give a study folder ({args.study}) or --results, not both")
    results = args.results or (list(claims.load(claims.study_file(args.study)).results) if args.study else None)
    if results:
        return load.load(results, experiments=args.experiment)
    from spot import tracking

    runs = load.load_runs(args.tracking_uri, args.experiment, args.sweep_id)
    if runs.empty:
        raise SpotError(
            f"no runs in {args.tracking_uri or 'the default store'} (experiments {args.experiment or 'all'})"
        )
    return export.add_curves(runs, tracking.reader(args.tracking_uri)) if curves else runs


def _results_figure(args: argparse.Namespace) -> None:
    from spot.results import figures_curves as fc
    from spot.results.figures_curves import image_format
    from spot.results.table_format import check_out

    image_format(args.out)  # an unknown extension or folder fails before any work
    check_out(args.out)
    runs = _runs(args, args.figure == "curves")
    if args.figure == "curves":
        table = fc.summarize_curves(fc.curve_points(runs, args.by))
        fig = fc.draw_curves(table)
    else:
        metric = args.metric if args.metric.startswith("metrics.") else f"metrics.{args.metric}"
        table = fc.profile(fc.final_scores(runs, metric, args.by))
        fig = fc.draw_profile(table, metric)
    print(f"wrote {fc.save(fig, args.out)}")


def _claims_figure(args: argparse.Namespace) -> None:
    from spot.cli.results import report_inputs
    from spot.results import figures_curves, figures_report, report
    from spot.results.figures_curves import image_format
    from spot.results.table_format import check_out

    image_format(args.out)
    check_out(args.out)
    claims_file, runs = report_inputs(args)
    rows = report.build(runs, claims_file, args.high_mode).rows
    for r in figures_report.claim_rows(rows):
        print(f"{r.claim} {r.stat} {r.comparison}: {r.effect.text(r.digits) if r.effect else '-'} {r.verdict}")
    print(f"wrote {figures_curves.save(figures_report.draw_claims(rows), args.out)}")
