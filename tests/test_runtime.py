"""No hidden state: importing spot changes nothing; :func:`spot.runtime.configure` sets what it says."""

import json
import os
import subprocess
import sys
from pathlib import Path

from spot import runtime

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=300)


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MUJOCO_GL")}


def test_importing_every_spot_module_leaves_the_environment_alone():
    modules = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
                     for p in (ROOT / "spot").rglob("*.py"))
    code = ("import importlib, json, os\nbefore = dict(os.environ)\n"
            f"for m in {modules!r}:\n    importlib.import_module(m)\n"
            "after = dict(os.environ)\n"
            "print(json.dumps({k: [before.get(k), after.get(k)] for k in set(before) | set(after)"
            " if before.get(k) != after.get(k)}))")
    out = _python(code, _clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    changed = json.loads(out.stdout.strip().splitlines()[-1])
    # Third-party imports set a few of their own (TF_CPP_MIN_LOG_LEVEL, PYGAME_HIDE_SUPPORT_PROMPT);
    # what spot's settings touch must be left alone.
    ours = {k: v for k, v in changed.items() if k in ("XLA_FLAGS", "MUJOCO_GL") or k.startswith(("SPOT_", "JAX_"))}
    assert ours == {}, f"importing spot modules changed the environment: {ours}"


def test_configure_sets_the_xla_flag_and_mujoco_gl_once():
    code = ("import json\nfrom spot import runtime\nfirst = runtime.configure()\nsecond = runtime.configure()\n"
            "print(json.dumps([first, second]))")
    env = {**_clean_env(), "XLA_FLAGS": "--xla_dump_to=/tmp/x"}
    out = _python(code, env)
    assert out.returncode == 0, out.stderr[-3000:]
    first, second = json.loads(out.stdout.strip().splitlines()[-1])
    assert first == second  # idempotent: the flag is appended once
    assert first["XLA_FLAGS"] == f"--xla_dump_to=/tmp/x {runtime.YNN_FLAG}"
    assert first["MUJOCO_GL"] == "egl"
    out = _python(code, {**_clean_env(), "MUJOCO_GL": "osmesa"})  # a user's choice is kept
    assert json.loads(out.stdout.strip().splitlines()[-1])[0]["MUJOCO_GL"] == "osmesa"


def test_configure_after_jax_started_without_the_flag_is_an_error():
    code = ("import jax, jax.numpy as jnp\njnp.ones(2).block_until_ready()\nfrom spot import runtime\n"
            "try:\n    runtime.configure()\nexcept RuntimeError as e:\n    print('raised', e)\n")
    out = _python(code, _clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "raised spot.runtime.configure() was called after a jax backend started" in out.stdout


def test_the_test_session_is_configured():
    """conftest.py's ``pytest_configure`` ran ``configure()`` before the tests imported jax."""
    assert runtime.YNN_FLAG in os.environ["XLA_FLAGS"].split()
