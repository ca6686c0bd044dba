"""Code versions: a digest of the code a stage runs, for the stage cache's keys (:mod:`spot.cache`).

:func:`code_version` hashes the bytecode, constants and defaults of the stage function, the helpers
it calls and every spot module it uses, as loaded in this process, so editing a stage or a module it
uses retires its old entries without a hand-bumped number; comments and line numbers do not count,
and a file edited while a process runs does not change that process's keys (they name the code
that computed the entry). :data:`NOT_CODE` names the modules a key does not cover, and module
globals that hold process state (:func:`_state_names`) are left out.
"""

from __future__ import annotations

import dataclasses
import dis
import functools
import hashlib
import importlib
import sys
import types
from collections.abc import Callable, Iterator, Mapping
from typing import Any

PACKAGE = "spot"
# Modules (and packages, with every module under them) whose code a stage's key does not cover: the
# config only declares fields, and the values a stage reads are in its deps.
NOT_CODE = frozenset({"spot.config"})


def _const_repr(c: Any) -> str:
    """A process-independent repr of a code constant (frozensets sorted: their order follows string
    hashes, which differ between processes)."""
    if isinstance(c, (frozenset, set)):
        return "{" + ",".join(sorted(_const_repr(x) for x in c)) + "}"
    if isinstance(c, (tuple, list)):
        return "(" + ",".join(_const_repr(x) for x in c) + ")"
    if isinstance(c, dict):
        return "{" + ",".join(sorted(f"{_const_repr(k)}:{_const_repr(v)}" for k, v in c.items())) + "}"
    if isinstance(c, (int, float, complex, str, bytes, bool, type(None), type(Ellipsis))):
        return repr(c)
    target = _unwrap(c)  # a function, class or other object as a default value: by name, never by address
    name = getattr(target, "__qualname__", None) or type(target).__qualname__
    return f"<{getattr(target, '__module__', None) or type(target).__module__}.{name}>"


def _walk_code(co: types.CodeType) -> Iterator[types.CodeType]:
    yield co
    for c in co.co_consts:
        if isinstance(c, types.CodeType):
            yield from _walk_code(c)


def _hash_code(co: types.CodeType, h: Any) -> None:
    for c in _walk_code(co):
        h.update(c.co_code)
        h.update(repr(c.co_names).encode())
        h.update(repr([_const_repr(k) for k in c.co_consts if not isinstance(k, types.CodeType)]).encode())


def _imports_in(co: types.CodeType, package: str | None) -> set[str]:
    """Modules named by the ``import`` statements inside a function (``IMPORT_NAME``/``IMPORT_FROM``)."""
    out: set[str] = set()
    for c in _walk_code(co):
        current = None
        instructions = list(dis.get_instructions(c))
        for i, ins in enumerate(instructions):
            if ins.opname == "IMPORT_NAME":
                level = instructions[i - 2].argval if i >= 2 and instructions[i - 2].opname == "LOAD_CONST" else 0
                current = ins.argval
                if isinstance(level, int) and level > 0 and package:  # from .x import y
                    base = package.rsplit(".", level - 1)[0] if level > 1 else package
                    current = f"{base}.{current}" if current else base
                out.add(current)
            elif ins.opname == "IMPORT_FROM" and current is not None:
                out.add(f"{current}.{ins.argval}")
    return out


def _plain(value: Any) -> bool:
    """Data a definition may read as a constant: scalars, strings and containers of them."""
    if isinstance(value, (int, float, str, bytes, bool, type(None))):
        return True
    if isinstance(value, (tuple, list, frozenset, set)):
        return all(_plain(v) for v in value)
    if isinstance(value, dict):
        return all(_plain(k) and _plain(v) for k, v in value.items())
    return False


def _state_names(glb: Mapping[str, Any]) -> frozenset[str]:
    """Globals of a module that hold process state, not code: the names its functions assign with
    ``global`` (``STORE_GLOBAL``) and private mutable containers (``_seen: set = set()``). Their
    values change as a process runs (a reused Ray actor runs trial after trial), so they are left
    out of code versions."""
    name = glb.get("__name__")
    if name in _STATE_CACHE:
        return _STATE_CACHE[name]
    out = {k for k, v in glb.items() if k.startswith("_") and isinstance(v, (set, list, dict))}
    for value in list(glb.values()):
        target = _unwrap(value)
        if getattr(target, "__module__", None) != name:
            continue
        codes = [target.__code__] if hasattr(target, "__code__") else []
        if isinstance(target, type):
            codes += [_unwrap(v).__code__ for v in vars(target).values() if hasattr(_unwrap(v), "__code__")]
        for co in codes:
            for c in _walk_code(co):
                out.update(i.argval for i in dis.get_instructions(c) if i.opname in ("STORE_GLOBAL", "DELETE_GLOBAL"))
    result = frozenset(out)
    if isinstance(name, str):
        _STATE_CACHE[name] = result
    return result


_STATE_CACHE: dict[str, frozenset[str]] = {}


def _usable(value: Any) -> bool:
    """A global a definition's code may run: a module, a function or a class."""
    target = _unwrap(value)
    return isinstance(target, (types.ModuleType, type)) or hasattr(target, "__code__")


def _unwrap(obj: Any) -> Any:
    while True:
        if isinstance(obj, (staticmethod, classmethod)):
            obj = obj.__func__
        elif isinstance(obj, property):
            obj = obj.fget
        elif isinstance(obj, functools.partial):
            obj = obj.func
        elif hasattr(obj, "__wrapped__") and not isinstance(obj, type):
            obj = obj.__wrapped__
        else:
            return obj


class _Code:
    """Digests of the code a stage runs, as loaded in this process: functions by their bytecode,
    constants and defaults; modules by all the functions and classes they define."""

    def __init__(self, package: str) -> None:
        self.package = package
        self.parts: dict[str, str] = {}

    def _in_package(self, name: str) -> bool:
        outside = any(name == m or name.startswith(m + ".") for m in NOT_CODE)
        return (name == self.package or name.startswith(self.package + ".")) and not outside

    def _module_of_import(self, name: str) -> str | None:
        """The package module an import names (``a.b.c`` where ``c`` may be an attribute)."""
        for candidate in (name, name.rpartition(".")[0]):
            if candidate and self._in_package(candidate):
                try:
                    importlib.import_module(candidate)
                except ImportError:
                    continue
                return candidate
        return None

    def _function(self, fn: Any, h: Any, deps: list[Any]) -> None:
        fn = _unwrap(fn)
        code = getattr(fn, "__code__", None)
        if code is None:
            return
        _hash_code(code, h)
        h.update(_const_repr((fn.__defaults__ or ()) + tuple(sorted((fn.__kwdefaults__ or {}).items()))).encode())
        glb = getattr(fn, "__globals__", {})
        state = _state_names(glb)
        for c in _walk_code(code):
            for name in c.co_names:
                # Dunder globals (``__file__``, ``__name__``) say where the code is installed, not
                # what it does: hashed, two checkouts (or nodes sharing a store) would never share entries.
                if name in glb and name not in state and not (name.startswith("__") and name.endswith("__")):
                    value = glb[name]
                    if _plain(value):
                        h.update(f"{name}={_const_repr(value)}".encode())
                    elif _usable(value):
                        deps.append(value)
        deps.extend(sorted(_imports_in(code, glb.get("__package__"))))

    def _object(self, obj: Any, h: Any, deps: list[Any]) -> None:
        """A function or a class (its methods, class attributes and dataclass fields)."""
        obj = _unwrap(obj)
        if isinstance(obj, type):
            for name, value in sorted(vars(obj).items()):
                value = _unwrap(value)
                if hasattr(value, "__code__"):
                    h.update(name.encode())
                    self._function(value, h, deps)
                elif _plain(value) and not name.startswith("__"):
                    h.update(f"{name}={_const_repr(value)}".encode())
            if dataclasses.is_dataclass(obj):
                for f in dataclasses.fields(obj):
                    default = f.default if _plain(f.default) else type(f.default).__name__
                    h.update(f"field {f.name}={_const_repr(default)}".encode())
        else:
            self._function(obj, h, deps)

    def _follow(self, deps: list[Any]) -> None:
        for dep in deps:
            if isinstance(dep, str):
                module = self._module_of_import(dep)
                if module is not None:
                    self.add_module(module)
            elif isinstance(dep, types.ModuleType):
                if self._in_package(dep.__name__):
                    self.add_module(dep.__name__)
            else:
                module = getattr(_unwrap(dep), "__module__", None)
                if isinstance(module, str) and self._in_package(module):
                    self.add_module(module)

    def add_module(self, name: str) -> None:
        if name in self.parts or not self._in_package(name):
            return
        self.parts[name] = ""  # placeholder: import cycles end here
        module = importlib.import_module(name)
        h, deps = hashlib.sha256(), []
        state = _state_names(vars(module))
        for attr, value in sorted(vars(module).items()):
            if attr in state:
                continue
            target = _unwrap(value)
            if getattr(target, "__module__", None) == name and (
                isinstance(target, type) or hasattr(target, "__code__")
            ):
                h.update(attr.encode())
                self._object(target, h, deps)
            elif _plain(value) and not attr.startswith("__"):
                h.update(f"{attr}={_const_repr(value)}".encode())
            elif isinstance(value, types.ModuleType) and value.__name__.startswith(name + "."):
                continue  # a submodule: the import system sets it on its package, the package does not use it
            elif _usable(value):
                deps.append(value)
        self.parts[name] = h.hexdigest()
        self._follow(deps)

    def add_definition(self, module: str, name: str) -> None:
        """A module-level function or class, the definitions of its module it uses, and the
        package modules it uses (whole)."""
        ref = f"{module}:{name}"
        if ref in self.parts or module in self.parts:
            return
        self.parts[ref] = ""
        mod = importlib.import_module(module)
        obj = getattr(mod, name, None)
        if obj is None:
            raise ValueError(f"cannot find {name!r} in module {module!r}")
        h, deps = hashlib.sha256(), []
        self._object(obj, h, deps)
        self.parts[ref] = h.hexdigest()
        for dep in deps:
            target = _unwrap(dep) if not isinstance(dep, str) else dep
            own = getattr(target, "__module__", None) == module and getattr(target, "__name__", None) in vars(mod)
            if own and (isinstance(target, type) or hasattr(target, "__code__")):
                self.add_definition(module, target.__name__)
            else:
                self._follow([dep])


def code_parts(fn: Callable[..., Any], package: str = PACKAGE) -> dict[str, str]:
    """``name -> digest`` of the code a stage runs, as loaded in this process: the module-level
    function or class that defines ``fn`` (the enclosing stage function of a closure or lambda;
    the class of a callable instance), the functions and classes of its module that this uses, and
    every module of ``package`` those use or import, transitively (module-level and function-level
    imports; a module's digest covers every function and class it defines and its plain constants).
    Bytecode, constants and defaults count; line numbers and comments do not."""
    while isinstance(fn, functools.partial):
        fn = fn.func
    if not hasattr(fn, "__qualname__"):  # a callable instance: its class
        fn = type(fn)
    module, qualname = getattr(fn, "__module__", None), getattr(fn, "__qualname__", None)
    if not module or not qualname:
        raise ValueError(f"cannot find the code of {fn!r}; pass code= to cache.cached")
    code = _Code(package)
    code.add_definition(module, qualname.split(".<locals>.")[0].split(".")[0])
    return dict(sorted(code.parts.items()))


def code_version(fn: Callable[..., Any], package: str = PACKAGE) -> str:
    """SHA-256 (hex, 16 chars) over :func:`code_parts`; changes when any of that code changes."""
    h = hashlib.sha256(f"python {sys.version_info[:2]}".encode())
    for name, digest in code_parts(fn, package).items():
        h.update(f"{name}:{digest};".encode())
    return h.hexdigest()[:16]
