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

It also turns on JAX's persistent compilation cache (:func:`compilation_cache_settings`), so that
the trials of a sweep, the commands run one after another and the test suite's subprocesses
compile each program once per machine instead of once per process:

* ``JAX_COMPILATION_CACHE_DIR`` = ``$SPOT_CACHE_DIR/jax/jax-<jax version>`` (``SPOT_CACHE_DIR``
  defaults to ``~/.cache/spot/stages``, the stage cache's folder);
* ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` = :data:`MIN_COMPILE_S` (JAX's default, 1 s,
  would leave out most of a small run's programs, which compile in 0.1-1 s on CPU);
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
from pathlib import Path

from spot import SpotError

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_REDUCE"
MUJOCO_GL_DEFAULT = "egl"
JAX_CACHE_SWITCH = "SPOT_JAX_CACHE"
MIN_COMPILE_S = "0.2"
MAX_SIZE_BYTES = str(2 * 1024**3)
_CACHE_VARS = {
    "JAX_COMPILATION_CACHE_DIR": ("jax_compilation_cache_dir", str),
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": ("jax_persistent_cache_min_compile_time_secs", float),
    "JAX_COMPILATION_CACHE_MAX_SIZE": ("jax_compilation_cache_max_size", int),
}


def jax_cache_dir() -> Path:
    """``$SPOT_CACHE_DIR/jax/jax-<version>`` (``SPOT_CACHE_DIR`` defaults to ``~/.cache/spot/stages``)."""
    from importlib.metadata import version

    from spot import cache

    return cache.cache_dir() / "jax" / f"jax-{version('jax')}"


def compilation_cache_settings() -> dict[str, str]:
    """The persistent-compilation-cache variables :func:`configure` sets (module docstring); empty
    when ``SPOT_JAX_CACHE`` is ``0``/``false``/``no``/``off``. Values the user set win."""
    switch = os.environ.get(JAX_CACHE_SWITCH, "1").strip().lower()
    if switch in ("0", "false", "no", "off"):
        return {}
    if switch not in ("1", "true", "yes", "on"):
        raise SpotError(f"{JAX_CACHE_SWITCH}={os.environ[JAX_CACHE_SWITCH]!r}: expected 1 or 0 (on or off)")
    defaults = {
        "JAX_COMPILATION_CACHE_DIR": str(jax_cache_dir()),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": MIN_COMPILE_S,
        "JAX_COMPILATION_CACHE_MAX_SIZE": MAX_SIZE_BYTES,
    }
    return {k: os.environ.get(k) or v for k, v in defaults.items()}


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
      RuntimeError: the YNN flag is missing and a jax backend has already started (too late for
        the flag to take effect; call ``configure()`` earlier).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if YNN_FLAG not in flags.split():
        if _jax_backend_started():
            raise RuntimeError(
                "spot.runtime.configure() was called after a jax backend started; call it "
                "before any jax computation so that XLA_FLAGS takes effect"
            )
        os.environ["XLA_FLAGS"] = f"{flags} {YNN_FLAG}".strip()
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
