"""``spot bench``: throughput, compile time and peak memory of a stage, or of a whole sweep."""

from __future__ import annotations

import argparse
from typing import Any

from spot import SpotError
from spot.cli.common import positive_int, subcommand


def add(sub: Any) -> None:
    """The bench command."""
    from spot.config import IQL_ORDERS, IQLConfig

    d = subcommand(
        sub,
        "bench",
        "throughput, compile time and peak memory of a stage (paper sizes)",
        "spot bench iql --small\nspot bench iql --seeds 5 --order sequential\nspot bench pt --small --seeds 2\n"
        "spot bench sac --env hopper --size paper-fast\nspot bench eval\nspot bench eval --stepper gymnasium\n"
        "spot bench programs\nspot bench sweep sweeps/quickstart.yaml",
    )
    d.add_argument(
        "what",
        choices=("iql", "pt", "relabel", "cvae", "sac", "eval", "programs", "sweep"),
        help="a stage, a sweep, or programs: each stage's per-step overhead at tiny sizes against its FLOPs",
    )
    d.add_argument("file", nargs="?", help="sweep: the sweep file (runs it; prints each trial's time by phase)")
    d.add_argument("--smoke", action="store_true", help="sweep: the file's smoke block")
    d.add_argument("--small", action="store_true", help="small sizes: a quick check in seconds")
    d.add_argument("--seeds", type=positive_int, default=1, help="iql, pt: seeds as a vmap axis; eval: runs")
    d.add_argument("--episodes", type=positive_int, help="eval: episodes per run, batched vs sequential (default 10)")
    d.add_argument(
        "--stepper",
        choices=("mujoco", "gymnasium"),
        help="eval: how the batched episodes step (eval.stepper; default mujoco)",
    )
    d.add_argument("--order", default=IQLConfig.order, choices=IQL_ORDERS, help="iql: update order (iql.order)")
    d.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="pt: compute dtype")
    d.add_argument("--mode", default="chunked", choices=("chunked", "sliding"), help="relabel: mode")
    d.add_argument("--env", choices=("hopper", "walker2d"), help="sac: the locomotion recipe's env (default: walker2d)")
    d.add_argument("--size", choices=("paper", "paper-fast"), help="sac: the recipe's size (default: paper)")
    d.set_defaults(fn=_bench)


def _bench(args: argparse.Namespace) -> int | None:
    from spot import bench
    from spot.config import EvalConfig

    for flag, value in (("--env", args.env), ("--size", args.size)):
        if value and args.what != "sac":
            raise SpotError(f"spot bench {args.what}: {flag} goes with 'spot bench sac'")
    for flag, value in (("--episodes", args.episodes), ("--stepper", args.stepper)):
        if value and args.what != "eval":
            raise SpotError(f"spot bench {args.what}: {flag} goes with 'spot bench eval'")
    if args.what == "sweep":
        if not args.file:
            raise SpotError("spot bench sweep needs the sweep file: spot bench sweep FILE [--smoke]")
        return bench.bench_sweep(args.file, smoke=args.smoke)
    if args.file or args.smoke:
        raise SpotError(f"spot bench {args.what}: a sweep file and --smoke go with 'spot bench sweep'")
    if args.what == "programs":
        from spot import bench_programs

        if args.seeds != 1:
            raise SpotError("spot bench programs: --seeds does not go with it (the paper row's widths: 3 and 12)")
        print(bench_programs.format_programs(bench_programs.bench_programs(small=args.small)))
        return None
    kwargs = {"small": args.small}
    if args.what == "iql":
        kwargs["seeds"], kwargs["order"] = args.seeds, args.order
    if args.what == "pt":
        kwargs["dtype"], kwargs["seeds"] = args.dtype, args.seeds
    if args.what == "eval":
        kwargs["seeds"], kwargs["episodes"] = args.seeds, args.episodes or 10
        kwargs["stepper"] = args.stepper or EvalConfig.stepper
    if args.seeds != 1 and args.what not in ("iql", "pt", "eval"):
        raise SpotError(f"spot bench {args.what}: --seeds (seeds as a vmap axis) goes with iql, pt and eval")
    if args.what == "relabel":
        kwargs["mode"] = args.mode
    if args.what == "sac":
        kwargs["env"], kwargs["size"] = args.env, args.size
    print(bench.format_result(args.what, bench.BENCHES[args.what](**kwargs)))
