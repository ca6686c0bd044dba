"""Count the programs JAX compiles: ``with compiles.counting() as c: ...``.

JAX reports every program it hands to XLA through :mod:`jax.monitoring`: the time span
``/jax/core/compile/backend_compile_duration`` (with the program's name, ``jit(chunk)``) wraps
each compilation, and a program found in the persistent compilation cache (:mod:`spot.runtime`)
records ``/jax/compilation_cache/cache_hits`` inside that span (a load instead of an XLA compile).
A program that jit finds in its in-memory cache reports nothing: it costs nothing.

So a :class:`Count` says how many programs a block needed, how many of them XLA compiled and how
many came from the persistent cache, by name; the sweep's trials log the first two as
``trial/compiles`` and ``trial/compile_cache_hits`` (docs/benchmarks.md). Only the thread that
opened the count is counted (a sweep trial's own thread, as :mod:`spot.phases` times it).
"""

from __future__ import annotations

import collections
import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"
CACHE_HIT = "/jax/compilation_cache/cache_hits"


@dataclass(eq=False)  # counts are told apart by identity (nested counts may be equal)
class Count:
    """Programs a block handed to XLA (``programs``: name -> how many), how many of them the
    persistent cache had (``cache_hits``) and the seconds of their spans (``seconds``)."""

    thread: int = field(default_factory=threading.get_ident)
    programs: collections.Counter = field(default_factory=collections.Counter)
    cache_hits: int = 0
    seconds: float = 0.0

    @property
    def total(self) -> int:
        """Programs compiled or loaded from the persistent cache."""
        return sum(self.programs.values())

    @property
    def compiled(self) -> int:
        """Programs XLA compiled (not found in the persistent cache)."""
        return self.total - self.cache_hits

    def named(self, name: str) -> int:
        """How many programs named ``name`` (``"chunk"`` or ``"jit(chunk)"``)."""
        return self.programs[name if name.startswith(("jit(", "pmap(")) else f"jit({name})"]

    def metrics(self, prefix: str = "trial/") -> dict[str, float]:
        """``{prefix}compiles`` and ``{prefix}compile_cache_hits``."""
        return {f"{prefix}compiles": float(self.total), f"{prefix}compile_cache_hits": float(self.cache_hits)}


_ACTIVE: list[Count] = []
_LOCK = threading.Lock()
_LISTENING = False


def _on_span(event: str, start: float, end: float, **kwargs: Any) -> None:
    if event != BACKEND_COMPILE or not _ACTIVE:
        return
    me = threading.get_ident()
    for c in list(_ACTIVE):
        if c.thread == me:
            c.programs[str(kwargs.get("fun_name", "?"))] += 1
            c.seconds += end - start


def _on_event(event: str, **_: Any) -> None:
    if event != CACHE_HIT or not _ACTIVE:
        return
    me = threading.get_ident()
    for c in list(_ACTIVE):
        if c.thread == me:
            c.cache_hits += 1


def _listen() -> None:
    global _LISTENING
    with _LOCK:
        if not _LISTENING:
            import jax.monitoring

            jax.monitoring.register_event_time_span_listener(_on_span)
            jax.monitoring.register_event_listener(_on_event)
            _LISTENING = True


@contextlib.contextmanager
def counting() -> Iterator[Count]:
    """Count the programs this thread hands to XLA until the block ends (counts may nest)."""
    _listen()
    count = Count()
    _ACTIVE.append(count)
    try:
        yield count
    finally:
        _ACTIVE.remove(count)
