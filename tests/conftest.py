"""Shared fixtures: an isolated data/cache dir per test session, and tiny built datasets."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spot import runtime


def pytest_configure(config):
    """spot's process settings (XLA flag, MUJOCO_GL) before any test module imports jax or mujoco."""
    runtime.configure()


# The files that take longest (summed setup + call + teardown of `pytest --durations=0` on 2 cores,
# 2026-11-26: 366 s down to 47 s), longest first. xdist hands out whole files in collection order
# (`--dist loadfile --no-loadscope-reorder` in pyproject.toml), so starting the long ones first
# keeps both workers busy to the end. Measured from a clean clone: 1,097 s before (xdist's order
# by test count; one niced training run beside it) and 1,067 s after (idle machine); the gain is
# smaller than the ~130 s the durations promised because test_hardening and test_learning, both
# CPU-heavy, now run at the same time and slow each other (2,075 s of work instead of 1,939 s).
# Files not listed keep pytest's order after these.
LONGEST_FIRST = (
    "test_hardening.py",
    "test_learning.py",
    "test_multinode.py",
    "test_sweep.py",
    "test_pipeline.py",
    "test_bench_sweep.py",
    "test_cli.py",
    "test_recorded.py",
    "test_recipe_robosuite.py",
    "test_docker.py",
    "test_envs.py",
)


def pytest_collection_modifyitems(config, items):
    """Run the files of :data:`LONGEST_FIRST` first, in that order (a stable sort: tests keep their
    order within a file)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="session")
def spot_dirs(tmp_path_factory):
    """Session-wide SPOT_DATA_DIR / SPOT_CACHE_DIR so built datasets are shared by tests.

    An existing ``SPOT_DATA_DIR`` is kept (CI and developers reuse built datasets across sessions;
    builds are keyed by name, size, seed and recipe version); the stage cache is always fresh.
    """
    root = tmp_path_factory.mktemp("spot")
    old = {k: os.environ.get(k) for k in ("SPOT_DATA_DIR", "SPOT_CACHE_DIR")}
    os.environ.setdefault("SPOT_DATA_DIR", str(root / "data"))
    os.environ["SPOT_CACHE_DIR"] = str(root / "cache")
    yield root
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


# A whole run in seconds: the tiny budget on the tiny drawer-open dataset (fixture tiny_drawer).
TINY_RUN = [
    "budget=tiny",
    "data.name=drawer-open",
    "iql.steps=200",
    "eval.every=100",
    "eval.episodes=1",
    "labels.num_queries=30",
    "labels.segment_length=25",
]


@pytest.fixture(scope="session")
def tiny_drawer(spot_dirs):
    """drawer-open, tiny size, built once per session (Meta-World, ~5 s)."""
    from spot.data import registry

    return registry.build("drawer-open", "tiny", 0, progress=False)


def run_cli(*args: str, cwd: Path | None = None, env: dict | None = None, timeout: int = 600):
    """Run ``python -m spot.cli ARGS`` in a subprocess; returns CompletedProcess."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "spot.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=full_env,
        timeout=timeout,
    )


def make_dataset(episode_lengths: list[int], seed: int = 0, obs_dim: int = 4, act_dim: int = 2):
    """A qlearning-view Dataset of random transitions in episodes of the given lengths."""
    from spot.data.dataset import Dataset

    rng = np.random.default_rng(seed)
    n = sum(episode_lengths)
    obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    return Dataset(
        observations=obs,
        actions=rng.uniform(-1, 1, size=(n, act_dim)).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_observations=obs,
        terminals=np.zeros(n, bool),
        episode_ids=np.repeat(np.arange(len(episode_lengths)), episode_lengths),
        raw_index=np.arange(n),
        name="test",
    )
