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

Minari datasets (``minari:<dataset id>``) go through Minari's own ``minari.download_dataset``
(extra ``minari``); Minari publishes no checksums, so their files are trust-on-first-use too: the
digest of the dataset folder is recorded in the lock file and checked on every later fetch.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path
from typing import Any

from spot import SpotError

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


# --------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class SourceFile:
    path: str  # relative to the destination folder
    urls: tuple[str, ...]
    sha256: str | None
    size: int | None
    trust: str
    note: str = ""


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
    return {name: _source(name, entry, label) for name, entry in data["sources"].items()}


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
        or not all(isinstance(u, str) and u.startswith(("http://", "https://")) for u in urls)
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
    return SourceFile(path, tuple(urls), sha, size, trust, str(f.get("note", "")))


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
    from spot.data.registry import data_dir

    return data_dir() / "real"


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


class _Mismatch(Exception):
    """A URL served something that failed verification (deleted; try the next URL)."""


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
) -> FetchResult:
    """Download every file of a registered source into ``dest``, verified.

    Args:
      name: a registry name (``spot data fetch --list``); ``minari:<id>`` goes to
        :func:`fetch_minari`.
      dest: destination folder; default ``$SPOT_DATA_DIR/real``.
      mirrors: base URLs tried before the registry's own, as ``<mirror>/<file path>``.
      registry: another registry file (default ``$SPOT_FETCH_REGISTRY`` or the package's).
      lock: the TOFU lock file (default ``$SPOT_DATA_LOCK`` or ``./spot-data.lock.json``).
      progress: show a tqdm progress bar per file.
      retries: attempts per URL after a dropped connection or timeout (each resumes).
      timeout: seconds to wait for a server to answer or send more bytes.
      backoff: seconds to wait before the second attempt (doubled each time).
    """
    source = resolve(name, load_registry(registry))
    dest = Path(dest).expanduser() if dest else default_dest()
    lock_path = Path(lock).expanduser() if lock else default_lock()
    result = FetchResult(source, lock=lock_path)
    for sf in source.files:
        result.files.append(_fetch_file(source, sf, dest, lock_path, mirrors, progress, retries, timeout, backoff))
    return result


def _lock_key(source: Source, sf: SourceFile) -> str:
    return f"{source.name}:{sf.path}"


def _fetch_file(
    source: Source,
    sf: SourceFile,
    dest: Path,
    lock_path: Path,
    mirrors: Sequence[str],
    progress: bool,
    retries: int,
    timeout: float,
    backoff: float,
) -> FileResult:
    final = dest / sf.path
    key = _lock_key(source, sf)
    sha, size, pinned_by = sf.sha256, sf.size, sf.trust
    if sf.trust == "tofu":
        recorded = read_lock(lock_path).get(key)
        if recorded:
            sha, size, pinned_by = recorded.get("sha256"), recorded.get("size"), "tofu"
            if not isinstance(sha, str) or len(sha) != 64:
                raise SpotError(f"lock file '{lock_path}': '{key}' has no valid sha256")
    final.parent.mkdir(parents=True, exist_ok=True)
    with _flock(dest / ".locks" / (sf.path.replace("/", "__") + ".lock")):
        if final.is_file() and (sha is not None):
            have_size = final.stat().st_size
            if (size is None or have_size == size) and sha256_file(final) == sha:
                _write_sidecar(final, source, sf, sha, have_size, "", pinned_by)
                return FileResult(final, sha, have_size, pinned_by, "", "present")
        urls = [m.rstrip("/") + "/" + sf.path for m in mirrors] + list(sf.urls)
        failures = []
        for url in urls:
            part = final.with_name(final.name + PART_SUFFIX)
            try:
                got_sha, got_size = _download(url, part, size, progress, retries, timeout, backoff)
                if size is not None and got_size != size:
                    raise _Mismatch(f"got {got_size} bytes; expected {size}")
                if sha is not None and got_sha != sha:
                    raise _Mismatch(
                        f"sha256 mismatch: expected {sha}, got {got_sha} (expected sum from: {_trust_words(pinned_by)})"
                    )
            except _Mismatch as err:
                part.unlink(missing_ok=True)
                failures.append(f"{url}: {err}")
                continue
            except _Unreachable as err:
                failures.append(f"{url}: {err}")
                continue
            status = "downloaded"
            if sha is None:  # TOFU, first use: record what was verified against nothing but size
                _record_lock(
                    lock_path,
                    key,
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


class _Unreachable(Exception):
    """A URL could not deliver the file (HTTP error, connection failures past the retries)."""


def _download(
    url: str, part: Path, size: int | None, progress: bool, retries: int, timeout: float, backoff: float
) -> tuple[str, int]:
    """Download ``url`` into ``part``, resuming what it holds; return (sha256, size).

    Raises ``_Unreachable`` for HTTP errors and connections that keep failing (the partial file
    is kept for a later resume), ``_Mismatch`` when the server announces a size other than the
    expected one.
    """
    import requests
    from tqdm.auto import tqdm

    attempt = 0
    announced = size  # the size the file must have: pinned, else what the server announced
    while True:
        have = part.stat().st_size if part.exists() else 0
        if size is not None and have > size:
            part.unlink()
            have = 0
        headers = {"Range": f"bytes={have}-"} if have else {}
        try:
            with requests.get(url, headers=headers, stream=True, timeout=timeout) as r:
                if r.status_code == 416 and have and size is not None and have == size:
                    break  # the partial file is already complete
                if r.status_code == 416 and have:
                    part.unlink()  # the server has no bytes past what we hold: start over
                    attempt += 1
                    if attempt > retries:
                        raise _Unreachable(f"HTTP 416 for a resume at byte {have}")
                    continue
                if r.status_code not in (200, 206):
                    raise _Unreachable(f"HTTP {r.status_code} {r.reason}")
                total = _announced_total(r, have)
                if size is not None and total is not None and total != size:
                    raise _Mismatch(f"the server announces {total} bytes; expected {size}")
                announced = announced if announced is not None else total
                mode = "ab"
                if r.status_code == 200 and have:
                    mode, have = "wb", 0  # the server ignored the Range header: start over
                elif r.status_code == 206 and not _range_starts_at(r, have):
                    raise _Unreachable(f"server answered Range bytes={have}- with '{r.headers.get('Content-Range')}'")
                bar = tqdm(
                    total=size or total,
                    initial=have,
                    unit="B",
                    unit_scale=True,
                    unit_divisor=1024,
                    desc=part.name[: -len(PART_SUFFIX)],
                    disable=not progress,
                    leave=False,
                )
                with bar, open(part, mode) as fh:
                    for chunk in r.iter_content(_NET_CHUNK):
                        fh.write(chunk)
                        bar.update(len(chunk))
            break
        except (requests.ConnectionError, requests.Timeout, requests.exceptions.ChunkedEncodingError) as err:
            attempt += 1
            if attempt > retries:
                raise _Unreachable(
                    f"connection failed {attempt} times ({type(err).__name__}: "
                    f"{err}); the partial download is kept for a resume"
                ) from None
            time.sleep(backoff * 2 ** (attempt - 1))
    got = part.stat().st_size
    if announced is not None and got != announced:
        raise _Mismatch(f"got {got} bytes; the server announced {announced}")
    return sha256_file(part), got


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
