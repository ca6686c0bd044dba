"""Where a sweep trial's wall time goes: an exclusive phase clock.

A trial (:func:`spot.sweep.trial._trainable`) runs inside :func:`measure`; the code it calls marks
what it is doing with :func:`phase` (``with phases.phase("evaluate"): ...``). Phases nest, and the
clock is *exclusive*: time spent in an inner phase is charged to it, not to the phase around it,
so the phases of a trial add up to its wall time. Outside :func:`measure` (a ``spot run``, a
notebook, the tests) :func:`phase` does nothing. Only the thread that opened the clock is timed
(Tune runs a function trainable in a thread of its actor; MLflow's system-metrics thread and
other background threads are not charged).

The phases (:data:`PHASES`):

* ``startup``: before the trial function runs (measured by the trial, :func:`spot.sweep.trial._trainable`);
* ``data``: opening the trial's dataset;
* ``compile``: JAX tracing, lowering to StableHLO and XLA compilation, or loading the program from
  the persistent compilation cache. Measured with JAX's own monitoring events
  (:func:`jax.monitoring.register_event_time_span_listener` on
  ``/jax/core/compile/jaxpr_trace_duration``, ``.../jaxpr_to_mlir_module_duration`` and
  ``.../backend_compile_duration``; the last one wraps the persistent cache's lookup). The spans
  nest (a jitted function traced inside another's trace), so their union is counted, and the
  time is taken from the phase in which the compilation happened. The clock also counts the
  programs (``Clock.compiles``: one backend span each) and those loaded from the persistent cache
  (``Clock.cache_hits``: ``/jax/compilation_cache/cache_hits``), which a trial logs as
  ``trial/compiles`` and ``trial/compile_cache_hits`` (:mod:`spot.compiles` counts the same outside
  a trial);
* ``train``: the stages' own work (labels, reward model, relabelling, subgoals, CVAE, shaping, IQL
  updates), everything in a run not in another phase;
* ``evaluate``: policy evaluations in the environment;
* ``tracking``: calls to MLflow (:func:`timed_calls` wraps the client of every run);
* ``other``: the trial's own bookkeeping between runs.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator
from typing import Any

PHASES = ("startup", "data", "compile", "train", "evaluate", "tracking", "other")
COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",  # last: one per program (Clock.compiles)
)
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"


def _add_span(spans: list[list[float]], start: float, end: float) -> float:
    """Add ``[start, end]`` to the sorted disjoint ``spans`` (merged in place); return the time it
    adds to their union."""
    if end <= start:
        return 0.0
    covered = sum(max(0.0, min(end, b) - max(start, a)) for a, b in spans)
    keep = [s for s in spans if s[1] < start or s[0] > end]
    lo = min([start, *(a for a, b in spans if not (b < start or a > end))])
    hi = max([end, *(b for a, b in spans if not (b < start or a > end))])
    spans[:] = sorted([*keep, [lo, hi]])
    return (end - start) - covered


class Clock:
    """Seconds per phase of one thread's work; ``base`` is the phase outside any :func:`phase`."""

    def __init__(self, base: str = "other") -> None:
        if base not in PHASES:
            raise ValueError(f"phase {base!r}; expected one of {PHASES}")
        self.thread = threading.get_ident()
        self.totals = dict.fromkeys(PHASES, 0.0)
        self.stack = [base]
        self.start = self.since = time.perf_counter()
        self.read_wall = 0.0
        self.start_wall = time.time()
        self.spans: list[list[float]] = []  # compile spans (wall clock), merged
        self.compiles = 0  # programs handed to XLA (compiled, or loaded from the persistent cache)
        self.cache_hits = 0  # of which the persistent compilation cache had (spot.compiles)

    def _switch(self) -> float:
        now = time.perf_counter()
        self.totals[self.stack[-1]] += now - self.since
        self.since = now
        return now

    def push(self, name: str) -> None:
        if name not in PHASES:
            raise ValueError(f"phase {name!r}; expected one of {PHASES}")
        self._switch()
        self.stack.append(name)

    def pop(self) -> None:
        self._switch()
        self.stack.pop()

    def compiled(self, start: float, end: float) -> None:
        """A compilation ran from ``start`` to ``end`` (``time.time()``) in the current phase."""
        added = _add_span(self.spans, max(start, self.start_wall), end)
        self.totals["compile"] += added
        self.totals[self.stack[-1]] -= added

    def add(self, name: str, seconds: float) -> None:
        """Time measured elsewhere (the trial's start-up), added to ``name``."""
        self.totals[name] += seconds

    def read(self) -> dict[str, float]:
        """Seconds per phase so far; their sum is :attr:`read_wall` (the clock's wall time at this
        read, from ``perf_counter``) plus what :meth:`add` added."""
        self.read_wall = self._switch() - self.start
        return dict(self.totals)

    @property
    def wall(self) -> float:
        return time.perf_counter() - self.start


_ACTIVE: Clock | None = None
_LISTENING = False


def _on_span(event: str, start: float, end: float, **_: Any) -> None:
    clock = _ACTIVE
    if clock is not None and event in COMPILE_EVENTS and threading.get_ident() == clock.thread:
        clock.compiled(start, end)
        clock.compiles += event == COMPILE_EVENTS[-1]


def _on_event(event: str, **_: Any) -> None:
    clock = _ACTIVE
    if clock is not None and event == CACHE_HIT_EVENT and threading.get_ident() == clock.thread:
        clock.cache_hits += 1


def listen_to_compiles() -> None:
    """Register the compile-span and cache-hit listeners with ``jax.monitoring`` (once per process;
    imports jax)."""
    global _LISTENING
    if not _LISTENING:
        import jax.monitoring

        jax.monitoring.register_event_time_span_listener(_on_span)
        jax.monitoring.register_event_listener(_on_event)
        _LISTENING = True


@contextlib.contextmanager
def measure(base: str = "other") -> Iterator[Clock]:
    """Time this thread's work by phase until the block ends (one clock at a time per process)."""
    global _ACTIVE
    if _ACTIVE is not None:
        raise RuntimeError("a phase clock is already running in this process")
    _ACTIVE = clock = Clock(base)
    try:
        yield clock
    finally:
        clock.read()
        _ACTIVE = None


@contextlib.contextmanager
def phase(name: str) -> Iterator[None]:
    """Charge the block's time to phase ``name`` (a no-op outside :func:`measure` or on another thread)."""
    clock = _ACTIVE
    if clock is None or threading.get_ident() != clock.thread:
        yield
        return
    clock.push(name)
    try:
        yield
    finally:
        clock.pop()


class timed_calls:  # noqa: N801 - used like a function: timed_calls(client)
    """``obj`` whose method calls are charged to phase ``name`` (an MLflow client: ``tracking``)."""

    def __init__(self, obj: Any, name: str = "tracking") -> None:
        self._obj = obj
        self._name = name

    def __getattr__(self, attr: str) -> Any:
        value = getattr(self._obj, attr)
        if not callable(value):
            return value
        name = self._name

        def call(*args: Any, **kwargs: Any) -> Any:
            with phase(name):
                return value(*args, **kwargs)

        return call


# --------------------------------------------------------------------------- CPU of a process tree
def _tree_cpu(pid: int | None = None) -> dict[tuple[int, float], float]:
    """CPU seconds (user + system) of process ``pid`` (default: this one) and each live descendant,
    keyed by ``(pid, create time)``."""
    import psutil

    root = psutil.Process(pid)
    out = {}
    for proc in [root, *root.children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            t = proc.cpu_times()
            out[(proc.pid, proc.create_time())] = t.user + t.system
    return out


class CpuMeter:
    """``with CpuMeter() as m: ...``: the block's wall seconds (``m.wall_s``), the CPU seconds of
    this process and every descendant (``m.cpu_s``: the driver, Ray's processes and trial workers,
    the MLflow server) and their ratio to the cores this process may use (``m.util``, 1.0 = every
    core busy all the time).

    Processes end during a sweep (Ray's workers, and all of Ray at the end), and the CPU time of a
    process whose parent has gone is lost to ``wait()``; so the tree is sampled every ``interval``
    seconds and each process counts with its last sample (what a process used after its last
    sample, or a process shorter than ``interval``, is missed).
    """

    def __init__(self, interval: float = 1.0) -> None:
        self.interval = interval
        self.cpus = len(os.sched_getaffinity(0))
        self.wall_s = self.cpu_s = 0.0

    def _sample(self) -> None:
        with contextlib.suppress(Exception):  # psutil races with processes ending: skip a sample
            self._last.update(_tree_cpu())

    def _loop(self) -> None:
        while not self._stop.wait(self.interval):
            self._sample()

    def __enter__(self) -> CpuMeter:
        self._base = _tree_cpu()
        self._last = dict(self._base)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="spot-cpu-meter", daemon=True)
        self._t0 = time.perf_counter()
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()
        self.wall_s = time.perf_counter() - self._t0
        self.cpu_s = sum(v - self._base.get(k, 0.0) for k, v in self._last.items())

    @property
    def util(self) -> float:
        return self.cpu_s / max(self.wall_s * self.cpus, 1e-9)


def devices() -> str:
    """The devices JAX runs on, from ``jax.devices()``: ``cpu:cpu``, ``gpu:NVIDIA H100 80GB HBM3``,
    ``8x gpu:...`` (imports jax)."""
    import jax

    kinds = [f"{d.platform}:{getattr(d, 'device_kind', '')}" for d in jax.devices()]
    return ", ".join(f"{n}x {k}" if n > 1 else k for k, n in {k: kinds.count(k) for k in kinds}.items())
