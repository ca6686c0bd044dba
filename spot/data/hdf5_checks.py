"""An untrusted hdf5 dataset file, checked before it is read (issue 43).

:func:`open_hdf5` opens a file read-only and runs :func:`check_hdf5` on it before anything else
reads it: external links, soft links that dangle or leave the file, too many links, virtual
datasets, HDF5 external storage, filter plugins, compression bombs and files whose declared
arrays do not fit in memory (:class:`ReadLimits`) are refused from the file's declared shapes
and dtypes, without reading an array. :func:`read_array`, :func:`check_rows` and
:func:`as_flags` then check what the readers of :mod:`spot.data.formats` take from it: real
numeric arrays of the expected rank, one row per step, flags 0 or 1.

Every bad input raises :class:`SpotError` naming the file, the key and what was expected.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from spot import SpotError


# --------------------------------------------------------------------------- the file, before it is read
@dataclass(frozen=True)
class ReadLimits:
    """What an hdf5 dataset file may make the reader allocate, checked from the file's declared
    shapes and dtypes before any array is read (:func:`check_hdf5`).

    Attributes:
      memory_bytes: memory the arrays may take; None = the memory available now
        (:func:`available_memory`). The file's datasets need twice their declared size (the arrays
        read and their float32 copies).
      max_expansion: most declared bytes per byte a dataset stores in the file, for datasets over
        ``expansion_floor``. gzip cannot exceed about 1032:1, so only a compression bomb or chunks
        never written (read back as fill values) pass it.
      expansion_floor: datasets up to this many declared bytes are not ratio-checked (a small
        all-zero array compresses to almost nothing).
      max_links: most links (groups, datasets, soft links) a file may hold; robomimic's mh files
        hold about 15,000.
    """

    memory_bytes: int | None = None
    max_expansion: float = 1100.0
    expansion_floor: int = 64 << 20
    max_links: int = 200_000


DEFAULT_LIMITS = ReadLimits()
# HDF5's own filters (gzip, shuffle, fletcher32, szip, nbit, scaleoffset) and h5py's lzf: a file
# naming another filter would make HDF5 look for a plugin library to run.
_BUILTIN_FILTERS = {1: "gzip", 2: "shuffle", 3: "fletcher32", 4: "szip", 5: "nbit", 6: "scaleoffset", 32000: "lzf"}


def available_memory() -> int:
    """Bytes of memory available to this process now: psutil's ``available`` (else free pages from
    ``os.sysconf``), lowered to what the cgroup (a container's limit) still allows."""
    try:
        import psutil

        avail = int(psutil.virtual_memory().available)
    except ImportError:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            avail = min(avail, max(int(limit) - used, 0))
    except (OSError, ValueError):
        pass
    return avail


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"


def _soft_target_error(f: h5py.File, name: str, target: str, depth: int = 0) -> str | None:
    """Why the soft link ``name`` -> ``target`` may not be read (it dangles, loops, or reaches
    another file through an external link), or None: it names an object of this file."""
    if depth > 16:
        return "is a chain of more than 16 soft links (a loop)"
    parent = name.rsplit("/", 1)[0] if "/" in name else ""
    where = "" if target.startswith("/") else parent
    for part in [p for p in target.split("/") if p not in ("", ".")]:
        here = f"{where}/{part}" if where else part
        group = f[where] if where else f
        link = group.get(part, getlink=True) if isinstance(group, h5py.Group) else None
        if link is None:
            return f"points to '{target}', which does not exist in the file (a dangling link)"
        if isinstance(link, h5py.ExternalLink):
            return f"points to '{target}', which passes through an external link to file '{link.filename}'"
        if isinstance(link, h5py.SoftLink):
            why = _soft_target_error(f, here, link.path, depth + 1)
            if why is not None:
                return why
        where = here  # a checked soft link is then followed by HDF5 itself
    return None


def _link_error(f: h5py.File, name: str) -> str | None:
    """Why the link ``name`` may not be read, or None."""
    link = f.get(name, getlink=True)
    if isinstance(link, h5py.ExternalLink):
        return (
            f"'{name}' is an external link to '{link.filename}:{link.path}'; expected every array inside "
            "the file (external links are refused)"
        )
    if isinstance(link, h5py.SoftLink):
        why = _soft_target_error(f, name, link.path)
        if why is not None:
            return f"soft link '{name}' {why}; expected links inside the file"
    return None


def _check_links(f: h5py.File, path: Path, limits: ReadLimits) -> None:
    """Refuse external links, soft links that dangle or leave the file, and too many links.

    The walk is HDF5's own (``H5Lvisit``, which follows no soft or external link), through h5py's
    low-level API: a robomimic mh file's 15,000 links take a tenth of a second. Its callback must
    not raise, so the walk stops at the first problem, which is raised after it.
    """
    count, problem = 0, []
    soft_or_external = (h5py.h5l.TYPE_SOFT, h5py.h5l.TYPE_EXTERNAL)

    def visit(name: bytes, info: Any) -> bool | None:
        nonlocal count
        count += 1
        if count > limits.max_links:
            return True
        if info.type in soft_or_external:
            why = _link_error(f, name.decode("utf-8", errors="replace"))
            if why is not None:
                problem.append(why)
                return True
        return None

    f.id.links.visit(visit, info=True)
    if problem:
        raise SpotError(f"dataset file '{path}': {problem[0]}")
    if count > limits.max_links:
        raise SpotError(
            f"dataset file '{path}' holds more than {limits.max_links} links (groups and arrays); "
            "expected a D4RL or robomimic file"
        )


def _check_layout(name: str, dsid: Any, path: Path) -> None:
    """Refuse a virtual dataset, external storage and unknown filters. ``dsid``: the dataset's
    low-level ``h5py.h5d.DatasetID``."""
    plist = dsid.get_create_plist()
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        raise SpotError(
            f"dataset file '{path}': '{name}' is a virtual dataset (VDS) mapping other files; "
            "expected arrays stored in the file"
        )
    if plist.get_external_count() > 0:
        target = plist.get_external(0)[0].decode(errors="replace")
        raise SpotError(
            f"dataset file '{path}': '{name}' stores its data in the external file '{target}'; "
            "expected arrays stored in the file (HDF5 external storage is refused)"
        )
    for i in range(plist.get_nfilters()):
        code = plist.get_filter(i)[0]
        if code not in _BUILTIN_FILTERS:
            raise SpotError(
                f"dataset file '{path}': '{name}' is compressed with HDF5 filter {code}; expected one of "
                f"{', '.join(sorted(_BUILTIN_FILTERS.values()))} (filter plugins are not loaded)"
            )


def check_hdf5(f: h5py.File, path: Path, limits: ReadLimits = DEFAULT_LIMITS) -> None:
    """Check an open hdf5 file before reading anything from it; :class:`SpotError` names the file
    and the dataset path.

    Refused: external links, soft links that dangle or reach another file, datasets with HDF5
    external storage, virtual datasets, filters other than HDF5's built-in ones and lzf, a
    dataset whose declared size exceeds ``limits.max_expansion`` times what it stores, and files
    whose datasets declare more than the memory available (``limits.memory_bytes``) can hold.
    Every dataset of the file counts, read or not.
    """
    _check_links(f, path, limits)
    names: list[bytes] = []

    def visit(name: bytes, info: Any) -> None:  # H5Ovisit: each object once, hard links only
        if info.type == h5py.h5o.TYPE_DATASET:
            names.append(name)

    h5py.h5o.visit(f.id, visit, info=True)
    sizes = {}  # name -> (declared bytes, stored bytes, shape, dtype)
    for raw_name in names:
        dsid = h5py.h5d.open(f.id, raw_name)
        name = raw_name.decode("utf-8", errors="replace")
        _check_layout(name, dsid, path)
        declared = int(np.prod(dsid.shape, dtype=object)) * int(dsid.dtype.itemsize)  # exact: no overflow
        sizes[name] = (declared, int(dsid.get_storage_size()), dsid.shape, dsid.dtype)
    total = sum(size[0] for size in sizes.values())
    budget = limits.memory_bytes if limits.memory_bytes is not None else available_memory()
    if sizes and 2 * total > budget:
        name, (declared, _, shape, dtype) = max(sizes.items(), key=lambda kv: kv[1][0])
        raise SpotError(
            f"dataset file '{path}': '{name}' declares shape {shape} of {dtype} ({_size(declared)}); "
            f"reading the file's arrays needs {_size(2 * total)} (twice their {_size(total)}) but "
            f"{_size(budget)} of memory is available; expected a file that fits in memory"
        )
    for name, (declared, stored, shape, dtype) in sizes.items():
        if declared > limits.expansion_floor and declared > limits.max_expansion * stored:
            raise SpotError(
                f"dataset file '{path}': '{name}' declares shape {shape} of {dtype} ({_size(declared)}) but "
                f"stores {_size(stored)} in the file; expected at most {limits.max_expansion:g} times its "
                "stored size (a compression bomb, or chunks never written)"
            )


def open_hdf5(path: Path, limits: ReadLimits | None = None) -> h5py.File:
    """Open ``path`` read-only and run :func:`check_hdf5` on it before anything else reads it."""
    if not path.exists():
        raise SpotError(f"dataset file '{path}' does not exist")
    if not path.is_file():
        raise SpotError(f"dataset file '{path}' is not a regular file; expected an hdf5 file")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise SpotError(f"dataset file '{path}' is not a readable hdf5 file ({err})") from None
    try:
        check_hdf5(f, path, limits or DEFAULT_LIMITS)
    except BaseException:
        f.close()
        raise
    return f


# --------------------------------------------------------------------------- what the readers take from it
def read_array(group: h5py.Group, key: str, path: Path, rank: int | None = None) -> np.ndarray:
    """A real numeric array ``group[key]`` (integers, floats or bools), or :class:`SpotError`
    naming file and key. The file has passed :func:`check_hdf5` (opened by :func:`open_hdf5`)."""
    where = f"{group.name.rstrip('/')}/{key}".lstrip("/")
    if key not in group:
        raise SpotError(f"dataset file '{path}': missing key '{where}'; found {sorted(group.keys())}")
    node = group[key]
    if not isinstance(node, h5py.Dataset):
        raise SpotError(f"dataset file '{path}': '{where}' is a group; expected an array")
    if node.dtype.kind not in "biuf":
        raise SpotError(
            f"dataset file '{path}': '{where}' has dtype {node.dtype}; expected numbers (real: integers, "
            "floats or bools)"
        )
    if rank is not None and node.ndim != rank:
        raise SpotError(f"dataset file '{path}': '{where}' has shape {node.shape}; expected rank {rank}")
    try:
        return node[()]
    except OSError as err:  # damaged chunks, a filter that fails
        raise SpotError(f"dataset file '{path}': '{where}' cannot be read ({err})") from None


def check_rows(group: h5py.Group, keys: list[str], path: Path) -> None:
    """The declared first dimension of every array ``keys`` present in ``group`` is the same
    (checked before reading: a file whose arrays disagree is refused without loading them)."""
    rows = {k: group[k].shape[0] for k in keys if isinstance(group.get(k), h5py.Dataset) and group[k].ndim >= 1}
    first = next(iter(rows.items()), None)
    for key, n in rows.items():
        if first is not None and n != first[1]:
            raise SpotError(
                f"dataset file '{path}': '{key}' has {n} rows but '{first[0]}' has {first[1]}; "
                "expected one row per step in every array"
            )


def as_flags(arr: np.ndarray, key: str, path: Path) -> np.ndarray:
    """A 0/1 flag array (terminals, timeouts, dones) as bool; any other value is an error (a 3.5
    would otherwise read as True)."""
    if arr.dtype != np.bool_:
        bad = np.flatnonzero((arr != 0) & (arr != 1))
        if bad.size:
            raise SpotError(
                f"dataset file '{path}': '{key}' has the value {arr[bad[0]].item()!r} at row {int(bad[0])} "
                f"({bad.size} rows not 0/1); expected flags 0 or 1"
            )
    return arr.astype(bool)
