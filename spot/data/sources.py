"""The sources registry of ``spot data fetch``: which files exist, where, and how they are pinned.

The sources (D4RL v2 hdf5, robomimic v0.1 ``low_dim`` hdf5, the PT human label files) are listed
in the package data file ``spot/data/sources.json``: per file, its path under the destination
folder, the URLs tried in order, the pinned sha256 and size, and where the pin comes from
(``trust``):

* ``lfs-oid``: the Git LFS object id (= sha256 of the file) that a Hugging Face mirror publishes;
* ``git-commit``: sha256 of the file as stored in a pinned public git commit;
* ``third-party``: sum (and size) recorded by an independent public project, not the publisher;
* ``tofu``: no published sum known. Trust on first use: the first verified download records its
  sha256 and size in a lock file (:mod:`spot.data.fetch`); every later download must match it.

A registry also declares ``redirect_hosts``: the hosts (besides its URLs' own) a download may be
redirected to over https (:mod:`spot.data.download`). ``$SPOT_FETCH_REGISTRY`` (or ``--registry``)
names another registry file in the same format.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from spot import SpotError

REGISTRY_ENV = "SPOT_FETCH_REGISTRY"  # another registry file (same format): private mirrors, tests
TRUST = ("lfs-oid", "git-commit", "third-party", "tofu")
KINDS = ("d4rl", "robomimic", "pt-labels")


@dataclass(frozen=True)
class SourceFile:
    path: str  # relative to the destination folder
    urls: tuple[str, ...]
    sha256: str | None
    size: int | None
    trust: str
    note: str = ""
    max_size: int | None = None  # declared cap where no size is pinned (trust on first use)


@dataclass(frozen=True)
class Source:
    name: str
    kind: str
    description: str
    files: tuple[SourceFile, ...]
    labels: str = ""  # name of the PT label source for this dataset
    labels_for: str = ""  # for a label source: the dataset it indexes


def registry_path(path: str | Path | None = None) -> Path | None:
    """The registry file in use: ``path``, else ``$SPOT_FETCH_REGISTRY``, else None (package)."""
    if path:
        return Path(path).expanduser()
    env = os.environ.get(REGISTRY_ENV)
    return Path(env).expanduser() if env else None


def load_registry(path: str | Path | None = None) -> dict[str, Source]:
    """Read a sources registry (default: the package's ``sources.json``), checking every field."""
    data, label = _registry_json(path)
    _redirect_hosts(data, label)
    return {name: _source(name, entry, label) for name, entry in data["sources"].items()}


def declared_hosts(path: str | Path | None = None) -> frozenset[str]:
    """Hosts a redirect may go to (over https): every host the registry's URLs name, and its
    ``redirect_hosts`` (``name`` or ``*.domain``: the CDNs the listed servers hand files to)."""
    data, label = _registry_json(path)
    hosts = set(_redirect_hosts(data, label))
    for source in load_registry(path).values():
        hosts.update(urlsplit(u).hostname or "" for f in source.files for u in f.urls)
    return frozenset(hosts - {""})


def _redirect_hosts(data: dict[str, Any], label: str) -> list[str]:
    hosts = data.get("redirect_hosts", [])
    ok = isinstance(hosts, list) and all(
        isinstance(h, str)
        and h
        and h == h.lower()
        and "/" not in h
        and ":" not in h
        and "*" not in h.removeprefix("*.")
        for h in hosts
    )
    if not ok:
        raise SpotError(
            f"sources registry '{label}': 'redirect_hosts' must be a list of lowercase host names or '*.domain'"
        )
    return hosts


def _registry_json(path: str | Path | None) -> tuple[dict[str, Any], str]:
    where = registry_path(path)
    try:
        if where is None:
            text = resources.files("spot.data").joinpath("sources.json").read_text()
            label = "spot/data/sources.json"
        else:
            text = where.read_text()
            label = str(where)
    except OSError as err:
        raise SpotError(f"sources registry '{where}' cannot be read ({err})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise SpotError(f"sources registry '{label}' is not valid JSON ({err})") from None
    if not isinstance(data, dict) or not isinstance(data.get("sources"), dict):
        raise SpotError(f"sources registry '{label}': expected an object with a 'sources' object")
    return data, label


def _source(name: str, entry: Any, label: str) -> Source:
    where = f"sources registry '{label}', source '{name}'"
    if not isinstance(entry, dict):
        raise SpotError(f"{where}: expected an object")
    kind = entry.get("kind")
    if kind not in KINDS:
        raise SpotError(f"{where}: 'kind' is {kind!r}; expected one of {', '.join(KINDS)}")
    files = entry.get("files")
    if not isinstance(files, list) or not files:
        raise SpotError(f"{where}: 'files' must be a non-empty list")
    return Source(
        name,
        kind,
        str(entry.get("description", "")),
        tuple(_source_file(f, f"{where}, files[{i}]") for i, f in enumerate(files)),
        str(entry.get("labels", "")),
        str(entry.get("labels_for", "")),
    )


def _source_file(f: Any, where: str) -> SourceFile:
    if not isinstance(f, dict):
        raise SpotError(f"{where}: expected an object")
    path = f.get("path")
    if not isinstance(path, str) or not path or Path(path).is_absolute() or ".." in Path(path).parts:
        raise SpotError(f"{where}: 'path' is {path!r}; expected a relative path inside the destination")
    urls = f.get("urls")
    if (
        not isinstance(urls, list)
        or not urls
        or not all(isinstance(u, str) and u.startswith(("http://", "https://")) and has_host(u) for u in urls)
    ):
        raise SpotError(f"{where}: 'urls' must be a non-empty list of http(s) URLs")
    trust = f.get("trust")
    if trust not in TRUST:
        raise SpotError(f"{where}: 'trust' is {trust!r}; expected one of {', '.join(TRUST)}")
    sha = f.get("sha256")
    if trust == "tofu":
        if sha is not None:
            raise SpotError(f"{where}: a 'tofu' file has no pinned 'sha256' (it is recorded in the lock file)")
    elif not (isinstance(sha, str) and len(sha) == 64 and all(c in "0123456789abcdef" for c in sha)):
        raise SpotError(f"{where}: 'sha256' is {sha!r}; expected 64 lowercase hex digits (trust '{trust}')")
    size = f.get("size")
    if size is not None and (not isinstance(size, int) or isinstance(size, bool) or size < 0):
        raise SpotError(f"{where}: 'size' is {size!r}; expected a byte count or null")
    cap = f.get("max_size")
    if cap is not None and (not isinstance(cap, int) or isinstance(cap, bool) or cap < 1 or size is not None):
        raise SpotError(f"{where}: 'max_size' is {cap!r}; expected a positive byte count, only where 'size' is null")
    return SourceFile(path, tuple(urls), sha, size, trust, str(f.get("note", "")), cap)


def has_host(url: str) -> bool:
    try:
        parts = urlsplit(url)
        _ = parts.port  # ValueError for a port that is not a number
    except ValueError:
        return False
    return bool(parts.hostname)


def resolve(name: str, sources: dict[str, Source]) -> Source:
    """A source by full name (``d4rl/hopper-medium-replay-v2``) or by the part after the slash
    (``hopper-medium-replay-v2``: the dataset, not its labels)."""
    if name in sources:
        return sources[name]
    matches = [s for key, s in sources.items() if key.split("/", 1)[-1] == name]
    data = [s for s in matches if s.kind != "pt-labels"]
    if len(data) == 1:
        return data[0]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise SpotError(f"fetch name '{name}' is ambiguous: {', '.join(s.name for s in matches)}")
    import difflib

    close = difflib.get_close_matches(name, list(sources), n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    raise SpotError(
        f"unknown fetch name '{name}'{hint} (`spot data fetch --list` shows them; Minari datasets: minari:<dataset id>)"
    )
