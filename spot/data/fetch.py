"""``spot data fetch``: download the paper's real data files, verified, with resume and mirrors.

The sources (D4RL v2 hdf5, robomimic v0.1 ``low_dim`` hdf5, the PT human label files) are listed
in the package data file ``spot/data/sources.json``: per file, its path under the destination
folder, the URLs tried in order, the pinned sha256 and size, and where the pin comes from
(``trust``):

* ``lfs-oid``: the Git LFS object id (= sha256 of the file) that a Hugging Face mirror publishes;
* ``git-commit``: sha256 of the file as stored in a pinned public git commit;
* ``third-party``: sum (and size) recorded by an independent public project, not the publisher;
* ``tofu``: no published sum known. Trust on first use: the first verified download records its
  sha256 and size in a lock file (``spot-data.lock.json`` by default) that the user can commit;
  every later download must match it.

A file is downloaded to ``<path>.part`` in the destination folder with HTTP Range resume (a
partial ``.part`` from an earlier run or a dropped connection is continued, not restarted), its
size and sha256 are checked, a sidecar ``<path>.verified.json`` records the verified sum, and only
then is it renamed to ``<path>``. A file that fails a check is deleted and the next URL is tried;
when every URL fails, :class:`SpotError` names each URL and what went wrong (expected and actual
sums for a mismatch). :func:`verify_fetched` rechecks size and sha256 against the sidecar; the
dataset and label loaders call it, so a fetched file that changed on disk is never used.

The server is not trusted (issue 43). Bytes are counted while they stream and capped at the pinned
size (else the size the lock file recorded, else the entry's ``max_size``, else ``max_bytes``):
an endless body stops one byte past the cap and its ``.part`` is deleted. Every wait has a limit
(:class:`Limits`: connect and per-read timeouts, a minimum rate over a window, a deadline per URL),
and the message names the host and the bytes received so far. Redirects are followed by hand, at
most ``max_redirects``: to the same origin, or to https on the same host or on a host the registry
declares (its URLs' hosts and ``redirect_hosts``); never to another scheme, and never to a private,
loopback, link-local, multicast or reserved address unless it is the very origin the user named
(``--mirror``, or a URL in the user's own ``--registry`` file). A file with nothing pinned yet is
recorded only after a transfer whose size the server announced and that reached it; its partial
download is never resumed from another URL.

Minari datasets (``minari:<dataset id>``) go through Minari's own ``minari.download_dataset``
(extra ``minari``); Minari publishes no checksums, so their files are trust-on-first-use too: the
digest of the dataset folder is recorded in the lock file and checked on every later fetch.
"""

from __future__ import annotations

import fcntl
import hashlib
import ipaddress
import json
import os
import socket
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import urljoin, urlsplit

from spot import SpotError, runtime

REGISTRY_ENV = "SPOT_FETCH_REGISTRY"  # another registry file (same format): private mirrors, tests
LOCK_ENV = "SPOT_DATA_LOCK"
DEFAULT_LOCK = "spot-data.lock.json"
TRUST = ("lfs-oid", "git-commit", "third-party", "tofu")
KINDS = ("d4rl", "robomimic", "pt-labels")
SIDECAR_SUFFIX = ".verified.json"
PART_SUFFIX = ".part"
MINARI_PREFIX = "minari:"
_CHUNK = 1 << 20
_NET_CHUNK = 1 << 16  # bytes per network read: what a dropped connection can lose before a resume
DEFAULT_MAX_BYTES = 8 << 30  # cap for a file with no pinned size, no recorded size and no max_size
MAX_REDIRECTS = 5
_PORTS = {"http": 80, "https": 443}


# --------------------------------------------------------------------------- registry
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
        or not all(isinstance(u, str) and u.startswith(("http://", "https://")) and _has_host(u) for u in urls)
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


def _has_host(url: str) -> bool:
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


def default_dest() -> Path:
    return runtime.data_dir() / "real"


def default_lock() -> Path:
    return Path(os.environ.get(LOCK_ENV) or DEFAULT_LOCK).expanduser()


# --------------------------------------------------------------------------- lock file (TOFU)
_LOCK_ABOUT = (
    "Trust-on-first-use checksums recorded by `spot data fetch` for files without a "
    "published checksum. Commit this file: later downloads must match it."
)


def read_lock(path: Path) -> dict[str, dict[str, Any]]:
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise SpotError(f"lock file '{path}' cannot be read as JSON ({err})") from None
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, dict):
        raise SpotError(f"lock file '{path}': expected an object with a 'files' object")
    return files


def _record_lock(path: Path, key: str, record: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with _flock(path.with_name(path.name + ".lck")):
        files = read_lock(path)
        files[key] = record
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps({"about": _LOCK_ABOUT, "files": dict(sorted(files.items()))}, indent=2) + "\n")
        os.replace(tmp, path)


@contextmanager
def _flock(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


# --------------------------------------------------------------------------- verification
def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def sidecar_path(path: Path) -> Path:
    return path.with_name(path.name + SIDECAR_SUFFIX)


def verify_fetched(path: str | Path) -> bool:
    """Recheck a fetched file (or every fetched file in a folder) against its sidecar.

    Returns False when nothing there was fetched by ``spot data fetch`` (no sidecar: a file the
    user made or copied, used as it is), True when every fetched file still has its verified
    size and sha256. Raises :class:`SpotError` naming the file, the expected and the actual sum
    otherwise.
    """
    path = Path(path)
    targets = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    checked = False
    for target in targets:
        side = sidecar_path(target)
        if target.name.endswith(SIDECAR_SUFFIX) or not side.is_file():
            continue
        try:
            record = json.loads(side.read_text())
            want_sha, want_size = str(record["sha256"]), int(record["size"])
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
            raise SpotError(
                f"fetch sidecar '{side}' is unreadable ({err}); delete '{target}' and its sidecar and fetch it again"
            ) from None
        if not target.is_file():
            raise SpotError(f"fetched file '{target}' is missing (its sidecar '{side}' exists)")
        size = target.stat().st_size
        got = sha256_file(target) if size == want_size else None
        if size != want_size or got != want_sha:
            raise SpotError(
                f"fetched file '{target}' changed since it was verified: expected {want_size} "
                f"bytes, sha256 {want_sha}; found {size} bytes"
                + (f", sha256 {got}" if got else "")
                + f". Delete it and run `spot data fetch {record.get('source', 'NAME')}` again"
            )
        checked = True
    return checked


# --------------------------------------------------------------------------- download
@dataclass
class FileResult:
    path: Path
    sha256: str
    size: int
    trust: str
    url: str  # the URL it came from ('' when it was already present and verified)
    status: str  # downloaded | present | recorded (TOFU, first use)


@dataclass
class FetchResult:
    source: Source
    files: list[FileResult] = field(default_factory=list)
    lock: Path | None = None


@dataclass(frozen=True)
class Limits:
    """How long and how much one file's download from one URL may take."""

    connect_timeout: float = 30.0  # seconds to open a connection
    read_timeout: float = 60.0  # seconds one socket read may wait (the answer, or more of the body)
    deadline: float | None = 4 * 3600.0  # seconds for the whole download, retries included; None: none
    min_rate: float = 1024.0  # bytes per second, averaged over each rate_window; 0: no check
    rate_window: float = 60.0
    max_bytes: int = DEFAULT_MAX_BYTES  # cap where no size is pinned, recorded or declared
    max_redirects: int = MAX_REDIRECTS

    def check(self) -> None:
        for key in ("connect_timeout", "read_timeout", "rate_window"):
            if not (getattr(self, key) > 0):  # also refuses NaN
                raise SpotError(f"fetch '{key}' is {getattr(self, key)!r}; expected a positive number of seconds")
        if self.deadline is not None and not self.deadline > 0:
            raise SpotError(f"fetch 'deadline' is {self.deadline!r}; expected positive seconds or None")
        if not self.min_rate >= 0:
            raise SpotError(f"fetch 'min_rate' is {self.min_rate!r}; expected bytes per second >= 0")
        if not (self.max_bytes >= 1 and 0 <= self.max_redirects <= 30):
            raise SpotError(
                f"fetch 'max_bytes' {self.max_bytes!r} / 'max_redirects' {self.max_redirects!r}: "
                "expected >= 1 byte and 0-30 redirects"
            )


class _Mismatch(Exception):
    """A URL served something that failed verification (deleted; try the next URL)."""


class _Refused(_Mismatch):
    """A redirect or an address that the policy does not allow."""


class _Unreachable(Exception):
    """A URL could not deliver the file (HTTP error, connection failures past the retries)."""


class _Retry(Exception):
    """A dropped, stalled or too slow transfer: resumed, unless ``final`` (the deadline passed)."""

    def __init__(self, message: str, final: bool = False):
        super().__init__(message)
        self.final = final


def fetch(
    name: str,
    dest: str | Path | None = None,
    *,
    mirrors: Sequence[str] = (),
    registry: str | Path | None = None,
    lock: str | Path | None = None,
    progress: bool = True,
    retries: int = 3,
    timeout: float = 60.0,
    backoff: float = 1.0,
    limits: Limits | None = None,
) -> FetchResult:
    """Download every file of a registered source into ``dest``, verified.

    Args:
      name: a registry name (``spot data fetch --list``); ``minari:<id>`` goes to
        :func:`fetch_minari`.
      dest: destination folder; default ``$SPOT_DATA_DIR/real``.
      mirrors: base URLs tried before the registry's own, as ``<mirror>/<file path>``. Their
        origins may be private or loopback addresses (the user named them).
      registry: another registry file (default ``$SPOT_FETCH_REGISTRY`` or the package's); the
        origins of its URLs count as the user's own, like ``mirrors``.
      lock: the TOFU lock file (default ``$SPOT_DATA_LOCK`` or ``./spot-data.lock.json``).
      progress: show a tqdm progress bar per file.
      retries: attempts per URL after a dropped, stalled or too slow connection (each resumes).
      timeout: seconds one read may wait for the server (``Limits.read_timeout``; ignored when
        ``limits`` is given).
      backoff: seconds to wait before the second attempt (doubled each time).
      limits: connect/read timeouts, minimum rate, deadline, byte cap and redirect count.
    """
    limits = limits or Limits(read_timeout=timeout)
    limits.check()
    for m in mirrors:
        if not (isinstance(m, str) and m.startswith(("http://", "https://")) and _has_host(m)):
            raise SpotError(f"mirror {str(m)[:200]!r}: expected an http(s) URL with a host")
    source = resolve(name, load_registry(registry))
    explicit = {_origin(m) for m in mirrors}
    if registry_path(registry) is not None:  # the user's own registry file
        explicit |= {_origin(u) for f in source.files for u in f.urls}
    policy = _Policy(declared_hosts(registry), frozenset(explicit), limits)
    dest = Path(dest).expanduser() if dest else default_dest()
    lock_path = Path(lock).expanduser() if lock else default_lock()
    result = FetchResult(source, lock=lock_path)
    for sf in source.files:
        result.files.append(_fetch_file(source, sf, dest, lock_path, mirrors, policy, progress, retries, backoff))
    return result


def _lock_key(source: Source, sf: SourceFile) -> str:
    return f"{source.name}:{sf.path}"


@dataclass(frozen=True)
class _Pin:
    sha: str | None  # None: trust on first use, nothing recorded yet
    size: int | None
    by: str  # the trust the sum comes from
    cap: int  # no more bytes than this are ever written
    cap_what: str


def _pin(source: Source, sf: SourceFile, lock_path: Path, limits: Limits) -> _Pin:
    sha, size, by = sf.sha256, sf.size, sf.trust
    if sf.trust == "tofu":
        key = _lock_key(source, sf)
        recorded = read_lock(lock_path).get(key)
        if recorded:
            sha, size, by = recorded.get("sha256"), recorded.get("size"), "tofu"
            if not isinstance(sha, str) or len(sha) != 64:
                raise SpotError(f"lock file '{lock_path}': '{key}' has no valid sha256")
            if not isinstance(size, int) or isinstance(size, bool) or size < 0:
                raise SpotError(f"lock file '{lock_path}': '{key}' has no valid size")
            return _Pin(sha, size, by, size, "the size recorded in the lock file")
    if size is not None:
        return _Pin(sha, size, by, size, "the pinned size")
    if sf.max_size is not None:
        return _Pin(sha, None, by, sf.max_size, "the registry's max_size")
    return _Pin(sha, None, by, limits.max_bytes, "the max_bytes limit")


def _fetch_file(
    source: Source,
    sf: SourceFile,
    dest: Path,
    lock_path: Path,
    mirrors: Sequence[str],
    policy: _Policy,
    progress: bool,
    retries: int,
    backoff: float,
) -> FileResult:
    final = dest / sf.path
    pin = _pin(source, sf, lock_path, policy.limits)
    final.parent.mkdir(parents=True, exist_ok=True)
    with _flock(dest / ".locks" / (sf.path.replace("/", "__") + ".lock")):
        if final.is_file() and (pin.sha is not None):
            have_size = final.stat().st_size
            if (pin.size is None or have_size == pin.size) and sha256_file(final) == pin.sha:
                _write_sidecar(final, source, sf, pin.sha, have_size, "", pin.by)
                return FileResult(final, pin.sha, have_size, pin.by, "", "present")
        urls = [m.rstrip("/") + "/" + sf.path for m in mirrors] + list(sf.urls)
        part = final.with_name(final.name + PART_SUFFIX)
        failures = []
        for url in urls:
            try:
                got_sha, got_size = _verified_download(url, part, pin, policy, progress, retries, backoff)
            except _Mismatch as err:
                part.unlink(missing_ok=True)
                failures.append(f"{_short(url)}: {err}")
                continue
            except _Unreachable as err:
                kept = ""
                if part.exists() and part.stat().st_size == 0:
                    part.unlink()
                if pin.sha is None:  # nothing pins it: never splice another server's bytes onto these
                    part.unlink(missing_ok=True)
                    kept = "; its partial download was deleted (nothing pins this file yet)"
                elif part.exists():
                    kept = "; the partial download is kept for a resume"
                failures.append(f"{_short(url)}: {err}{kept}")
                continue
            status = "downloaded"
            if pin.sha is None:  # TOFU, first use: record what was verified against nothing but size
                _record_lock(
                    lock_path,
                    _lock_key(source, sf),
                    {"sha256": got_sha, "size": got_size, "url": url, "recorded": _now(), "trust": "tofu"},
                )
                status = "recorded"
            _write_sidecar(final, source, sf, got_sha, got_size, url, "tofu" if sf.trust == "tofu" else sf.trust)
            os.replace(part, final)
            return FileResult(final, got_sha, got_size, sf.trust, url, status)
        raise SpotError(
            f"could not fetch '{sf.path}' of '{source.name}' from any of {len(urls)} URL(s); "
            "nothing unverified was kept: " + "; ".join(failures)
        )


def _verified_download(
    url: str, part: Path, pin: _Pin, policy: _Policy, progress: bool, retries: int, backoff: float
) -> tuple[str, int]:
    got_sha, got_size, announced = _download(url, part, pin, policy, progress, retries, backoff)
    if pin.size is not None and got_size != pin.size:
        raise _Mismatch(f"got {got_size} bytes; expected {pin.size}")
    if pin.sha is not None and got_sha != pin.sha:
        raise _Mismatch(
            f"sha256 mismatch: expected {pin.sha}, got {got_sha} (expected sum from: {_trust_words(pin.by)})"
        )
    if pin.sha is None and announced is None:
        raise _Mismatch(
            f"the server announced no size for these {got_size:,} bytes, so a cut transfer cannot be told "
            "from a whole one; a first download (trust on first use) is not recorded without it"
        )
    return got_sha, got_size


def _trust_words(trust: str) -> str:
    return {
        "lfs-oid": "the mirror's published Git LFS object id",
        "git-commit": "the file in the pinned git commit",
        "third-party": "a third-party record, not the publisher's",
        "tofu": "the lock file (trust on first use)",
    }[trust]


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _write_sidecar(final: Path, source: Source, sf: SourceFile, sha: str, size: int, url: str, trust: str) -> None:
    side = sidecar_path(final)
    record = {
        "source": source.name,
        "path": sf.path,
        "sha256": sha,
        "size": size,
        "trust": trust,
        "url": url,
        "verified": _now(),
    }
    tmp = side.with_name(f"{side.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(tmp, side)


# --------------------------------------------------------------------------- where a request may go
@dataclass(frozen=True)
class _Policy:
    hosts: frozenset[str]  # hosts (or '*.domain') a redirect may go to over https
    explicit: frozenset[tuple[str, str, int]]  # origins the user named: any address allowed
    limits: Limits


def _origin(url: str) -> tuple[str, str, int]:
    """(scheme, host, port) of ``url``; ValueError for a port that is not a number."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    return scheme, (parts.hostname or "").lower(), parts.port or _PORTS.get(scheme, 0)


def _short(text: str, n: int = 200) -> str:
    """A server-chosen string made safe for a one-line message: printable ASCII, at most n chars."""
    clean = "".join(c if " " <= c <= "~" else "?" for c in str(text))
    return clean if len(clean) <= n else clean[:n] + "..."


def _declared(host: str, patterns: frozenset[str]) -> bool:
    return any(host == p or (p.startswith("*.") and host.endswith(p[1:])) for p in patterns)


def _redirect_target(current: str, location: str, policy: _Policy) -> str:
    """The URL a redirect from ``current`` to ``location`` leads to, if the policy allows it."""
    target = urljoin(current, location.strip())
    try:
        new, cur = _origin(target), _origin(current)
    except ValueError:
        raise _Refused(f"redirect to '{_short(target)}' refused: not a valid URL") from None
    if new[0] not in _PORTS:
        raise _Refused(f"redirect to '{_short(target)}' refused: scheme '{_short(new[0], 20)}:' (only http(s))")
    if new == cur:
        return target  # same scheme, host and port: another path on the server already asked
    if new[0] != "https":
        raise _Refused(f"redirect to '{_short(target)}' refused: plain http to another origin than {cur[1]}:{cur[2]}")
    if new[1] != cur[1] and not _declared(new[1], policy.hosts):
        raise _Refused(
            f"redirect to '{_short(target)}' refused: host {_short(new[1], 80)} is neither {cur[1]} "
            "nor a host the sources registry declares"
        )
    return target


def _resolve(host: str, port: int) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as err:
        raise _Unreachable(f"cannot resolve host {_short(host, 80)} ({err})") from None
    return [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]


def _not_public(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str:
    """'' for a public unicast address, else what it is (loopback, link-local, ...)."""
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped:
        ip = ip.ipv4_mapped
    for kind in ("loopback", "link_local", "multicast", "private", "reserved", "unspecified"):
        if getattr(ip, f"is_{kind}"):
            return kind.replace("_", "-")
    return "" if ip.is_global else "non-public"


def _check_address(url: str, policy: _Policy) -> None:
    """Refuse a URL whose host resolves to a non-public address, unless the user named that origin."""
    origin = _origin(url)
    if origin in policy.explicit:
        return
    for ip in _resolve(origin[1], origin[2]):
        if kind := _not_public(ip):
            raise _Refused(
                f"'{_short(url)}' refused: {_short(origin[1], 80)} resolves to {ip}, a {kind} address; only "
                "an origin the user named (--mirror or their own --registry) may be one"
            )


def _check_peer(r: Any, url: str, policy: _Policy) -> None:
    """The address actually connected to must pass too (a name that resolved again elsewhere)."""
    import requests

    origin = _origin(url)
    if origin in policy.explicit or requests.utils.get_environ_proxies(url):
        return  # the user's own origin, or a proxy the user set up connects for us
    try:
        ip = ipaddress.ip_address(str(r.raw.connection.sock.getpeername()[0]).split("%")[0])
    except (AttributeError, OSError, ValueError, IndexError, TypeError):
        return  # no socket to ask (closed already): the resolution check stands
    if kind := _not_public(ip):
        raise _Refused(
            f"'{_short(url)}' refused: the connection to {_short(origin[1], 80)} went to {ip}, a {kind} address"
        )


# --------------------------------------------------------------------------- the transfer
class _Clock:
    """The deadline of one URL's download and the minimum-rate check; messages name the host."""

    def __init__(self, host: str, limits: Limits):
        self.host, self.limits = host, limits
        self.start = self.mark = time.monotonic()
        self.mark_bytes = 0

    def new_window(self, have: int) -> None:
        self.mark, self.mark_bytes = time.monotonic(), have

    def check(self, have: int, waiting_for: str) -> None:
        now, lim = time.monotonic(), self.limits
        if lim.deadline is not None and now - self.start > lim.deadline:
            raise _Retry(
                f"{self.host}: the download passed its deadline of {lim.deadline:g} s while waiting for "
                f"{waiting_for} ({have:,} bytes so far)",
                final=True,
            )
        span = now - self.mark
        if lim.min_rate and span >= lim.rate_window:
            got = have - self.mark_bytes
            if got < lim.min_rate * span:
                raise _Retry(
                    f"{self.host} sent {got:,} bytes in {span:.1f} s while we waited for {waiting_for}, below "
                    f"the minimum of {lim.min_rate:g} bytes/s ({have:,} bytes so far)"
                )
            self.new_window(have)


def _download(
    url: str, part: Path, pin: _Pin, policy: _Policy, progress: bool, retries: int, backoff: float
) -> tuple[str, int, int | None]:
    """Download ``url`` into ``part``, resuming what it holds; return (sha256, size, announced size).

    Raises ``_Unreachable`` for HTTP errors and connections that keep failing (the partial file
    is kept), ``_Mismatch`` when the server announces or sends another size than allowed, and
    ``_Refused`` for a redirect or address the policy refuses.
    """
    import requests

    clock = _Clock(_origin(url)[1], policy.limits)
    attempt, announced = 0, pin.size
    with requests.Session() as session:
        while True:
            have = part.stat().st_size if part.exists() else 0
            if have > pin.cap:
                part.unlink()
                have = 0
            try:
                clock.new_window(have)
                r = _open(session, url, have, policy, clock)
                with r:
                    if r.status_code == 416 and have:
                        if pin.size is not None and have == pin.size:
                            break  # the partial file is already complete
                        part.unlink()  # the server has no bytes past what we hold: start over
                        raise _Retry(f"HTTP 416 for a resume at byte {have}")
                    total = _receive(r, part, have, pin, clock, progress)
                announced = announced if announced is not None else total
                break
            except _Retry as err:
                attempt += 1
                if err.final:
                    raise _Unreachable(str(err)) from None
                if attempt > retries:
                    raise _Unreachable(f"connection failed {attempt} times (last: {err})") from None
                time.sleep(backoff * 2 ** (attempt - 1))
    got = part.stat().st_size
    if announced is not None and got != announced:
        raise _Mismatch(f"got {got} bytes; the server announced {announced}")
    return sha256_file(part), got, announced


def _open(session: Any, url: str, have: int, policy: _Policy, clock: _Clock) -> Any:
    """GET ``url`` (from byte ``have``), following the redirects the policy allows."""
    import requests

    lim = policy.limits
    headers = {"Accept-Encoding": "identity", **({"Range": f"bytes={have}-"} if have else {})}
    current = url
    for _ in range(lim.max_redirects + 1):
        clock.check(have, "an answer")
        _check_address(current, policy)
        clock.host = _short(_origin(current)[1], 80)
        try:
            r = session.get(
                current,
                headers=headers,
                stream=True,
                allow_redirects=False,
                timeout=(lim.connect_timeout, lim.read_timeout),
            )
        except requests.ConnectTimeout:
            raise _Retry(f"no connection to {clock.host} within {lim.connect_timeout:g} s") from None
        except requests.ReadTimeout:
            raise _Retry(f"{clock.host} sent no answer within {lim.read_timeout:g} s") from None
        except requests.ConnectionError as err:
            raise _Retry(f"connection to {clock.host} failed ({type(err).__name__}: {_short(err)})") from None
        except requests.RequestException as err:
            raise _Unreachable(f"{type(err).__name__}: {_short(err)}") from None
        if not r.is_redirect:
            try:
                _check_peer(r, current, policy)
            except _Refused:
                r.close()
                raise
            return r
        r.close()
        current = _redirect_target(current, r.headers.get("Location", ""), policy)
    raise _Refused(f"more than {lim.max_redirects} redirects (the last to '{_short(current)}')")


def _receive(r: Any, part: Path, have: int, pin: _Pin, clock: _Clock, progress: bool) -> int | None:
    """Write the body of ``r`` to ``part`` from byte ``have``, at most ``pin.cap`` bytes in all;
    return the size the server announced (None when it did not)."""
    host = clock.host
    if r.status_code not in (200, 206):
        raise _Unreachable(f"HTTP {r.status_code} {_short(r.reason, 80)}")
    encoding = r.headers.get("Content-Encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise _Mismatch(f"{host} sent the file with Content-Encoding '{_short(encoding, 40)}' (identity was asked)")
    total = _announced_total(r, have)
    if pin.size is not None and total is not None and total != pin.size:
        raise _Mismatch(f"the server announces {total} bytes; expected {pin.size}")
    if total is not None and total > pin.cap:
        raise _Mismatch(f"{host} announces {total:,} bytes, more than {pin.cap:,} ({pin.cap_what})")
    mode = "ab"
    if r.status_code == 200 and have:
        mode, have = "wb", 0  # the server ignored the Range header: start over
    elif r.status_code == 206 and not _range_starts_at(r, have):
        raise _Unreachable(f"server answered Range bytes={have}- with '{_short(r.headers.get('Content-Range'))}'")
    with _bar(pin.size or total, have, part, progress) as bar, open(part, mode) as fh:
        while chunk := _read(r, have, pin.cap + 1 - have, clock):
            if have + len(chunk) > pin.cap:
                raise _Mismatch(
                    f"{host} sent more than {pin.cap:,} bytes ({pin.cap_what}); stopped at {have + len(chunk):,}"
                )
            fh.write(chunk)
            have += len(chunk)
            bar.update(len(chunk))
            clock.check(have, "the rest of the file")
    return total


def _read(r: Any, have: int, most: int, clock: _Clock) -> bytes:
    """What the server has sent so far, up to ``most`` bytes: returns as soon as any bytes came, so
    a trickle cannot hold the deadline and rate checks off (each wait is ``read_timeout`` at most)."""
    from urllib3.exceptions import HTTPError, ReadTimeoutError

    try:
        return r.raw.read1(min(_NET_CHUNK, most), decode_content=False) or b""
    except ReadTimeoutError:
        raise _Retry(f"{clock.host} sent nothing for {clock.limits.read_timeout:g} s ({have:,} bytes so far)") from None
    except (HTTPError, OSError) as err:
        why = (
            "the body ended before the length it announced"
            if "IncompleteRead" in repr(err)
            else f"{type(err).__name__}: {_short(err, 120)}"
        )
        raise _Retry(f"{clock.host} broke off after {have:,} bytes ({why})") from None


def _bar(total: int | None, have: int, part: Path, progress: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=have,
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        desc=part.name[: -len(PART_SUFFIX)],
        disable=not progress,
        leave=False,
    )


def _announced_total(r: Any, have: int) -> int | None:
    if r.status_code == 206:
        cr = r.headers.get("Content-Range", "")
        tail = cr.rsplit("/", 1)[-1] if "/" in cr else ""
        return int(tail) if tail.isdigit() else None
    length = r.headers.get("Content-Length")
    return int(length) if length and length.isdigit() else None


def _range_starts_at(r: Any, have: int) -> bool:
    cr = r.headers.get("Content-Range", "")  # "bytes START-END/TOTAL"
    try:
        return int(cr.split()[1].split("-")[0]) == have
    except (IndexError, ValueError):
        return False


# --------------------------------------------------------------------------- Minari
def fetch_minari(dataset_id: str, *, lock: str | Path | None = None, force: bool = False) -> tuple[Path, str, str]:
    """Download a Minari dataset with Minari's own API and check it against the lock file.

    Minari publishes no checksums: the first fetch records the digest of the dataset folder
    (sha256 over its files' relative paths and sha256 sums) in the lock file; every later fetch
    must match it. Returns (folder, digest, status) with status ``recorded`` or ``verified``.
    """
    try:
        import minari
        from minari.storage import get_dataset_path
    except ImportError:
        raise SpotError(
            "fetching Minari datasets needs the optional 'minari' extra: pip install 'spot-pbrl[minari]'"
        ) from None
    try:
        minari.download_dataset(dataset_id, force_download=force)
    except ImportError as err:
        raise SpotError(
            f"Minari download of '{dataset_id}' needs a package that is missing "
            f"({err}); pip install 'spot-pbrl[minari]'"
        ) from None
    except Exception as err:  # noqa: BLE001 - minari raises ValueError, HTTP and OS errors
        raise SpotError(f"Minari could not download '{dataset_id}': {type(err).__name__}: {err}") from None
    folder = Path(get_dataset_path(dataset_id))
    digest = tree_digest(folder)
    lock_path = Path(lock).expanduser() if lock else default_lock()
    key = MINARI_PREFIX + dataset_id
    recorded = read_lock(lock_path).get(key)
    if recorded is None:
        _record_lock(lock_path, key, {"sha256": digest, "folder_digest": True, "recorded": _now(), "trust": "tofu"})
        return folder, digest, "recorded"
    if recorded.get("sha256") != digest:
        raise SpotError(
            f"Minari dataset '{dataset_id}' in '{folder}' does not match the lock file "
            f"'{lock_path}': expected folder digest {recorded.get('sha256')}, got {digest}"
        )
    return folder, digest, "verified"


def tree_digest(folder: Path) -> str:
    """sha256 over ``<relative path> <sha256>`` lines of every file under ``folder``, sorted."""
    lines = [f"{p.relative_to(folder).as_posix()} {sha256_file(p)}\n" for p in sorted(folder.rglob("*")) if p.is_file()]
    if not lines:
        raise SpotError(f"Minari dataset folder '{folder}' holds no files")
    return hashlib.sha256("".join(lines).encode()).hexdigest()
