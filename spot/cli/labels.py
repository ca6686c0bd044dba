"""``spot labels``: make and inspect preference queries."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from spot.cli.common import SIZES, add_data_seed, add_quiet, subcommand


def add(sub: Any) -> None:
    """The labels: make, info commands."""
    lab = sub.add_parser("labels", help="make and inspect preference queries").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    _add_make(lab)
    _add_info(lab)


# --------------------------------------------------------------------------- make
def _add_make(lab: Any) -> None:
    d = subcommand(
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
    d.add_argument("--size", choices=SIZES, help="data.size (default: the budget's)")
    add_data_seed(d, None, "dataset build seed (default: the config's)")
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
    add_quiet(d)
    d.set_defaults(fn=_labels_make)


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
    from spot import config
    from spot.data import registry
    from spot.run import label_stages as stages

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


# --------------------------------------------------------------------------- info
def _add_info(lab: Any) -> None:
    d = subcommand(
        lab,
        "info",
        "inspect a .npz query file or a PT human-label folder",
        "spot labels info queries.npz --dataset drawer-open --size tiny",
    )
    d.add_argument("path", help=".npz query file or PT human-label folder")
    d.add_argument("--dataset", help="check that every segment fits this dataset")
    d.add_argument("--size", default="small", choices=SIZES, help="with --dataset: its size")
    add_data_seed(d)
    add_quiet(d)
    d.set_defaults(fn=_labels_info)


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
