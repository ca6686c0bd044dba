"""A dataset built by a process with SPOT_FAST_COMPILE on is the normal build: the recipe runs in a
child process without the fast-compile XLA flags (spot.data.build_child), under the parent's locks."""

import hashlib
import json
import os
from pathlib import Path

import pytest
from conftest import run_cli

from spot import SpotError
from spot.data import build_child, registry
from spot.recipes import locomotion

FAST = (
    "--xla_backend_optimization_level=0",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_parallel_codegen_split_count=1",
)
NAME, SEED = "hopper-medium-replay", 0
SHIPPED = Path(__file__).resolve().parents[1] / "spot" / "data" / "embedded" / f"{NAME}__small__seed{SEED}.hdf5"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _normal_flags() -> str:
    return " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f not in FAST)


@pytest.fixture
def fast_process(tmp_path, monkeypatch):
    """This process's registry calls see fast compile on (switch and flags), a fresh data dir, no
    store, and a locomotion recipe that must not run here."""

    def not_here(*args, **kwargs):
        raise AssertionError("the recipe ran in the fast-compile process")

    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "fast"))
    monkeypatch.delenv("SPOT_STORE", raising=False)
    monkeypatch.setenv("SPOT_FAST_COMPILE", "1")
    monkeypatch.setenv("XLA_FLAGS", " ".join([_normal_flags(), *FAST]).strip())
    monkeypatch.setattr(locomotion, "build", not_here)
    return tmp_path / "fast"


def test_needed_and_the_child_environment(monkeypatch):
    monkeypatch.setenv("SPOT_FAST_COMPILE", "0")
    monkeypatch.setenv("XLA_FLAGS", "--xla_a=1")
    assert not build_child.needed()
    monkeypatch.setenv("XLA_FLAGS", f"--xla_a=1 {FAST[1]}")  # the flags without the switch
    assert build_child.needed()
    monkeypatch.setenv("XLA_FLAGS", "--xla_a=1")
    monkeypatch.setenv("SPOT_FAST_COMPILE", "1")  # the switch (configure() adds the flags)
    assert build_child.needed()
    env = build_child.child_env({"XLA_FLAGS": f"--xla_a=1 {FAST[0]} --xla_b=2 {FAST[1]}", "OTHER": "x"})
    assert env == {"XLA_FLAGS": "--xla_a=1 --xla_b=2", "SPOT_FAST_COMPILE": "0", "OTHER": "x"}


def test_a_tiny_build_under_fast_compile_is_the_normal_build(fast_process, tmp_path):
    normal_dir = tmp_path / "normal"
    env = {"SPOT_DATA_DIR": str(normal_dir), "SPOT_FAST_COMPILE": "0", "XLA_FLAGS": _normal_flags()}
    done = run_cli("data", "build", NAME, "--size", "tiny", "--data-seed", str(SEED), "--quiet", env=env)
    assert done.returncode == 0, done.stderr
    normal = normal_dir / f"{NAME}__tiny__seed{SEED}.hdf5"

    path = registry.build(NAME, "tiny", SEED, progress=False)
    assert path == fast_process / normal.name
    assert _sha256(path) == _sha256(normal)
    card = json.loads(path.with_suffix(".card.json").read_text())
    assert card["obtained"] == "built" and card["sha256"] == _sha256(path)
    assert card["xla_flags"].split() and not set(FAST) & set(card["xla_flags"].split())
    assert card["xla_flags"] == json.loads(normal.with_suffix(".card.json").read_text())["xla_flags"]
    # reused from the cache: no second child
    assert registry.build(NAME, "tiny", SEED, progress=False) == path


def test_a_failing_child_is_one_error_and_writes_nothing(fast_process, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", os.environ["XLA_FLAGS"] + " --xla_no_such_flag=1")
    with pytest.raises(SpotError) as err:
        registry.build(NAME, "tiny", SEED, progress=False)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"dataset {NAME} (tiny, seed {SEED}): its build in a process without SPOT_FAST_COMPILE")
    assert "--xla_no_such_flag=1" in msg
    assert not list(fast_process.glob("*.hdf5*")) and not list(fast_process.glob("*.card.json*"))


def test_the_embedded_copy_needs_no_child(fast_process, monkeypatch):
    def no_child(*args, **kwargs):
        raise AssertionError("a child process was started for the embedded copy")

    monkeypatch.setattr(build_child, "run", no_child)
    path = registry.build(NAME, "small", SEED, progress=False)
    assert registry.read_card(path)["obtained"] == "embedded"
    assert _sha256(path) == _sha256(SHIPPED)
