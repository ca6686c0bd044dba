"""Content-addressed stage cache.

Each pipeline stage's output is stored under a key hashed from everything it depends on (dataset
identity, labels, its config section, the seed and the stage's code version). A run that changes
only the shaping weight therefore reuses the reward model and the CVAE of an earlier run.

Entries are pickles of numpy/JAX pytrees (``jax.device_get`` first) written to a temporary name and
renamed, with a SHA-256 of the payload stored beside them; an entry whose checksum does not match
is reported, deleted and rebuilt, never used. The cache dir is ``$SPOT_CACHE_DIR`` (default
``~/.cache/spot/stages``).
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

# Bump a stage's version when its code changes what it computes.
STAGE_VERSIONS = {"labels": 1, "reward": 1, "relabel": 1, "subgoals": 1, "cvae": 1, "hpl": 1, "hpl_relabel": 1}


def cache_dir() -> Path:
    return Path(os.environ.get("SPOT_CACHE_DIR", Path.home() / ".cache" / "spot" / "stages")).expanduser()


def _canonical(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in sorted(obj.items())}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return {"sha256": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(),
                "shape": list(obj.shape), "dtype": str(obj.dtype)}
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    return obj


def key(stage: str, deps: dict[str, Any]) -> str:
    """Hash of the stage name, its code version and its dependencies."""
    payload = json.dumps({"stage": stage, "version": STAGE_VERSIONS[stage], "deps": _canonical(deps)},
                         sort_keys=True, default=str)
    return f"{stage}-{hashlib.sha256(payload.encode()).hexdigest()[:20]}"


def _paths(k: str) -> tuple[Path, Path]:
    d = cache_dir()
    return d / f"{k}.pkl", d / f"{k}.sha256"


def load(k: str) -> Any | None:
    """The cached value, or None if absent or corrupt (a corrupt entry is deleted)."""
    data_path, sum_path = _paths(k)
    if not data_path.exists() or not sum_path.exists():
        return None
    payload = data_path.read_bytes()
    if hashlib.sha256(payload).hexdigest() != sum_path.read_text().strip():
        warnings.warn(f"stage cache entry {data_path} is corrupt (checksum mismatch); rebuilding it", stacklevel=2)
        data_path.unlink(missing_ok=True)
        sum_path.unlink(missing_ok=True)
        return None
    try:
        return pickle.loads(payload)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means a bad entry
        warnings.warn(f"stage cache entry {data_path} cannot be read ({e}); rebuilding it", stacklevel=2)
        data_path.unlink(missing_ok=True)
        sum_path.unlink(missing_ok=True)
        return None


def store(k: str, value: Any) -> None:
    import jax

    data_path, sum_path = _paths(k)
    data_path.parent.mkdir(parents=True, exist_ok=True)
    payload = pickle.dumps(jax.device_get(value), protocol=pickle.HIGHEST_PROTOCOL)
    tmp = data_path.with_name(f"{data_path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(payload)
    tmp_sum = sum_path.with_name(f"{sum_path.name}.tmp-{os.getpid()}")
    tmp_sum.write_text(hashlib.sha256(payload).hexdigest())
    os.replace(tmp, data_path)
    os.replace(tmp_sum, sum_path)


def cached(stage: str, deps: dict[str, Any], compute: Callable[[], Any]) -> tuple[Any, bool, str]:
    """``(value, hit, key)``: the cached value for ``deps``, or ``compute()`` stored under it."""
    k = key(stage, deps)
    value = load(k)
    if value is not None:
        return value, True, k
    value = compute()
    store(k, value)
    return value, False, k
