"""What every ``spot`` command shares: the help formatter, the subcommand maker and the options
that mean the same everywhere (``--data-seed``, ``--quiet``, ``--tracking-uri``'s help).

This module and the parsers import no numpy, pandas, SciPy, JAX, MLflow or Ray, so that
``spot --help`` answers at once; the handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
from typing import Any

# The choices the parsers show. They are the library's own (spot.data.registry.SIZES,
# spot.results.tables.TABLES, spot.results.table_format.FORMATS), written out here because those
# modules import numpy, pandas and SciPy; tests/test_cli_package.py fails when they drift apart.
SIZES = ("tiny", "small", "paper", "paper-fast")
TABLES = (1, 2, 3, 4, 7, 8)
FORMATS = ("md", "latex", "csv", "text")

URI_HELP = (
    "MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else ./spot_runs/mlflow.db; "
    "an older folder's ./mlruns/mlflow.db if that is all there is)"
)


class Formatter(argparse.HelpFormatter):
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


def subcommand(sub: Any, name: str, help: str, examples: str, **kw: Any) -> argparse.ArgumentParser:
    """A subcommand with the shared formatter and ``examples`` (one per line) as its epilog."""
    lines = "\n".join(f"  {line}" for line in examples.strip().splitlines())
    return sub.add_parser(
        name,
        help=help,
        description=kw.pop("description", help[0].upper() + help[1:] + "."),
        epilog=f"example{'s' if len(examples.strip().splitlines()) > 1 else ''}:\n{lines}",
        formatter_class=Formatter,
        **kw,
    )


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer (>= 1), got {value}")
    return value


def add_data_seed(d: argparse.ArgumentParser, default: int | None = 0, what: str = "dataset build seed") -> None:
    """``--data-seed`` (``data.build_seed``), with ``--seed`` kept as its old name."""
    d.add_argument(
        "--data-seed",
        "--seed",
        dest="data_seed",
        type=int,
        default=default,
        help=f"{what} (data.build_seed; --seed is the old name)",
    )


def add_quiet(d: argparse.ArgumentParser) -> None:
    d.add_argument("--quiet", action="store_true", help="no progress bars")
