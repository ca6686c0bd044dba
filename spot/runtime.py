"""Process settings spot needs, applied by one explicit call: :func:`configure`.

Importing ``spot`` changes nothing in the process. Entry points call :func:`configure` first,
before anything starts a jax backend or imports mujoco: the ``spot`` command (:func:`spot.cli.main`),
each sweep trial process, the test suite's ``conftest.py`` and library users who train in-process
(``import spot.runtime; spot.runtime.configure()``). It sets two environment variables:

* ``XLA_FLAGS`` gets :data:`YNN_FLAG` appended: jaxlib 0.10.2 on CPU crashes in transformer
  training at batch 256 with ``YNNPACK operation failed`` unless the YNN reduce fusion is off
  (docs/install.md). XLA reads the variable when the first backend starts, so a call after that
  raises :class:`RuntimeError` unless the flag is already set.
* ``MUJOCO_GL`` defaults to ``egl`` (headless rendering with Mesa's software driver; robosuite
  makes the same choice on Linux). MuJoCo reads it when first imported; a value already set is kept.

``SPOT_FAST_COMPILE=1`` appends :data:`FAST_COMPILE_FLAGS` to ``XLA_FLAGS``: XLA's backend
optimisations off, LLVM's expensive passes skipped, the CPU backend's older fusion emitters
instead of its MLIR-based ones, and each program's LLVM module compiled whole (not split for
parallel code generation, which a one-CPU trial cannot use). A tiny SPOT run's ~75 programs then
compile in about 14 s instead of 30 with the first two flags (cold cache, 2 CPU cores); the third
halves the XLA compile time of a tiny PT, HPL or IPL run again (PT 9.2 to 4.9 s) and the fourth
takes another fifth off (PT 4.7 to 3.7 s). The programs run slower (IQL at its default
sizes: 87 updates/s with the first three, 122 with the first two, 151 without any) and round differently,
so it is for smoke runs (a sweep file's
``fast_compile: true``), never for results; the flags are in every run's ``environment.json`` and
in the compilation cache's key. docs/benchmarks.md has the figures.

It also turns on JAX's persistent compilation cache (:func:`compilation_cache_settings`), so that
the trials of a sweep, the commands run one after another and the test suite's subprocesses
compile each program once per machine instead of once per process:

* ``JAX_COMPILATION_CACHE_DIR`` = ``$SPOT_CACHE_DIR/jax/jax-<jax version>`` (``SPOT_CACHE_DIR``
  defaults to ``~/.cache/spot/stages``, the stage cache's folder);
* ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` = :data:`MIN_COMPILE_S`, 0: every program
  (JAX's default, 1 s, would leave out most of a small run's programs, which compile in 0.05-1 s
  on CPU; a tiny SPOT run in a new process compiles ~75 programs, 2.5 s with all of them cached
  against 4.6 s with those under 0.2 s left out, docs/benchmarks.md);
* ``JAX_COMPILATION_CACHE_MAX_SIZE`` = :data:`MAX_SIZE_BYTES` (2 GiB): a bound on the folder
  (least recently used entries are deleted) and, as important, it makes jax read and write
  entries under a file lock (``filelock``, which Ray requires); without a bound jax writes an
  entry in place, unlocked, so a trial could read another's half-written entry.

jax reads them when it is imported; where jax is already imported, ``configure()`` sets them with
``jax.config.update`` as well. A value the user set (any of the three) is kept. ``SPOT_JAX_CACHE=0``
turns spot's setting off (jax's own default: no persistent cache unless ``JAX_COMPILATION_CACHE_DIR``
is set). The cache is safe to share: jax's key (``jax._src.cache_key.get`` in jax 0.10.2) hashes
the program (StableHLO), the jaxlib version, the backend's platform and platform version, the XLA
flags (``XLA_FLAGS`` minus dump/debug-only flags), the compile options and the device kind; the
jax version, which jax's key leaves out, is in the folder name.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from spot import SpotError

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_REDUCE"
FAST_COMPILE_SWITCH = "SPOT_FAST_COMPILE"
FAST_COMPILE_FLAGS = (
    "--xla_backend_optimization_level=0",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_parallel_codegen_split_count=1",
)
MUJOCO_GL_DEFAULT = "egl"
JAX_CACHE_SWITCH = "SPOT_JAX_CACHE"
MIN_COMPILE_S = "0"
MAX_SIZE_BYTES = str(2 * 1024**3)
_CACHE_VARS = {
    "JAX_COMPILATION_CACHE_DIR": ("jax_compilation_cache_dir", str),
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": ("jax_persistent_cache_min_compile_time_secs", float),
    "JAX_COMPILATION_CACHE_MAX_SIZE": ("jax_compilation_cache_max_size", int),
}


def cache_dir() -> Path:
    """The stage cache's folder: ``$SPOT_CACHE_DIR``, default ``~/.cache/spot/stages`` (:mod:`spot.cache`)."""
    return Path(os.environ.get("SPOT_CACHE_DIR", Path.home() / ".cache" / "spot" / "stages")).expanduser()


def data_dir() -> Path:
    """Built and fetched datasets: ``$SPOT_DATA_DIR``, default ``~/.cache/spot/data`` (:mod:`spot.data`)."""
    return Path(os.environ.get("SPOT_DATA_DIR", Path.home() / ".cache" / "spot" / "data")).expanduser()


def jax_cache_dir() -> Path:
    """``$SPOT_CACHE_DIR/jax/jax-<version>`` (``SPOT_CACHE_DIR`` defaults to ``~/.cache/spot/stages``)."""
    from importlib.metadata import version

    return cache_dir() / "jax" / f"jax-{version('jax')}"


def compilation_cache_settings() -> dict[str, str]:
    """The persistent-compilation-cache variables :func:`configure` sets (module docstring); empty
    when ``SPOT_JAX_CACHE`` is ``0``/``false``/``no``/``off``. Values the user set win."""
    if not _switch(JAX_CACHE_SWITCH, "1"):
        return {}
    defaults = {
        "JAX_COMPILATION_CACHE_DIR": str(jax_cache_dir()),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": MIN_COMPILE_S,
        "JAX_COMPILATION_CACHE_MAX_SIZE": MAX_SIZE_BYTES,
    }
    return {k: os.environ.get(k) or v for k, v in defaults.items()}


def _switch(name: str, default: str) -> bool:
    value = os.environ.get(name, default).strip().lower()
    if value in ("0", "false", "no", "off"):
        return False
    if value not in ("1", "true", "yes", "on"):
        raise SpotError(f"{name}={os.environ[name]!r}: expected 1 or 0 (on or off)")
    return True


def fast_compile() -> bool:
    """Whether ``SPOT_FAST_COMPILE`` asks for :data:`FAST_COMPILE_FLAGS` (module docstring)."""
    return _switch(FAST_COMPILE_SWITCH, "0")


def _jax_backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def configure() -> dict[str, str]:
    """Set ``XLA_FLAGS``, ``MUJOCO_GL`` and JAX's compilation cache for spot (see the module
    docstring); idempotent.

    Returns:
      The variables' values after the call (the cache's three only where it is on).

    Raises:
      SpotError: ``SPOT_JAX_CACHE`` or ``SPOT_FAST_COMPILE`` is neither on nor off.
      RuntimeError: the YNN flag (or a fast-compile flag asked for) is missing and a jax backend
        has already started (too late for the flag to take effect; call ``configure()`` earlier).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = [YNN_FLAG, *(FAST_COMPILE_FLAGS if fast_compile() else ())]
    missing = [f for f in wanted if f not in flags.split()]
    if missing:
        if _jax_backend_started():
            raise RuntimeError(
                "spot.runtime.configure() was called after a jax backend started; call it "
                "before any jax computation so that XLA_FLAGS takes effect"
            )
        os.environ["XLA_FLAGS"] = " ".join([flags, *missing]).strip()
    if "mujoco" not in sys.modules:
        os.environ.setdefault("MUJOCO_GL", MUJOCO_GL_DEFAULT)
    cache_vars = compilation_cache_settings()
    os.environ.update(cache_vars)
    if cache_vars and "jax" in sys.modules:  # jax read its config from the environment when imported
        import jax

        for var, (option, kind) in _CACHE_VARS.items():
            jax.config.update(option, kind(cache_vars[var]))
    return {"XLA_FLAGS": os.environ["XLA_FLAGS"], "MUJOCO_GL": os.environ.get("MUJOCO_GL", ""), **cache_vars}


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` may still run on this host: False only when no such process exists.
    Another user's process (``PermissionError``) and a number that is not a pid here (too large)
    count as alive, so that whoever asks leaves their files and runs alone."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def exit_interrupted(code: int) -> None:
    """End the process after Ctrl-C or SIGTERM without tearing down jax's backend under a compile.

    A KeyboardInterrupt can reach the main thread while XLA still compiles a program on one of its
    own threads (jaxlib 0.10.2 lets the wait for a compile be interrupted). Python's exit then runs
    jax's ``atexit`` hook (``jax._src.api.clean_up``), which destroys the CPU client, and the compile
    thread goes on to use it: a segmentation fault (exit -11) after ``interrupted`` was printed, in
    about 1 of 3 runs stopped mid-training. Here every other ``atexit`` hook runs (MLflow's,
    logging's), the standard streams are flushed, and the process ends with ``os._exit(code)``, so
    neither jax's hook nor the interpreter's teardown runs. Only for the ``spot`` command's own
    process (:func:`spot.cli.main` called with no arguments), never for in-process callers."""
    import atexit

    api = sys.modules.get("jax._src.api")
    if api is not None and hasattr(api, "clean_up"):
        atexit.unregister(api.clean_up)
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe or stream: nothing left to write to
                pass
        os._exit(code)


def resend_swallowed_signal(name: str, signal_of: Callable[[Any], int | None]) -> None:
    """Make a signal whose handler raised inside a garbage-collector callback take effect.

    Python runs signal handlers in the main thread between bytecodes, also inside a callback the
    garbage collector calls (jax's ``_xla_gc_callback``, a ``WeakSet``'s ``_remove``). An exception
    raised there cannot propagate: Python prints ``Exception ignored in: ...`` and the process goes
    on. This :data:`sys.unraisablehook` asks ``signal_of`` which signal raised such an exception
    (None: not one of ours), prints nothing and sends that signal again 50 ms later, outside the
    callback; anything else goes to the hook that was there. Set once per process and ``name``."""
    import threading

    previous = sys.unraisablehook
    names = getattr(previous, "spot_resends", ())
    if name in names:
        return

    def hook(unraisable: Any) -> None:
        signum = signal_of(unraisable)
        if signum is None:
            previous(unraisable)
            return
        timer = threading.Timer(0.05, os.kill, (os.getpid(), signum))
        timer.daemon = True
        timer.start()

    hook.spot_resends = (*names, name)  # type: ignore[attr-defined]
    sys.unraisablehook = hook


def _interrupt_signal(unraisable: Any) -> int | None:
    """SIGTERM for the KeyboardInterrupt :func:`spot.cli.run`'s handler raises (``signal SIGTERM``),
    SIGINT for Ctrl-C's, None for anything else."""
    import signal

    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        return None
    return signal.SIGTERM if str(unraisable.exc_value) == "signal SIGTERM" else signal.SIGINT


def redeliver_swallowed_interrupts() -> None:
    """A Ctrl-C or SIGTERM that lands inside a garbage-collector callback still stops the command
    (:func:`resend_swallowed_signal`): without this the KeyboardInterrupt was swallowed and the
    command went on to finish with exit 0 (seen in 1 of 14 runs stopped in their first seconds).
    Set by the ``spot`` command's own process only."""
    resend_swallowed_signal("interrupts", _interrupt_signal)
