"""The ``spot`` command. Thin: parses arguments and calls into the library.

User errors (:class:`spot.SpotError`) print one line ``error: ...`` and exit with code 2; no
traceback. Run ``spot <command> --help`` for each command's options, defaults and an example.
One name per concept across commands: ``--tracking-uri`` (the MLflow store), ``--data-seed`` (the
dataset build seed, ``data.build_seed``; ``--seed`` is its old name), ``--quiet`` (no progress
bars) wherever a command draws them.

One module per command group, each with its parsers beside their handlers: :mod:`.data`,
:mod:`.labels`, :mod:`.run` (run, eval), :mod:`.bench`, :mod:`.sweep`, :mod:`.ui`, :mod:`.config_cmd`,
:mod:`.results` (tables, results, report), :mod:`.figures`; :mod:`.common` holds what they share.
Building the parser imports no numpy, pandas, SciPy, JAX, MLflow or Ray (``spot --help`` answers
at once); a handler imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
import os
import select
import shlex
import sys

from spot import NonFiniteError, SpotError
from spot.cli import bench, config_cmd, data, figures, labels, results, run, sweep, ui
from spot.cli.common import Formatter

__all__ = ["build_parser", "main"]


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
        formatter_class=Formatter,
        epilog="examples:\n  spot sweep sweeps/quickstart.yaml --smoke\n  spot run configs/quickstart.yaml method=pt\n"
        "  spot tables --table 1\n\nEvery command has --help with its options, defaults and an example.",
    )
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    # in the order `spot --help` lists them
    for group in (data, labels, run, bench, sweep, ui, config_cmd, results, figures):
        group.add(sub)
    return p


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (poll reports an error on it)."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
    except (AttributeError, OSError, ValueError):  # no real descriptor, or no poll() on this platform
        return False
    poller.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def _parse(argv: list[str] | None) -> argparse.Namespace:
    """The command line's arguments, KEY=VALUE overrides gathered wherever they stand."""
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
    return args


def main(argv: list[str] | None = None) -> int:
    from spot import runtime

    try:
        runtime.configure()  # XLA flags and MUJOCO_GL, before anything imports jax or mujoco
    except SpotError as e:  # SPOT_JAX_CACHE / SPOT_FAST_COMPILE neither on nor off
        print(f"error: {e}", file=sys.stderr)
        return 2
    args = _parse(argv)  # --help, --version and usage errors exit here, before any heavy import
    if argv is None:  # the command's own process: a Ctrl-C or SIGTERM in a gc callback still stops it
        runtime.redeliver_swallowed_interrupts()
    from spot.tracking.provenance import COMMAND_ENV

    # the command line, recorded as each run's mlflow.source.name (sweep trials inherit it)
    os.environ[COMMAND_ENV] = shlex.join(["spot", *(sys.argv[1:] if argv is None else argv)])
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
        if argv is None:  # the command's own process: XLA may still be compiling on its threads
            runtime.exit_interrupted(130)
        return 130
    except BrokenPipeError:
        if not _stdout_closed():  # a socket or a child's pipe (MLflow, Ray): a real failure
            raise
        # `spot ... | head`: the reader left; stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the final flush must not raise again
        return 141  # 128 + SIGPIPE, the shell's status for a command killed by a closed pipe
    except Exception as e:  # a tracking server that stopped answering mid-run: one line, not MLflow's traceback
        from spot.tracking import limits

        if (gone := limits.unreachable(e)) is None:
            raise
        print(f"error: {gone}", file=sys.stderr)
        return 2
    return rc or 0
