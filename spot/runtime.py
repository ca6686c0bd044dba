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
"""

from __future__ import annotations

import os
import sys

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_REDUCE"
MUJOCO_GL_DEFAULT = "egl"


def _jax_backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def configure() -> dict[str, str]:
    """Set ``XLA_FLAGS`` and ``MUJOCO_GL`` for spot (see the module docstring); idempotent.

    Returns:
      The two variables' values after the call.

    Raises:
      RuntimeError: the YNN flag is missing and a jax backend has already started (too late for
        the flag to take effect; call ``configure()`` earlier).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if YNN_FLAG not in flags.split():
        if _jax_backend_started():
            raise RuntimeError("spot.runtime.configure() was called after a jax backend started; call it "
                               "before any jax computation so that XLA_FLAGS takes effect")
        os.environ["XLA_FLAGS"] = f"{flags} {YNN_FLAG}".strip()
    if "mujoco" not in sys.modules:
        os.environ.setdefault("MUJOCO_GL", MUJOCO_GL_DEFAULT)
    return {"XLA_FLAGS": os.environ["XLA_FLAGS"], "MUJOCO_GL": os.environ.get("MUJOCO_GL", "")}
