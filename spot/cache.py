"""Content-addressed stage cache, stored as data only.

Each pipeline stage's output is stored under a key hashed from everything it depends on (the
dataset's fingerprint, labels, its config section, the seed) and from the code the stage runs
(:func:`spot.codeversion.code_version`: the bytecode, constants and defaults of the stage function,
the helpers it calls and every spot module it uses, as loaded in this process), so editing a stage
or a module it uses retires its old entries without a hand-bumped number; comments and line
numbers do not count, and a file edited while a process runs does not change that process's keys
(they name the code that computed the entry). A run that changes only the shaping weight therefore
reuses the reward model and the CVAE of an earlier run.

Entries hold data only and reading one never runs code from it. An entry is one ``.npz`` file (read
with ``allow_pickle=False``): the output's numpy arrays plus a JSON description of the tree around
them (dicts, lists, tuples, numbers, strings, None, and NamedTuples or dataclasses *defined in
spot* by qualified name, rebuilt from their fields) and a SHA-256 digest of both. An entry that is
truncated, compressed, fails its digest, holds a pickle or an object array, declares an array
larger than its bytes, nests deeper than :data:`MAX_DEPTH` (counted before parsing, never left to
a RecursionError), names a type outside spot or one that no longer exists, or fails to rebuild for
any other reason is reported, deleted and recomputed once, never used. Entries of the older pickle
format (``<key>.pkl``) are never opened.

Entries are read and written through the store (:mod:`spot.store`): ``<store>/stages/<key>.npz``
when ``$SPOT_STORE`` names one (a shared folder or ``s3://bucket/prefix``), else the cache dir
``$SPOT_CACHE_DIR`` (default ``~/.cache/spot/stages``; a file or a read-only folder there is one
SpotError naming the variable). Writes are atomic (a temporary name renamed into place; one PUT on
S3; a full disk is one SpotError and leaves no temporary file). :func:`cached` computes a missing
entry under the store's lock on its key, so trials that need the same entry at the same time, on
one machine or on several, compute it once: the others wait for the lock and then read the entry.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import io
import json
import re
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from spot import runtime
from spot.codeversion import PACKAGE, code_version
from spot.codeversion import code_parts as code_parts  # re-exported beside code_version for callers

FORMAT = 2  # the entry format; part of every key (format 1 was pickles)
MAX_DEPTH = 64  # nesting of a stored tree (a run's networks and histories: under 10)


class EntryError(ValueError):
    """A stage-cache entry that cannot be used (corrupt, foreign or of the wrong structure)."""


def cache_dir() -> Path:
    """The stage cache's folder (defined in :mod:`spot.runtime`, which sets JAX's cache beneath it)."""
    return runtime.cache_dir()


# --------------------------------------------------------------------------- keys
def _canonical(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            "__type__": type(obj).__qualname__,
            **{f.name: _canonical(getattr(obj, f.name)) for f in dataclasses.fields(obj)},
        }
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return {
            "sha256": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(),
            "shape": list(obj.shape),
            "dtype": str(obj.dtype),
        }
    if isinstance(obj, (np.integer, np.floating, np.bool_)):
        return obj.item()
    return obj


def key(stage: str, deps: Mapping[str, Any], code: str) -> str:
    """Hash of the stage name, its code version (:func:`code_version`) and its dependencies.

    Under ``SPOT_FAST_COMPILE`` (:mod:`spot.runtime`: XLA's optimisations off, which rounds
    differently) the key also says so: a smoke run's entries never stand in for a normal run's.
    """
    fields = {"stage": stage, "format": FORMAT, "code": code, "deps": _canonical(deps)}
    if runtime.fast_compile():
        fields["xla"] = "fast_compile"  # only then: every other key stays what it was
    payload = json.dumps(fields, sort_keys=True, default=str)
    return f"{stage}-{hashlib.sha256(payload.encode()).hexdigest()[:20]}"


# --------------------------------------------------------------------------- entry format
def _type_ref(cls: type) -> str:
    if "<locals>" in cls.__qualname__:
        raise TypeError(f"stage cache: cannot store an instance of local class {cls.__qualname__}")
    return f"{cls.__module__}:{cls.__qualname__}"


def encode(value: Any) -> tuple[Any, dict[str, np.ndarray]]:
    """``(tree, arrays)``: a JSON-able description of ``value`` and its arrays, named ``a0, a1, ...``."""
    arrays: dict[str, np.ndarray] = {}

    def array(x: np.ndarray, kind: str) -> dict[str, Any]:
        if x.dtype.hasobject or x.dtype.kind not in "biufc":
            raise TypeError(f"stage cache: cannot store an array of dtype {x.dtype}")
        name = f"a{len(arrays)}"
        arrays[name] = np.ascontiguousarray(x)
        return {"t": kind, "ref": name}

    def enc(x: Any) -> Any:
        if x is None:
            return {"t": "none"}
        if isinstance(x, np.generic):
            return array(np.asarray(x), "scalar")
        if isinstance(x, bool):
            return {"t": "bool", "v": x}
        if isinstance(x, int):
            return {"t": "int", "v": int(x)}
        if isinstance(x, float):
            return {"t": "float", "v": float(x)}
        if isinstance(x, str):
            return {"t": "str", "v": x}
        if isinstance(x, np.ndarray):
            return array(x, "array")
        if isinstance(x, tuple) and hasattr(type(x), "_fields"):
            return {"t": "namedtuple", "type": _type_ref(type(x)), "v": [enc(v) for v in x]}
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            names = [f.name for f in dataclasses.fields(x)]
            return {"t": "dataclass", "type": _type_ref(type(x)), "k": names, "v": [enc(getattr(x, n)) for n in names]}
        if isinstance(x, (list, tuple)):
            return {"t": type(x).__name__ if type(x) in (list, tuple) else "list", "v": [enc(v) for v in x]}
        if isinstance(x, Mapping):
            keys = list(x)
            if not all(isinstance(k, (str, int)) and not isinstance(k, bool) for k in keys):
                raise TypeError(f"stage cache: dict keys must be str or int, got {keys[:5]}")
            return {"t": "dict", "k": keys, "v": [enc(x[k]) for k in keys]}
        if hasattr(x, "__array__"):
            return array(np.asarray(x), "array")
        raise TypeError(f"stage cache: cannot store a {type(x).__module__}.{type(x).__qualname__}")

    return enc(value), arrays


def _resolve_type(ref: Any, package: str) -> type:
    if not isinstance(ref, str) or ref.count(":") != 1:
        raise EntryError(f"bad type reference {ref!r}")
    module, qualname = ref.split(":")
    if not (module == package or module.startswith(package + ".")) or "<" in qualname:
        raise EntryError(f"type {ref!r} is not a {package} type")
    if not all(p.isidentifier() and p != "__main__" for p in module.split(".") + qualname.split(".")):
        raise EntryError(f"bad type reference {ref!r}")
    try:
        obj: Any = importlib.import_module(module)
    except Exception as e:  # noqa: BLE001 - a module that is gone (renamed since) or fails to import
        raise EntryError(f"type {ref!r}: cannot import {module} ({type(e).__name__})") from None
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
    if not isinstance(obj, type):
        raise EntryError(f"type {ref!r} does not exist")
    return obj


def decode(tree: Any, arrays: Mapping[str, np.ndarray], package: str = PACKAGE) -> Any:
    """Inverse of :func:`encode`; raises :class:`EntryError` on anything it did not write (a tree
    nested deeper than :data:`MAX_DEPTH` included), whatever goes wrong in rebuilding it."""

    def dec(node: Any, depth: int = 0) -> Any:
        if depth > MAX_DEPTH:
            raise EntryError(f"the tree is nested deeper than {MAX_DEPTH} levels")
        if not isinstance(node, dict) or not isinstance(node.get("t"), str):
            raise EntryError(f"bad node {str(node)[:80]}")
        t = node["t"]
        if t == "none":
            return None
        if t in ("bool", "int", "float", "str"):
            v = node.get("v")
            kinds = {"bool": (bool,), "int": (int,), "float": (float, int), "str": (str,)}[t]
            if not isinstance(v, kinds) or (t == "int" and isinstance(v, bool)):
                raise EntryError(f"bad {t} value {v!r}")
            return float(v) if t == "float" else v
        if t in ("array", "scalar"):
            ref = node.get("ref")
            if not isinstance(ref, str) or ref not in arrays:
                raise EntryError(f"missing array {ref!r}")
            return arrays[ref][()] if t == "scalar" else arrays[ref]
        items = node.get("v")
        if not isinstance(items, list):
            raise EntryError(f"bad {t} node")
        values = [dec(v, depth + 1) for v in items]
        if t == "list":
            return values
        if t == "tuple":
            return tuple(values)
        if t == "dict":
            keys = node.get("k")
            if not isinstance(keys, list) or len(keys) != len(values):
                raise EntryError("bad dict node")
            return dict(zip(keys, values, strict=True))
        if t == "namedtuple":
            cls = _resolve_type(node.get("type"), package)
            if not (issubclass(cls, tuple) and len(getattr(cls, "_fields", ())) == len(values)):
                raise EntryError(f"{node['type']} is not a NamedTuple of {len(values)} fields")
            return cls(*values)
        if t == "dataclass":
            cls = _resolve_type(node.get("type"), package)
            names = node.get("k")
            if not dataclasses.is_dataclass(cls) or names != [f.name for f in dataclasses.fields(cls)]:
                raise EntryError(f"{node['type']} is not a dataclass with fields {names}")
            return cls(**dict(zip(names, values, strict=True)))
        raise EntryError(f"unknown node type {t!r}")

    try:
        return dec(tree)
    except EntryError:
        raise
    except Exception as e:  # noqa: BLE001 - a stored type's constructor may raise anything
        raise EntryError(f"cannot rebuild the stored value ({type(e).__name__}: {str(e)[:200]})") from None


def _digest(tree_bytes: bytes, arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256(tree_bytes)
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"|{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def entry_bytes(value: Any) -> bytes:
    """``value`` as the bytes of an entry (an ``.npz``)."""
    tree, arrays = encode(value)  # jax arrays are copied to host numpy arrays
    tree_bytes = json.dumps(tree).encode()
    meta = {
        "__tree__": np.frombuffer(tree_bytes, np.uint8),
        "__digest__": np.frombuffer(_digest(tree_bytes, arrays).encode(), np.uint8),
    }
    buf = io.BytesIO()
    np.savez(buf, **meta, **arrays)
    return buf.getvalue()


def write_entry(path: Path, value: Any) -> None:
    """Write ``value`` to ``path`` (``.npz``) atomically: a temporary file, then a rename (a full
    disk: SpotError, no temporary file left)."""
    from spot import store as store_lib

    store_lib.write_atomic(path, entry_bytes(value))


def _check_members(data: bytes) -> None:
    """EntryError unless every member of the entry's zip is stored uncompressed (as :func:`entry_bytes`
    writes them) and declares an array no larger than the bytes it holds: reading an entry never
    allocates more than the entry's size."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            if info.compress_type != zipfile.ZIP_STORED or info.file_size > len(data):
                raise EntryError(f"member {info.filename!r} is compressed or larger than the entry")
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version not in ((1, 0), (2, 0)):
                    raise EntryError(f"member {info.filename!r}: .npy format {version}")
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(fh)
                if dtype.hasobject or int(np.prod(shape, dtype=object)) * dtype.itemsize > info.file_size:
                    raise EntryError(f"member {info.filename!r} declares {dtype}{list(shape)}, more than it holds")


def _json_depth(text: bytes, limit: int) -> None:
    """EntryError if the JSON ``text`` nests deeper than ``limit`` (counted before parsing it: its
    strings blanked, then the running count of open brackets)."""
    code = np.frombuffer(re.sub(rb'"(?:[^"\\]|\\.)*"', b'""', text), np.uint8)
    step = np.isin(code, (ord("["), ord("{"))).astype(np.int64) - np.isin(code, (ord("]"), ord("}")))
    if step.size and int(np.cumsum(step).max()) > limit:
        raise EntryError(f"the tree is nested deeper than {MAX_DEPTH} levels")


def read_entry_bytes(data: bytes, package: str = PACKAGE) -> Any:
    """The value an entry's bytes hold; :class:`EntryError` if they cannot be used, for any reason
    (truncated, compressed, oversized, a pickle, a bad digest, tree or type). Never unpickles."""
    try:
        _check_members(data)
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except EntryError:
        raise
    except Exception as e:  # noqa: BLE001 - a truncated zip, a pickle, an object array: all unusable
        raise EntryError(f"not a readable entry ({type(e).__name__}: {str(e)[:200]})") from None
    tree_bytes = arrays.pop("__tree__", np.zeros(0, np.uint8)).tobytes()
    digest = arrays.pop("__digest__", np.zeros(0, np.uint8)).tobytes().decode("ascii", "replace")
    if not tree_bytes or digest != _digest(tree_bytes, arrays):
        raise EntryError("checksum mismatch")
    _json_depth(tree_bytes, 2 * MAX_DEPTH + 2)  # a node is an object holding a list of nodes
    try:
        tree = json.loads(tree_bytes)
    except (ValueError, RecursionError) as e:
        raise EntryError(f"bad tree description ({type(e).__name__}: {str(e)[:200]})") from None
    return decode(tree, arrays, package)


def read_entry(path: Path, package: str = PACKAGE) -> Any:
    """The value stored at ``path``; :class:`EntryError` if the entry cannot be used. Never unpickles."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise EntryError(f"not a readable entry ({type(e).__name__}: {e})") from None
    return read_entry_bytes(data, package)


# --------------------------------------------------------------------------- the cache
def _store() -> Any:
    from spot import store as store_lib

    return store_lib.stages(cache_dir())


def entry_path(k: str) -> Path:
    """The local file of entry ``k`` in the cache dir (the default store)."""
    return cache_dir() / f"{k}.npz"


def load(k: str) -> tuple[bool, Any]:
    """``(found, value)`` of entry ``k``; an unusable entry is reported, deleted and not found."""
    st = _store()
    name = f"{k}.npz"
    data = st.get_bytes(name)
    if data is None:
        return False, None
    try:
        return True, read_entry_bytes(data)
    except EntryError as e:
        warnings.warn(
            f"stage cache entry {st.describe(name)} is unusable ({e}); deleting and recomputing it", stacklevel=2
        )
        st.delete(name)
        return False, None


def store(k: str, value: Any) -> None:
    _store().put_bytes(f"{k}.npz", entry_bytes(value))


def cached(
    stage: str, deps: Mapping[str, Any], compute: Callable[[], Any], code: str | None = None
) -> tuple[Any, bool, str]:
    """``(value, hit, key)``: the cached value for ``deps``, or ``compute()`` stored under it.

    A miss is computed under the store's lock on the key: a process that finds the lock held
    waits, then reads the entry the holder stored (a hit). ``code`` is the stage's code version;
    by default :func:`code_version` of ``compute`` (the code of the stage function that defines it
    and of what that runs).
    """
    k = key(stage, deps, code if code is not None else code_version(compute))
    found, value = load(k)
    if found:
        return value, True, k
    with _store().lock(k):
        found, value = load(k)  # computed by another process while this one waited
        if found:
            return value, True, k
        value = compute()
        store(k, value)
    return value, False, k
