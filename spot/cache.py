"""Content-addressed stage cache, stored as data only.

Each pipeline stage's output is stored under a key hashed from everything it depends on (the
dataset's fingerprint, labels, its config section, the seed) and from the *source* of the code the
stage runs (:func:`code_version`), so editing a stage or a module it uses retires its old entries
without a hand-bumped number. A run that changes only the shaping weight therefore reuses the
reward model and the CVAE of an earlier run.

Entries hold data only and reading one never runs code from it. An entry is one ``.npz`` file (read
with ``allow_pickle=False``): the output's numpy arrays plus a JSON description of the tree around
them (dicts, lists, tuples, numbers, strings, None, and NamedTuples or dataclasses *defined in
spot* by qualified name, rebuilt from their fields) and a SHA-256 digest of both. An entry that is
truncated, fails its digest, holds a pickle or an object array, names a type outside spot or
has any other wrong structure is reported, deleted and recomputed, never used. Entries of the
older pickle format (``<key>.pkl``) are never opened. Writes go to a temporary name and are
renamed into place. The cache dir is ``$SPOT_CACHE_DIR`` (default ``~/.cache/spot/stages``).
"""

from __future__ import annotations

import ast
import dataclasses
import hashlib
import importlib
import importlib.util
import io
import json
import os
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = 2  # the entry format; part of every key (format 1 was pickles)
PACKAGE = "spot"
# Modules whose code a stage's key does not cover: the config only declares fields, and the values
# a stage reads are in its deps.
NOT_CODE = frozenset({"spot.config"})


class EntryError(ValueError):
    """A stage-cache entry that cannot be used (corrupt, foreign or of the wrong structure)."""


def cache_dir() -> Path:
    return Path(os.environ.get("SPOT_CACHE_DIR", Path.home() / ".cache" / "spot" / "stages")).expanduser()


# --------------------------------------------------------------------------- code versions
def _module_path(name: str) -> Path | None:
    """The ``.py`` file of module ``name`` of an installed package, found without importing it."""
    top, *rest = name.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    base = Path(spec.origin).parent if spec.submodule_search_locations else None
    if not rest:
        return Path(spec.origin)
    if base is None:
        return None
    for path in (base.joinpath(*rest).with_suffix(".py"), base.joinpath(*rest, "__init__.py")):
        if path.is_file():
            return path
    return None


class _Sources:
    """The source text of a function and of everything it runs inside ``package``."""

    def __init__(self, package: str) -> None:
        self.package = package
        self.texts: dict[str, str] = {}
        self._parsed: dict[Path, tuple[str, ast.Module]] = {}

    def _parse(self, path: Path) -> tuple[str, ast.Module]:
        if path not in self._parsed:
            text = path.read_text()
            self._parsed[path] = (text, ast.parse(text))
        return self._parsed[path]

    def _in_package(self, name: str) -> bool:
        return (name == self.package or name.startswith(self.package + ".")) and name not in NOT_CODE

    def _imported_modules(self, tree: ast.AST, module: str, is_pkg: bool) -> set[str]:
        """Package modules named by every ``import`` in ``tree`` (module- or function-level)."""
        out: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = module.split(".")
                    parts = parts[: len(parts) - node.level + (1 if is_pkg else 0)]
                    base = ".".join(parts + ([base] if base else []))
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    out.add(sub if _module_path(sub) is not None else base)
        return {m for m in out if self._in_package(m)}

    def add_module(self, name: str) -> None:
        if name in self.texts or not self._in_package(name):
            return
        path = _module_path(name)
        if path is None:
            return
        text, tree = self._parse(path)
        self.texts[name] = text
        for m in sorted(self._imported_modules(tree, name, path.name == "__init__.py")):
            self.add_module(m)

    def add_function(self, module: str, qualname: str) -> None:
        ref = f"{module}:{qualname}"
        if ref in self.texts or module in self.texts:
            return
        path = _module_path(module)
        if path is None:
            raise ValueError(f"cannot find the source of module {module!r}")
        text, tree = self._parse(path)
        node = _find_def(tree, qualname)
        if node is None:
            raise ValueError(f"cannot find {qualname!r} in {path}")
        self.texts[ref] = "\n".join(text.splitlines()[node.lineno - 1: node.end_lineno])
        is_pkg = path.name == "__init__.py"
        for m in sorted(self._imported_modules(node, module, is_pkg)):
            self.add_module(m)
        top_defs = {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}
        imported = _module_level_imports(tree, module, is_pkg)
        for name in sorted(_names_run(node)):
            if name in top_defs and name != qualname.split(".")[0]:
                self.add_function(module, name)
            elif name in imported:
                target_module, target_name = imported[name]
                if target_name is None or _module_path(f"{target_module}.{target_name}") is not None:
                    self.add_module(target_module if target_name is None else f"{target_module}.{target_name}")
                elif self._in_package(target_module):
                    self.add_module(target_module)


def _names_run(node: ast.AST) -> set[str]:
    """Names a definition's body refers to; annotations (types, not code that runs) are left out."""
    body = node.body if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) else [node]
    out: set[str] = set()
    for stmt in body:
        for n in ast.walk(stmt):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for a in (*n.args.posonlyargs, *n.args.args, *n.args.kwonlyargs, n.args.vararg, n.args.kwarg):
                    if a is not None:
                        a.annotation = None
                n.returns = None
            elif isinstance(n, ast.AnnAssign) and n.value is None:
                n.annotation = ast.Constant(None)
    for stmt in body:
        out.update(n.id for n in ast.walk(stmt) if isinstance(n, ast.Name))
    return out


def _find_def(tree: ast.AST, qualname: str) -> ast.AST | None:
    body = tree.body  # type: ignore[attr-defined]
    node = None
    for part in qualname.split("."):
        node = next((n for n in body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                     and n.name == part), None)
        if node is None:
            return None
        body = node.body
    return node


def _module_level_imports(tree: ast.Module, module: str, is_pkg: bool) -> dict[str, tuple[str, str | None]]:
    """``local name -> (module, imported name or None)`` of the module's top-level imports."""
    out: dict[str, tuple[str, str | None]] = {}
    for node in tree.body:
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = (a.name if a.asname else a.name.split(".")[0], None)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".")
                parts = parts[: len(parts) - node.level + (1 if is_pkg else 0)]
                base = ".".join(parts + ([base] if base else []))
            for a in node.names:
                out[a.asname or a.name] = (base, a.name)
    return out


def code_sources(fn: Callable[..., Any], package: str = PACKAGE) -> dict[str, str]:
    """``name -> source`` of what a stage runs: the module-level function or class that defines
    ``fn`` (the enclosing stage function of a closure or lambda), the module-level functions and
    classes of its module that this calls by name, and every module
    of ``package`` those import, transitively (module- and function-level imports). Read from the
    files on disk, so an edit counts without a reload."""
    while hasattr(fn, "func"):  # functools.partial
        fn = fn.func
    if not hasattr(fn, "__qualname__"):  # a callable instance: its class
        fn = type(fn)
    module, qualname = getattr(fn, "__module__", None), getattr(fn, "__qualname__", None)
    if not module or not qualname:
        raise ValueError(f"cannot find the source of {fn!r}; pass code= to cache.cached")
    outer = qualname.split(".<locals>.")[0].split(".")[0]  # the module-level def or class around fn
    sources = _Sources(package)
    sources.add_function(module, outer)
    return dict(sorted(sources.texts.items()))


def code_version(fn: Callable[..., Any], package: str = PACKAGE) -> str:
    """SHA-256 (hex, 16 chars) of :func:`code_sources`; changes when any of that source changes."""
    h = hashlib.sha256()
    for name, text in code_sources(fn, package).items():
        h.update(f"{len(name)}:{name}{len(text)}:".encode())
        h.update(text.encode())
    return h.hexdigest()[:16]


# --------------------------------------------------------------------------- keys
def _canonical(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__type__": type(obj).__qualname__,
                **{f.name: _canonical(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return {"sha256": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(),
                "shape": list(obj.shape), "dtype": str(obj.dtype)}
    if isinstance(obj, (np.integer, np.floating, np.bool_)):
        return obj.item()
    return obj


def key(stage: str, deps: Mapping[str, Any], code: str) -> str:
    """Hash of the stage name, its code version (:func:`code_version`) and its dependencies."""
    payload = json.dumps({"stage": stage, "format": FORMAT, "code": code, "deps": _canonical(deps)},
                         sort_keys=True, default=str)
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
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
    if not isinstance(obj, type):
        raise EntryError(f"type {ref!r} does not exist")
    return obj


def decode(tree: Any, arrays: Mapping[str, np.ndarray], package: str = PACKAGE) -> Any:
    """Inverse of :func:`encode`; raises :class:`EntryError` on anything it did not write."""

    def dec(node: Any) -> Any:
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
        values = [dec(v) for v in items]
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
    except (TypeError, ValueError, KeyError) as e:
        if isinstance(e, EntryError):
            raise
        raise EntryError(f"cannot rebuild the stored value ({type(e).__name__}: {e})") from None


def _digest(tree_bytes: bytes, arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256(tree_bytes)
    for name in sorted(arrays):
        a = arrays[name]
        h.update(f"|{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def write_entry(path: Path, value: Any) -> None:
    """Write ``value`` to ``path`` (``.npz``) atomically: a temporary file, then a rename."""
    tree, arrays = encode(value)  # jax arrays are copied to host numpy arrays
    tree_bytes = json.dumps(tree).encode()
    meta = {"__tree__": np.frombuffer(tree_bytes, np.uint8),
            "__digest__": np.frombuffer(_digest(tree_bytes, arrays).encode(), np.uint8)}
    buf = io.BytesIO()
    np.savez(buf, **meta, **arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, path)


def read_entry(path: Path, package: str = PACKAGE) -> Any:
    """The value stored at ``path``; :class:`EntryError` if the entry cannot be used. Never unpickles."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except Exception as e:  # noqa: BLE001 - a truncated zip, a pickle, an object array: all unusable
        raise EntryError(f"not a readable entry ({type(e).__name__}: {e})") from None
    tree_bytes = arrays.pop("__tree__", np.zeros(0, np.uint8)).tobytes()
    digest = arrays.pop("__digest__", np.zeros(0, np.uint8)).tobytes().decode("ascii", "replace")
    if not tree_bytes or digest != _digest(tree_bytes, arrays):
        raise EntryError("checksum mismatch")
    try:
        tree = json.loads(tree_bytes)
    except ValueError as e:
        raise EntryError(f"bad tree description ({e})") from None
    return decode(tree, arrays, package)


# --------------------------------------------------------------------------- the cache
def entry_path(k: str) -> Path:
    return cache_dir() / f"{k}.npz"


def load(k: str) -> tuple[bool, Any]:
    """``(found, value)`` of entry ``k``; an unusable entry is reported, deleted and not found."""
    path = entry_path(k)
    if not path.exists():
        return False, None
    try:
        return True, read_entry(path)
    except EntryError as e:
        warnings.warn(f"stage cache entry {path} is unusable ({e}); deleting and recomputing it", stacklevel=2)
        path.unlink(missing_ok=True)
        return False, None


def store(k: str, value: Any) -> None:
    write_entry(entry_path(k), value)


def cached(stage: str, deps: Mapping[str, Any], compute: Callable[[], Any],
           code: str | None = None) -> tuple[Any, bool, str]:
    """``(value, hit, key)``: the cached value for ``deps``, or ``compute()`` stored under it.

    ``code`` is the stage's code version; by default :func:`code_version` of ``compute`` (the
    source of the stage function that defines it and of what that runs).
    """
    k = key(stage, deps, code if code is not None else code_version(compute))
    found, value = load(k)
    if found:
        return value, True, k
    value = compute()
    store(k, value)
    return value, False, k

