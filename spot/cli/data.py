"""``spot data``: list, build, info and fetch datasets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.cli.common import SIZES, add_data_seed, add_quiet, subcommand


def add(sub: Any) -> None:
    """The data: list, build, info, fetch commands."""
    data = sub.add_parser("data", help="list, build, inspect and fetch datasets").add_subparsers(
        dest="sub", required=True, metavar="SUB"
    )
    d = subcommand(data, "list", "registered datasets and what is built", "spot data list")
    d.set_defaults(fn=_data_list)
    _add_build(data)
    _add_info(data)
    _add_fetch(data)


def _data_list(args: argparse.Namespace) -> None:
    from spot.data import registry

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
                + ("  (embedded copy)" if b.get("obtained") == "embedded" else "")
                + ("" if b["status"] == "ok" else f"  [{b['status']}]")
            )


# --------------------------------------------------------------------------- build
def _add_build(data: Any) -> None:
    d = subcommand(
        data,
        "build",
        "make a dataset: the copy spot ships of it, else a build with its local recipe (once; cached)",
        "spot data build hopper-medium-replay --size small --data-seed 0\n"
        "spot data build hopper-medium-replay --size small --from-recipe",
        description="Make a registered dataset in $SPOT_DATA_DIR. Where spot ships this build "
        "(hopper-medium-replay, size small, seed 0: byte-equal to the recipe's build), the shipped "
        "file is copied in after its sha256 is checked; --from-recipe runs the recipe instead.",
    )
    d.add_argument("name", help="registered dataset name (spot data list)")
    d.add_argument("--size", default="small", choices=SIZES, help="dataset size")
    add_data_seed(d)
    d.add_argument("--force", action="store_true", help="rebuild with the recipe even if cached")
    d.add_argument(
        "--from-recipe",
        action="store_true",
        help="build with the recipe, not from the embedded copy (a cached recipe build is reused)",
    )
    add_quiet(d)
    d.set_defaults(fn=_data_build)


def _data_build(args: argparse.Namespace) -> None:
    from spot.data import registry

    path = registry.build(
        args.name,
        args.size,
        args.data_seed,
        force=args.force,
        from_recipe=args.from_recipe,
        progress=not args.quiet,
    )
    card = registry.read_card(path)
    print(f"{'copied' if card.get('obtained') == 'embedded' else 'built'} {path}")
    print(json.dumps({k: card[k] for k in card if k not in ("name",)}, indent=2, default=str))


# --------------------------------------------------------------------------- info
def _add_info(data: Any) -> None:
    d = subcommand(
        data,
        "info",
        "summary and card of a built dataset or an hdf5 file",
        "spot data info hopper-medium-replay --size tiny",
    )
    d.add_argument("name", help="registered name or path")
    d.add_argument("--size", default="small", choices=SIZES, help="dataset size (registered names)")
    add_data_seed(d)
    add_quiet(d)
    d.set_defaults(fn=_data_info)


def _data_info(args: argparse.Namespace) -> None:
    from spot.data import registry

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
    built = registry.read_card(Path(args.name))  # the card file beside a build: its data and build facts
    if built:
        card = {**built, "path": card.get("path")}
    print(json.dumps({"source": _source(card), "summary": ds.summary(), "card": card}, indent=2, default=str))


def _source(card: dict[str, Any]) -> str:
    """Where a dataset's bytes came from, in words (``spot data info``)."""
    if card.get("source") != "recipe":
        return str(card.get("source", "file"))
    if card.get("obtained") == "embedded":
        return "recipe: the build spot ships (embedded copy, sha256 verified; byte-equal to the recipe's build)"
    return "recipe: built on this machine"


# --------------------------------------------------------------------------- fetch
def _add_fetch(data: Any) -> None:
    d = subcommand(
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
    add_quiet(d)
    d.set_defaults(fn=_data_fetch)


def _data_fetch(args: argparse.Namespace) -> None:
    from spot.data import fetch

    if args.list:
        _list_sources(args)
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


def _list_sources(args: argparse.Namespace) -> None:
    """``spot data fetch --list``: the registered sources, where their checksums come from."""
    from spot.data import fetch

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
