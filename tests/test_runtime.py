"""No hidden state: importing spot changes nothing; :func:`spot.runtime.configure` sets what it says."""

import json
import os
import subprocess
import sys
from pathlib import Path

from spot import runtime

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MUJOCO_GL", runtime.FAST_COMPILE_SWITCH)}


def test_importing_every_spot_module_leaves_the_environment_alone():
    modules = sorted(
        ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for p in (ROOT / "spot").rglob("*.py")
    )
    code = (
        "import importlib, json, os\nbefore = dict(os.environ)\n"
        f"for m in {modules!r}:\n    importlib.import_module(m)\n"
        "after = dict(os.environ)\n"
        "print(json.dumps({k: [before.get(k), after.get(k)] for k in set(before) | set(after)"
        " if before.get(k) != after.get(k)}))"
    )
    out = _python(code, _clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    changed = json.loads(out.stdout.strip().splitlines()[-1])
    # Third-party imports set a few of their own (TF_CPP_MIN_LOG_LEVEL, PYGAME_HIDE_SUPPORT_PROMPT);
    # what spot's settings touch must be left alone.
    ours = {k: v for k, v in changed.items() if k in ("XLA_FLAGS", "MUJOCO_GL") or k.startswith(("SPOT_", "JAX_"))}
    assert ours == {}, f"importing spot modules changed the environment: {ours}"


def test_configure_sets_the_xla_flag_and_mujoco_gl_once():
    code = (
        "import json\nfrom spot import runtime\nfirst = runtime.configure()\nsecond = runtime.configure()\n"
        "print(json.dumps([first, second]))"
    )
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
    code = (
        "import jax, jax.numpy as jnp\njnp.ones(2).block_until_ready()\nfrom spot import runtime\n"
        "try:\n    runtime.configure()\nexcept RuntimeError as e:\n    print('raised', e)\n"
    )
    out = _python(code, _clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "raised spot.runtime.configure() was called after a jax backend started" in out.stdout


def test_the_test_session_is_configured():
    """conftest.py's ``pytest_configure`` ran ``configure()`` before the tests imported jax."""
    assert runtime.YNN_FLAG in os.environ["XLA_FLAGS"].split()


# --------------------------------------------------------------------------- JAX compilation cache
_TRAIN_AND_COUNT = """
import json, os
from spot import runtime
settings = runtime.configure()
import jax, numpy as np
hits = []
jax.monitoring.register_event_listener(lambda name, **kw: hits.append(name) if name.endswith("cache_hits") else None)
from spot.batches import Transitions
from spot.config import IQLConfig
from spot.policy import iql
cfg = IQLConfig(hidden=(16, 16), batch_size=8, steps=20, chunk=10)
rng = np.random.default_rng(0)
data = Transitions(*(rng.normal(size=s).astype(np.float32) for s in ((64, 3), (64, 2), (64,), (64, 3))),
                   np.ones(64, np.float32))
state = iql.init_state(jax.random.key(1), 3, 2, cfg)
state, metrics = iql.make_train_chunk(cfg)(state, 10, data, jax.random.key(2))
print(json.dumps({"settings": settings, "hits": len(hits), "critic_loss": float(metrics["iql/critic_loss"]),
                  "q": np.asarray(iql.act(state.actor.params, np.ones((1, 3)), cfg)).tolist()}))
"""


def _cache_env(tmp_path: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in _clean_env().items() if not k.startswith("JAX_") and k != runtime.JAX_CACHE_SWITCH}
    return {**env, "SPOT_CACHE_DIR": str(tmp_path / "cache"), **extra}


def test_a_second_process_loads_the_programs_the_first_compiled(tmp_path):
    """The persistent compilation cache under $SPOT_CACHE_DIR/jax/jax-<version>: the first process
    writes its programs there, the second finds them (jax's cache-hit events) and computes the same
    numbers. The min compile time is 0 (spot's default, also set here), so that every program of
    this tiny run is cached."""
    env = _cache_env(tmp_path, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    first = _python(_TRAIN_AND_COUNT, env)
    assert first.returncode == 0, first.stderr[-3000:]
    a = json.loads(first.stdout.strip().splitlines()[-1])
    folder = Path(a["settings"]["JAX_COMPILATION_CACHE_DIR"])
    assert folder.parent == tmp_path / "cache" / "jax" and folder.name.startswith("jax-")
    assert a["settings"]["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
    written = sorted(p.name for p in folder.iterdir() if p.name.endswith("-cache"))
    assert written and a["hits"] == 0
    second = _python(_TRAIN_AND_COUNT, env)
    assert second.returncode == 0, second.stderr[-3000:]
    b = json.loads(second.stdout.strip().splitlines()[-1])
    assert b["hits"] >= 3  # the three network inits, the train chunk and act at least
    assert (b["critic_loss"], b["q"]) == (a["critic_loss"], a["q"])
    assert sorted(p.name for p in folder.iterdir() if p.name.endswith("-cache")) == written  # nothing new


def test_the_compilation_cache_switch(tmp_path):
    code = "import json, os\nfrom spot import runtime\nprint(json.dumps(runtime.configure()))"
    on = json.loads(_python(code, _cache_env(tmp_path)).stdout.strip().splitlines()[-1])
    assert on["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == runtime.MIN_COMPILE_S
    assert on["JAX_COMPILATION_CACHE_MAX_SIZE"] == str(2 * 1024**3)  # bounded: entries read and written under a lock
    assert on["JAX_COMPILATION_CACHE_DIR"].startswith(str(tmp_path / "cache" / "jax" / "jax-"))
    mine = json.loads(
        _python(code, _cache_env(tmp_path, JAX_COMPILATION_CACHE_DIR="/tmp/mine")).stdout.strip().splitlines()[-1]
    )
    assert mine["JAX_COMPILATION_CACHE_DIR"] == "/tmp/mine"  # the user's folder is kept
    slow_only = _python(code, _cache_env(tmp_path, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="2"))
    assert json.loads(slow_only.stdout.strip().splitlines()[-1])["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "2"
    off = json.loads(_python(code, _cache_env(tmp_path, SPOT_JAX_CACHE="0")).stdout.strip().splitlines()[-1])
    assert "JAX_COMPILATION_CACHE_DIR" not in off and set(off) == {"XLA_FLAGS", "MUJOCO_GL"}
    bad = _python(code, _cache_env(tmp_path, SPOT_JAX_CACHE="maybe"))
    assert bad.returncode != 0 and "SPOT_JAX_CACHE='maybe': expected 1 or 0" in bad.stderr


def test_fast_compile_appends_its_flags_and_a_sweep_trial_sets_the_switch(tmp_path):
    code = "import json, os\nfrom spot import runtime\nprint(json.dumps(runtime.configure()))"
    fast = json.loads(_python(code, _cache_env(tmp_path, SPOT_FAST_COMPILE="1")).stdout.strip().splitlines()[-1])
    assert fast["XLA_FLAGS"].split() == [
        runtime.YNN_FLAG,
        "--xla_backend_optimization_level=0",
        "--xla_llvm_disable_expensive_passes=true",
        "--xla_cpu_use_fusion_emitters=false",
        "--xla_cpu_parallel_codegen_split_count=1",
    ]
    plain = json.loads(_python(code, _cache_env(tmp_path)).stdout.strip().splitlines()[-1])
    assert plain["XLA_FLAGS"].split() == [runtime.YNN_FLAG]
    bad = _python(code, _cache_env(tmp_path, SPOT_FAST_COMPILE="fast"))
    assert bad.returncode != 0 and "SPOT_FAST_COMPILE='fast': expected 1 or 0" in bad.stderr
    # a trial of a sweep with fast_compile: true makes the setting before jax starts, and XLA accepts
    # the flags (it aborts on a flag it does not know)
    trial = (
        "import json, os\nfrom spot.sweep import trial\ntrial._configure_once(1, 0.0, True)\n"
        "import jax.numpy as jnp\nx = float(jnp.arange(4.0).sum())\n"
        "print(json.dumps([os.environ['XLA_FLAGS'], x]))"
    )
    out = _python(trial, _cache_env(tmp_path))
    assert out.returncode == 0, out.stderr[-3000:]
    flags, x = json.loads(out.stdout.strip().splitlines()[-1])
    assert "--xla_backend_optimization_level=0" in flags.split() and x == 6.0


def test_pid_alive_is_false_only_for_a_process_that_is_gone():
    import os
    import subprocess
    import sys

    from spot.runtime import pid_alive

    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    gone = int(done.stdout)  # reaped: no such process (unless the pid was reused meanwhile)
    assert pid_alive(os.getpid()) and pid_alive(1)  # this process; init (another user's or ours)
    assert not pid_alive(gone) or os.path.exists(f"/proc/{gone}")
    assert pid_alive(2**70)  # not a pid here: left alone, never "gone"


def test_bad_switch_values_are_one_error_line_and_exit_2(monkeypatch, capsys):
    from spot import cli

    monkeypatch.setenv("SPOT_FAST_COMPILE", "maybe")
    assert cli.main(["config", "keys"]) == 2
    assert capsys.readouterr().err.strip() == "error: SPOT_FAST_COMPILE='maybe': expected 1 or 0 (on or off)"


def test_a_process_cannot_switch_fast_compile_once_jax_started(monkeypatch):
    import jax  # noqa: F401  (started: the flags can no longer change)
    import pytest

    from spot import SpotError
    from spot.sweep import trial

    # whatever happens, this process's environment is restored
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    monkeypatch.setenv("SPOT_FAST_COMPILE", os.environ.get("SPOT_FAST_COMPILE", "0"))
    monkeypatch.setitem(trial._PROCESS, "settings", (1, 0.0, False))
    with pytest.raises(SpotError, match="fast_compile: this process compiled with fast_compile=False"):
        trial._configure_once(1, 0.0, True)


def test_an_interrupt_raised_in_a_gc_callback_is_sent_again_and_stops_the_process():
    # The KeyboardInterrupt a SIGTERM handler raises inside a weakref callback cannot propagate;
    # without the hook the loop below would end on its own ("finished", exit 0).
    code = """
import signal, time, weakref
from spot import runtime
runtime.redeliver_swallowed_interrupts()
def on_term(signum, frame):
    raise KeyboardInterrupt("signal SIGTERM")
signal.signal(signal.SIGTERM, on_term)
class Thing: pass
def callback(ref):
    on_term(signal.SIGTERM, None)  # as if the signal landed while the gc ran this callback
thing = Thing(); ref = weakref.ref(thing, callback); del thing
try:
    deadline = time.time() + 5
    while time.time() < deadline:
        time.sleep(0.01)
    print("finished")
except KeyboardInterrupt as e:
    print("stopped by", e)
"""
    done = _python(code, dict(os.environ))
    assert done.stdout.strip() == "stopped by signal SIGTERM", done.stderr
    assert "Exception ignored" not in done.stderr


def test_an_interrupted_exit_runs_the_other_atexit_hooks_but_not_jaxs_teardown():
    code = """
import atexit, sys
from spot import runtime
runtime.configure()
import jax, jax.numpy as jnp
from jax._src import api
jnp.ones(3).block_until_ready()
atexit.register(lambda: print("hook ran", flush=True))
def never():  # stands for jax's clean_up, which must not run under a compile that is still going
    print("jax teardown ran", flush=True)
atexit.unregister(api.clean_up)
api.clean_up = never
atexit.register(never)
print("partial line", end="")
runtime.exit_interrupted(130)
"""
    done = _python(code, dict(os.environ))
    assert done.returncode == 130, done.stderr
    assert done.stdout == "partial linehook ran\n"
