"""A run's trained models as artifacts: data only, with a JSON header, reloadable by ``spot``.

Each model is two artifacts under ``models/``: ``<name>.npz``, written by
:func:`spot.cache.write_entry` (the arrays plus a JSON description of the tree around them and a
SHA-256 of both; read with ``allow_pickle=False``, never unpickled, types rebuilt only if defined
in spot), and ``<name>.json``, a header saying what it is, the config sections it was built with,
the shape of every array, and whatever the model needs to be used again (e.g. the policy's
evaluation env). :func:`load_model` reads both back from any run; a stored value that cannot be
rebuilt, for any reason, is one SpotError naming the artifact. The ``policy`` of a run is also
checked against the networks its config builds (:func:`check_tree`: every leaf a finite array of the
expected shape and dtype) before anything uses it.

Models a run saves (:mod:`spot.stages`): ``policy`` (IQL/IPL: actor, critics, value and target
critics), ``reward_model`` (MR, PT or HPL), ``cvae`` (SPOT, and PT runs with the Fig. 2
diagnostics).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from spot import SpotError, cache, store
from spot.tracking.provenance import git_commit, package_versions
from spot.tracking.trackers import Tracker, json_safe

MODELS_DIR = "models"
FORMAT = (
    "spot.cache entry: .npz read with allow_pickle=False; the arrays, a JSON description of "
    "the tree around them (__tree__) and a SHA-256 of both (__digest__); spot.cache.read_entry"
)


def shapes(value: Any) -> dict[str, list[int]]:
    """``{tree path: shape}`` of every array leaf of ``value``."""
    import jax

    leaves = jax.tree_util.tree_leaves_with_path(value)
    return {jax.tree_util.keystr(path): list(getattr(leaf, "shape", ())) for path, leaf in leaves}


def header(name: str, what: str, value: Any, config: Mapping[str, Any], **extra: Any) -> dict[str, Any]:
    """The JSON header of a saved model."""
    return json_safe(
        {
            "name": name,
            "what": what,
            "file": f"{name}.npz",
            "format": FORMAT,
            "config": dict(config),
            "shapes": shapes(value),
            "git_commit": git_commit(),
            "spot_version": package_versions().get("spot-pbrl"),
            **extra,
        }
    )


def save_model(
    tracker: Tracker, folder: Path, name: str, what: str, value: Any, config: Mapping[str, Any], **extra: Any
) -> dict[str, Any]:
    """Write ``value`` (a pytree of arrays: dicts, NamedTuples, spot dataclasses) and its header to
    ``folder`` and log both under ``models/``; returns the header."""
    folder.mkdir(parents=True, exist_ok=True)
    npz = folder / f"{name}.npz"
    cache.write_entry(npz, value)
    head = header(name, what, value, config, **extra)
    meta = folder / f"{name}.json"
    store.write_atomic(meta, (json.dumps(head, indent=2, allow_nan=False) + "\n").encode())
    tracker.log_artifact(npz, MODELS_DIR)
    tracker.log_artifact(meta, MODELS_DIR)
    return head


def read_model(folder: Path, name: str) -> tuple[Any, dict[str, Any]]:
    """``(value, header)`` of a model saved by :func:`save_model` in ``folder``."""
    npz, meta = folder / f"{name}.npz", folder / f"{name}.json"
    try:
        head = json.loads(meta.read_text())
        value = cache.read_entry(npz)
    except (OSError, ValueError, RecursionError) as e:  # cache.EntryError is a ValueError
        raise SpotError(f"{npz}: not a readable saved model ({e})") from None
    if not isinstance(head, dict):
        raise SpotError(f"{meta}: expected a JSON object (the model's header), got {type(head).__name__}")
    return value, head


def _describe(leaf: Any) -> str:
    shape = getattr(leaf, "shape", None)
    return f"{leaf.dtype}{list(shape)}" if shape is not None and hasattr(leaf, "dtype") else type(leaf).__name__


def check_tree(value: Any, expected: Any, where: str) -> None:
    """SpotError (one line naming ``where``) unless ``value`` has the tree of ``expected`` (arrays or
    ``jax.ShapeDtypeStruct`` leaves) with, at every path, a finite numpy array of the same shape
    and dtype."""
    import jax
    import numpy as np

    want = {jax.tree_util.keystr(p): leaf for p, leaf in jax.tree_util.tree_leaves_with_path(expected)}
    got = {jax.tree_util.keystr(p): leaf for p, leaf in jax.tree_util.tree_leaves_with_path(value)}
    missing, extra = [k for k in want if k not in got], [k for k in got if k not in want]
    if missing or extra:
        raise SpotError(
            f"{where}: not the expected networks: {len(missing)} arrays missing (e.g. {missing[:2]}), "
            f"{len(extra)} unexpected (e.g. {extra[:2]}); expected {len(want)} arrays such as "
            f"{next(iter(want), '')} {_describe(next(iter(want.values()), None))}"
        )
    for k, w in want.items():
        g = got[k]
        if not isinstance(g, np.ndarray) or g.shape != tuple(w.shape) or g.dtype != w.dtype:
            raise SpotError(f"{where}: {k} is {_describe(g)}; expected {_describe(w)}")
        if not np.isfinite(g).all():
            raise SpotError(f"{where}: {k} holds non-finite values (NaN or inf); expected finite weights")


def policy_template(cfg: Any, env: Any, where: str) -> dict[str, Any]:
    """Shapes and dtypes (``jax.ShapeDtypeStruct``) of the policy a run with config ``cfg`` saves
    for the evaluation env ``env`` (:mod:`spot.stages`: IQL's actor, critics, value and target
    critics), from fresh networks traced, not run."""
    import jax
    import numpy as np

    from spot import envs
    from spot.policy import iql

    if not isinstance(env, str) or not env:
        raise SpotError(f"{where}: 'env' is {env!r}; expected the name of the run's evaluation env")
    try:
        envs.env_spec(env)
    except SpotError as e:
        raise SpotError(f"{where}: 'env': {e}") from None
    made = envs.make_env(env, 0)
    try:
        obs_dim, act_dim = (int(np.prod(s.shape)) for s in (made.observation_space, made.action_space))
    finally:
        made.close()
    state = jax.eval_shape(lambda k: iql.init_state(k, obs_dim, act_dim, cfg.iql), jax.random.key(0))
    return {
        "actor": state.actor.params,
        "critic": state.critic.params,
        "value": state.value.params,
        "target_critic": state.target_critic_params,
    }


def _check_policy(run_id: str, value: Any, head: dict[str, Any], tracking_uri: str | None) -> None:
    """A run's ``models/policy``: its header's ``env`` and ``eval_seed``, and its networks against
    those the run's config builds."""
    where = f"run {run_id}: {MODELS_DIR}/policy"
    seed = head.get("eval_seed")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise SpotError(f"{where}.json: 'eval_seed' is {seed!r}; expected an integer")
    expected = policy_template(run_config(run_id, tracking_uri), head.get("env"), f"{where}.json")
    check_tree(value, expected, f"{where}.npz")


def load_model(
    run_id: str, name: str, tracking_uri: str | None = None, dst: str | Path | None = None
) -> tuple[Any, dict[str, Any]]:
    """``(value, header)`` of the model ``name`` a run saved (downloaded to ``dst`` if its
    artifact store is remote; a temporary folder by default).

    Raises SpotError if the run does not exist, saved no such model, or the model cannot be read;
    for ``policy``, also unless its networks are those the run's config builds (:func:`check_tree`).
    """
    from spot.tracking.queries import artifact_uri, download_artifact
    from spot.tracking.store import reader

    client = reader(tracking_uri)
    root = artifact_uri(client, run_id)
    dst = Path(dst or tempfile.mkdtemp(prefix="spot-model-"))
    got = {}
    for file in (f"{name}.json", f"{name}.npz"):
        path = download_artifact(run_id, root, f"{MODELS_DIR}/{file}", client.tracking_uri, str(dst))
        if path is None:
            raise SpotError(
                f"run {run_id} has no saved model {MODELS_DIR}/{file} (runs save their models "
                "since spot records them; older runs do not have them)"
            )
        got[file] = path
    if got[f"{name}.json"].parent != got[f"{name}.npz"].parent:
        raise SpotError(f"run {run_id}: {name}.json and {name}.npz were not found in one folder")
    value, head = read_model(got[f"{name}.npz"].parent, name)
    if name == "policy":
        _check_policy(run_id, value, head, tracking_uri)
    return value, head


def load_artifact_text(run_id: str, artifact_path: str, tracking_uri: str | None = None) -> str:
    """The text of one artifact of a run (e.g. ``config.yaml``); SpotError if it has none."""
    from spot.tracking.queries import artifact_uri, download_artifact
    from spot.tracking.store import reader

    client = reader(tracking_uri)
    root = artifact_uri(client, run_id)
    with tempfile.TemporaryDirectory(prefix="spot-artifact-") as tmp:
        path = download_artifact(run_id, root, artifact_path, client.tracking_uri, tmp)
        if path is None:
            raise SpotError(f"run {run_id} has no artifact {artifact_path!r} ({client.tracking_uri})")
        return path.read_text()


def run_config(run_id: str, tracking_uri: str | None = None) -> Any:
    """The resolved config a run logged (its ``config.yaml`` artifact), validated again."""
    from spot import config as config_lib

    text = load_artifact_text(run_id, "config.yaml", tracking_uri)
    with tempfile.TemporaryDirectory(prefix="spot-config-") as tmp:
        path = Path(tmp) / "config.yaml"
        path.write_text(text)
        return config_lib.load(path)
