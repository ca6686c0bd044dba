"""``spot data fetch``: download the paper's real data files, verified, with resume and mirrors.

The sources and their pins are the registry's (:mod:`spot.data.sources`, ``sources.json``). Files
pinned ``tofu`` (no published sum known) are trusted on first use: the first verified download
records its sha256 and size in a lock file (``spot-data.lock.json`` by default) that the user can
commit; every later download must match it.

A file is downloaded to ``<path>.part`` in the destination folder with HTTP Range resume (a
partial ``.part`` from an earlier run or a dropped connection is continued, not restarted), its
size and sha256 are checked, a sidecar ``<path>.verified.json`` records the verified sum, and only
then is it renamed to ``<path>``. A file that fails a check is deleted and the next URL is tried;
when every URL fails, :class:`SpotError` names each URL and what went wrong (expected and actual
sums for a mismatch). :func:`verify_fetched` rechecks size and sha256 against the sidecar; the
dataset and label loaders call it, so a fetched file that changed on disk is never used.

The transfer itself (byte caps, timeouts, minimum rate, deadline, redirect and address checks:
the server is not trusted) is :mod:`spot.data.download`'s. A file with nothing pinned yet is
recorded only after a transfer whose size the server announced and that reached it; its partial
download is never resumed from another URL.

Minari datasets (``minari:<dataset id>``) go through Minari's own ``minari.download_dataset``
(extra ``minari``); Minari publishes no checksums, so their files are trust-on-first-use too: the
digest of the dataset folder is recorded in the lock file and checked on every later fetch.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from spot import SpotError, runtime
from spot.data.download import PART_SUFFIX, Limits, Mismatch, Pin, Policy, Unreachable, download_to, origin_of, short
from spot.data.sources import Source, SourceFile, declared_hosts, has_host, load_registry, registry_path, resolve

LOCK_ENV = "SPOT_DATA_LOCK"
DEFAULT_LOCK = "spot-data.lock.json"
SIDECAR_SUFFIX = ".verified.json"
MINARI_PREFIX = "minari:"
_CHUNK = 1 << 20


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


# --------------------------------------------------------------------------- fetch
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
        if not (isinstance(m, str) and m.startswith(("http://", "https://")) and has_host(m)):
            raise SpotError(f"mirror {str(m)[:200]!r}: expected an http(s) URL with a host")
    source = resolve(name, load_registry(registry))
    explicit = {origin_of(m) for m in mirrors}
    if registry_path(registry) is not None:  # the user's own registry file
        explicit |= {origin_of(u) for f in source.files for u in f.urls}
    policy = Policy(declared_hosts(registry), frozenset(explicit), limits)
    dest = Path(dest).expanduser() if dest else default_dest()
    lock_path = Path(lock).expanduser() if lock else default_lock()
    result = FetchResult(source, lock=lock_path)
    for sf in source.files:
        result.files.append(_fetch_file(source, sf, dest, lock_path, mirrors, policy, progress, retries, backoff))
    return result


def _lock_key(source: Source, sf: SourceFile) -> str:
    return f"{source.name}:{sf.path}"


def _pin(source: Source, sf: SourceFile, lock_path: Path, limits: Limits) -> Pin:
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
            return Pin(sha, size, by, size, "the size recorded in the lock file")
    if size is not None:
        return Pin(sha, size, by, size, "the pinned size")
    if sf.max_size is not None:
        return Pin(sha, None, by, sf.max_size, "the registry's max_size")
    return Pin(sha, None, by, limits.max_bytes, "the max_bytes limit")


def _fetch_file(
    source: Source,
    sf: SourceFile,
    dest: Path,
    lock_path: Path,
    mirrors: Sequence[str],
    policy: Policy,
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
            except Mismatch as err:
                part.unlink(missing_ok=True)
                failures.append(f"{short(url)}: {err}")
                continue
            except Unreachable as err:
                kept = ""
                if part.exists() and part.stat().st_size == 0:
                    part.unlink()
                if pin.sha is None:  # nothing pins it: never splice another server's bytes onto these
                    part.unlink(missing_ok=True)
                    kept = "; its partial download was deleted (nothing pins this file yet)"
                elif part.exists():
                    kept = "; the partial download is kept for a resume"
                failures.append(f"{short(url)}: {err}{kept}")
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
    url: str, part: Path, pin: Pin, policy: Policy, progress: bool, retries: int, backoff: float
) -> tuple[str, int]:
    got_size, announced = download_to(url, part, pin, policy, progress, retries, backoff)
    got_sha = sha256_file(part)
    if pin.size is not None and got_size != pin.size:
        raise Mismatch(f"got {got_size} bytes; expected {pin.size}")
    if pin.sha is not None and got_sha != pin.sha:
        raise Mismatch(
            f"sha256 mismatch: expected {pin.sha}, got {got_sha} (expected sum from: {_trust_words(pin.by)})"
        )
    if pin.sha is None and announced is None:
        raise Mismatch(
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
