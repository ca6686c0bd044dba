"""The names runs' tags have in MLflow: a few first-class ones, the bookkeeping under ``spot.``.

First-class tags keep their bare names, so that they lead a run's tag list and the runs table:
``method``, ``dataset``, ``seed``, ``variant`` and every swept axis (``axis.<key>``), plus the
run's ``failure_reason`` (the one line a failed or stopped run shows its reader) and MLflow's own
``mlflow.*``. Every other tag spot writes is bookkeeping and is stored as ``spot.<name>``
(:func:`stored`): the sweep's ids (``spot.sweep_id``, ``spot.sweep_name``, ``spot.trial_id``,
``spot.trial_key``, ``spot.config_key``, ``spot.attempt``), the stage cache (``spot.cache.*``,
``spot.stage.*``), package versions (``spot.version.*``), the run's provenance
(``spot.git_commit``, ``spot.data_digest``, ``spot.budget``, ``spot.dataset_source``, ...), the
process that owns the run (``spot.host``, ``spot.pid``, ...).

Code names a tag by its bare name (``"trial_key"``); the tracking layer stores it under
:func:`stored` (:class:`spot.tracking.trackers.MlflowTracker`, :func:`spot.tracking.record.start_run`,
the record folders of :mod:`spot.tracking.recorded`). Stores written before the move carry the
bare names (``sweep_id``, ``trial_key``, ``cache.reward``): :func:`get` reads either,
:func:`normalized` renames a run's tags to the new names, and :func:`alternatives` gives the tag
sets a lookup tries (:func:`spot.tracking.queries.search_tagged`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

PREFIX = "spot."
FIRST_CLASS = frozenset({"method", "dataset", "seed", "variant"})
BARE = FIRST_CLASS | {"failure_reason"}
"""Tags that keep their bare names (with ``axis.*``, ``mlflow.*`` and the ``spot.*`` ones)."""
KEPT_PREFIXES = ("axis.", "mlflow.", PREFIX)


def stored(key: str) -> str:
    """The name tag ``key`` has in MLflow: ``key`` for a first-class tag, else ``spot.<key>``."""
    return key if key in BARE or key.startswith(KEPT_PREFIXES) else PREFIX + key


def legacy(key: str) -> str:
    """The bare name a bookkeeping tag had before it moved under ``spot.`` (``key`` for a first-class one)."""
    name = stored(key)
    return name[len(PREFIX) :] if name.startswith(PREFIX) else name


def stored_tags(tags: Mapping[str, Any]) -> dict[str, str]:
    """``tags`` under their :func:`stored` names, values as strings."""
    return {stored(k): str(v) for k, v in tags.items()}


def get(tags: Mapping[str, str], key: str, default: str = "") -> str:
    """Tag ``key`` (a bare or stored name) of a run: its stored name, else its old bare name."""
    name = stored(key)
    if name in tags:
        return tags[name]
    return tags.get(legacy(key), default)


def has(tags: Mapping[str, str], key: str) -> bool:
    """Whether a run has tag ``key`` under its stored or its old bare name."""
    return stored(key) in tags or legacy(key) in tags


def normalized(tags: Mapping[str, str]) -> dict[str, str]:
    """A run's tags under the stored names: an old bare name is renamed (the stored name wins when a
    run has both, e.g. a run of an old sweep tagged again by a newer spot)."""
    out = {stored(k): v for k, v in tags.items() if stored(k) != k}
    out.update({k: v for k, v in tags.items() if stored(k) == k})
    return out


def alternatives(tags: Mapping[str, Any]) -> list[dict[str, str]]:
    """The tag sets that find runs with ``tags`` (bare or stored names): under the stored names, and
    under the old bare names where they differ (stores written before the move)."""
    new = {stored(k): str(v) for k, v in tags.items()}
    old = {legacy(k): str(v) for k, v in tags.items()}
    return [new] if old == new else [new, old]
