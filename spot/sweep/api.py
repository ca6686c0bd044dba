"""The Python entry to a sweep: :func:`run_sweep` from a sweep file or a dict (docs/python.md).

A dict is what a sweep file's YAML parses to, ``name`` included. It is validated by
:func:`spot.sweep.spec.load_dict`, the same checks as a file's, before anything is written; then it
is written as ``<storage>/<experiment>.sweep.yaml`` and launched as that file, so the parent run
logs it as ``sweep.yaml`` and the printed ``--resume`` command names a file that exists.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from spot.sweep import launch
from spot.sweep.spec import Sweep, load, load_dict
from spot.sweep.summary import Row


def sweep_file(spec: Sweep, data: Mapping[str, Any], storage: str | Path) -> Path:
    """Write a validated dict sweep as ``<storage>/<experiment>.sweep.yaml`` (whole or not at all:
    a temporary file beside it, then renamed; left alone when it already holds the same text)."""
    path = Path(storage).resolve() / f"{spec.name}.sweep.yaml"
    text = "# written by spot.sweep.run_sweep from a dict\n" + yaml.safe_dump(
        dict(data), sort_keys=False, allow_unicode=True
    )
    if path.is_file() and path.read_text() == text:
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def resolve(sweep: str | Path | Mapping[str, Any], *, smoke: bool = False) -> Sweep:
    """The validated :class:`Sweep` of a sweep file or dict (what ``spot sweep FILE --dry-run``
    lists: ``.trials()``, ``.runs()``); launches nothing, writes nothing."""
    return load_dict(dict(sweep), smoke=smoke) if isinstance(sweep, Mapping) else load(sweep, smoke=smoke)


def run_sweep(
    sweep: str | Path | Mapping[str, Any],
    *,
    smoke: bool = False,
    storage: str | Path = launch.DEFAULT_STORAGE,
    **options: Any,
) -> list[Row]:
    """Run a sweep from a file or a dict end to end (``spot sweep``); return the summary rows.

    Args:
      sweep: a sweep file's path, or a dict of its content (``name``, ``base``, ``grid``, ...,
        docs/sweeps.md).
      smoke: apply the sweep's ``smoke:`` block (experiment ``<name>-smoke``).
      storage: Ray Tune storage folder; a dict sweep is written there as ``<name>.sweep.yaml``.
      options: the keyword arguments of :func:`spot.sweep.launch.run_sweep` (``resume``,
        ``tracking_uri``, ``workdir``, ``address``, ``max_concurrent``, ``store``, ...).

    Raises:
      SpotError: a sweep that does not validate (nothing written), or a launch that cannot start.
    """
    if isinstance(sweep, Mapping):
        spec = load_dict(dict(sweep), smoke=smoke, progress=False)  # before anything is written
        sweep = sweep_file(spec, sweep, storage)
    return launch.run_sweep(sweep, smoke=smoke, storage=storage, **options)
