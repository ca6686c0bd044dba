"""Readers and writers of offline-RL dataset files, all returning :class:`RawDataset`.

* D4RL hdf5 (Fu et al., 2020, arXiv:2004.07219): top-level datasets ``observations``,
  ``actions``, ``rewards``, ``terminals``, ``timeouts`` and optionally ``next_observations``; an
  ``infos`` group of extra per-step arrays (read into ``RawDataset.infos``: every numeric array
  with one row per step; arrays of another length are skipped); a ``metadata``
  group with scalars and strings. Locally built datasets are written in this layout (gzip level 1,
  atomically) with their card as the JSON attribute ``spot_card``.
* robomimic ``low_dim`` hdf5 (Mandlekar et al., 2021, arXiv:2108.03298):
  ``data/demo_N/{obs/<key>, next_obs/<key>, actions, rewards, dones}`` and
  ``data.attrs['env_args']``. Read so that the ``qlearning`` view equals the view the PT human
  labels index into (PT repo : JaxPref/reward_transform.py ``qlearning_robosuite_dataset``):
  demos in the file's key order (``demo_0, demo_1, demo_10, ...``, what ``f['data'].keys()``
  gives) and the last step of every demo dropped. The observation concatenates the keys in the
  order of :data:`ROBOMIMIC_OBS_KEYS` (PT and IPL, jhejna/inverse-preference-learning :
  research/datasets/robomimic_dataset.py). Can files recorded before robosuite 1.5 get their
  ``object`` block reordered into the evaluation env's order (:func:`robomimic_object_order`).
* Minari (Farama): episodes through ``minari.load_dataset`` / ``minari.MinariDataset``.

Before anything is read, an hdf5 file is checked (:mod:`spot.data.hdf5_checks`).

Every bad input raises :class:`SpotError` naming the file, the key and what was expected.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from spot import SpotError
from spot.data.dataset import RAW_KEYS, RawDataset
from spot.data.hdf5_checks import ReadLimits, as_flags, check_rows, open_hdf5, read_array

ROBOMIMIC_OBS_KEYS = (
    "object",
    "robot0_joint_pos",
    "robot0_joint_pos_cos",
    "robot0_joint_pos_sin",
    "robot0_joint_vel",
    "robot0_eef_pos",
    "robot0_eef_quat",
    "robot0_gripper_qpos",
    "robot0_gripper_qvel",
)
FORMATS = ("auto", "d4rl", "robomimic", "minari")

# Can's 14-D ``object`` block. robosuite 1.5 (the evaluation env, :mod:`spot.envs`) concatenates
# [Can_to_robot0_eef_pos, Can_to_robot0_eef_quat, Can_pos, Can_quat] (PickPlace._create_obj_sensors
# lists the relative sensors first); the robosuite releases robomimic's files were recorded with
# (v0.1: the offline_study branch; v1.4.1) list [Can_pos, Can_quat, Can_to_robot0_eef_pos,
# Can_to_robot0_eef_quat]. Column j of the evaluation env's block is column _CAN_OBJECT_TO_V15[j]
# of an older file's block.
_CAN_OBJECT_TO_V15 = np.r_[7:14, 0:7]


# --------------------------------------------------------------------------- helpers
def _raw_dataset(path: Path, **fields: Any) -> RawDataset:
    """Build a :class:`RawDataset`, prefixing any validation error with the file name."""
    try:
        return RawDataset(**fields)
    except SpotError as err:
        raise SpotError(f"dataset file '{path}': {err}") from None


def _plain(value: Any) -> Any:
    """An hdf5 attribute or scalar dataset value as plain Python."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return _plain(value.item())
    return value


def _json_attr(f: h5py.File, name: str, path: Path) -> dict[str, Any]:
    try:
        value = json.loads(_plain(f.attrs[name]))
    except (json.JSONDecodeError, TypeError) as err:
        raise SpotError(f"dataset file '{path}': attribute '{name}' is not JSON ({err})") from None
    if not isinstance(value, dict):
        raise SpotError(f"dataset file '{path}': attribute '{name}' must be a JSON object")
    return value


def _d4rl_metadata(f: h5py.File, path: Path) -> dict[str, Any]:
    """Root attributes (``spot_card``/``spot_metadata`` as JSON) and the scalars and strings of
    the ``metadata`` group (D4RL stores e.g. ``metadata/algorithm``; policy weights are skipped)."""
    meta: dict[str, Any] = {}
    if "spot_metadata" in f.attrs:
        meta.update(_json_attr(f, "spot_metadata", path))
    for name, value in f.attrs.items():
        if name == "spot_card":
            meta["spot_card"] = _json_attr(f, name, path)
        elif name != "spot_metadata":
            meta[name] = _plain(value)
    group = f.get("metadata")
    if isinstance(group, h5py.Group):

        def visit(name: str, node: Any) -> None:
            if isinstance(node, h5py.Dataset) and (node.ndim == 0 or node.dtype.kind in "SOU"):
                meta[name] = _plain(node[()])

        group.visititems(visit)
    return meta


# --------------------------------------------------------------------------- D4RL
def read_d4rl_hdf5(path: str | Path, limits: ReadLimits | None = None) -> RawDataset:
    """Read a D4RL-layout hdf5 file, checked first by :func:`~spot.data.hdf5_checks.check_hdf5`.

    Args:
      path: the ``.hdf5`` file.
      limits: what the file may make the reader allocate; default :data:`~spot.data.hdf5_checks.DEFAULT_LIMITS`.

    Returns:
      The raw dataset named after the file stem, observations/actions/rewards as float32 and the
      flags as bool; ``metadata`` holds the file's attributes and ``metadata`` group scalars.
    """
    path = Path(path)
    with open_hdf5(path, limits) as f:
        return _read_d4rl(f, path)


def _read_d4rl(f: h5py.File, path: Path) -> RawDataset:
    """:func:`read_d4rl_hdf5` of a file opened and checked by :func:`~spot.data.hdf5_checks.open_hdf5`."""
    ranks = {"observations": 2, "actions": 2, "rewards": 1, "terminals": 1, "timeouts": 1}
    check_rows(f, [*ranks, "next_observations"], path)
    arrays = {key: read_array(f, key, path, rank) for key, rank in ranks.items()}
    next_obs = read_array(f, "next_observations", path, 2) if "next_observations" in f else None
    infos = _d4rl_infos(f, arrays["rewards"].shape[0], path)
    metadata = _d4rl_metadata(f, path)
    return _raw_dataset(
        path,
        observations=arrays["observations"].astype(np.float32),
        actions=arrays["actions"].astype(np.float32),
        rewards=arrays["rewards"].astype(np.float32),
        terminals=as_flags(arrays["terminals"], "terminals", path),
        timeouts=as_flags(arrays["timeouts"], "timeouts", path),
        next_observations=None if next_obs is None else next_obs.astype(np.float32),
        name=path.stem,
        metadata=metadata,
        infos=infos,
    )


def _d4rl_infos(f: h5py.File, n: int, path: Path) -> dict[str, np.ndarray]:
    """The numeric arrays directly under ``infos/`` with ``n`` rows, by name."""
    group = f.get("infos")
    if not isinstance(group, h5py.Group):
        return {}
    return {
        key: read_array(group, key, path)
        for key, node in group.items()
        if isinstance(node, h5py.Dataset)
        and node.ndim >= 1
        and node.shape[0] == n
        and (np.issubdtype(node.dtype, np.number) or node.dtype == np.bool_)
    }


def write_d4rl_hdf5(raw: RawDataset, path: str | Path, card: dict[str, Any] | None = None) -> None:
    """Write ``raw`` in the D4RL layout, readable by :func:`read_d4rl_hdf5`.

    The file is made in memory (HDF5's core driver: a full disk never fails inside HDF5, whose
    file would stay open and crash the process at exit), then written to ``<path>.tmp-<pid>`` and
    moved into place (:func:`spot.store.write_atomic`), so ``path`` is either the old file or the
    complete new one, never a partial write; a full disk is one SpotError, no temporary file left.

    Args:
      raw: the dataset; its ``infos`` go to ``infos/<key>``, its ``metadata`` (less any
        ``spot_card``) to the JSON attribute ``spot_metadata``.
      path: destination file; parent folders are created.
      card: dataset card, stored as the JSON attribute ``spot_card``.
    """
    from spot import store

    path = Path(path)
    attrs = {}
    if card is not None:
        attrs["spot_card"] = json.dumps(card, default=str)
    meta = {k: v for k, v in raw.metadata.items() if k != "spot_card"}
    if meta:
        attrs["spot_metadata"] = json.dumps(meta, default=str)
    with h5py.File(f"{path.name}.in-memory", "w", driver="core", backing_store=False) as f:
        for key in RAW_KEYS + ("next_observations",):
            arr = getattr(raw, key)
            if arr is not None:
                f.create_dataset(key, data=arr, compression="gzip", compression_opts=1)
        for key, arr in raw.infos.items():
            f.create_dataset(f"infos/{key}", data=arr, compression="gzip", compression_opts=1)
        f.attrs.update(attrs)
        f.flush()
        image = f.id.get_file_image()
    store.write_atomic(path, image)


# --------------------------------------------------------------------------- robomimic
def robomimic_object_order(env_args: dict[str, Any], path: str | Path = "") -> np.ndarray | None:
    """Column order that puts a robomimic file's ``object`` block in the evaluation env's order.

    Only Can files need it: ``env_args["env_name"] == "PickPlaceCan"`` recorded before robosuite
    1.5 (``env_args["env_version"]`` below 1.5, or absent as in robomimic v0.1 files, whose
    ``env_args`` predate the key). Returns None when the file already matches (every other task,
    and Can files regenerated with robosuite 1.5, robomimic's ``*_v15.hdf5``).
    """
    if env_args.get("env_name") != "PickPlaceCan":
        return None
    version = env_args.get("env_version")
    if version is None:
        return _CAN_OBJECT_TO_V15
    match = re.match(r"\s*(\d+)\.(\d+)", str(version))
    if match is None:
        raise SpotError(
            f"dataset file '{path}': 'data.attrs[env_args]' has env_version {version!r}; expected "
            "a robosuite version such as '1.4.1'"
        )
    return None if (int(match[1]), int(match[2])) >= (1, 5) else _CAN_OBJECT_TO_V15


def _concat_obs(
    group: h5py.Group, keys: tuple[str, ...], path: Path, object_order: np.ndarray | None = None
) -> np.ndarray:
    parts = []
    for k in keys:
        part = read_array(group, k, path)
        part = part.reshape(part.shape[0], -1)
        if k == "object" and object_order is not None:
            if part.shape[1] != object_order.size:
                raise SpotError(
                    f"dataset file '{path}': '{group.name.lstrip('/')}/object' has {part.shape[1]} "
                    f"columns; expected {object_order.size} (PickPlaceCan's object block)"
                )
            part = part[:, object_order]
        parts.append(part)
    return np.concatenate(parts, axis=1)


def read_robomimic_hdf5(
    path: str | Path, obs_keys: tuple[str, ...] | None = None, limits: ReadLimits | None = None
) -> RawDataset:
    """Read a robomimic ``low_dim`` hdf5 file; each demo is one episode.

    Rows are the demos' steps in the file's key order. The last step of every demo is marked as a
    timeout, so the ``qlearning`` view drops it exactly as PT's loader does and the PT robomimic
    label indices line up; its ``terminals`` flag keeps the file's ``dones[-1]``. Earlier steps
    get ``terminals = dones``. A Can file recorded before robosuite 1.5 has its ``object`` block
    reordered into the evaluation env's order (:func:`robomimic_object_order`).

    Args:
      path: the ``low_dim.hdf5`` file.
      obs_keys: observation keys to concatenate; default :data:`ROBOMIMIC_OBS_KEYS`.
      limits: what the file may make the reader allocate (:func:`~spot.data.hdf5_checks.check_hdf5`); default
        :data:`~spot.data.hdf5_checks.DEFAULT_LIMITS`.

    Returns:
      The raw dataset; ``metadata`` has ``env_name``, ``env_args``, ``obs_keys`` and
      ``object_reordered`` (whether the ``object`` block was reordered).
    """
    path = Path(path)
    keys = tuple(obs_keys) if obs_keys is not None else ROBOMIMIC_OBS_KEYS
    with open_hdf5(path, limits) as f:
        return _read_robomimic(f, path, keys)


def _read_robomimic(f: h5py.File, path: Path, keys: tuple[str, ...]) -> RawDataset:
    """:func:`read_robomimic_hdf5` of a file opened and checked by :func:`~spot.data.hdf5_checks.open_hdf5`."""
    data = f.get("data")
    if not isinstance(data, h5py.Group):
        raise SpotError(f"dataset file '{path}': missing group 'data'; expected robomimic layout")
    demos = [name for name in data.keys() if name.startswith("demo_")]
    if not demos:
        raise SpotError(f"dataset file '{path}': group 'data' has no 'demo_N' groups")
    if "env_args" not in data.attrs:
        raise SpotError(f"dataset file '{path}': missing attribute 'data.attrs[env_args]'")
    try:
        env_args = json.loads(_plain(data.attrs["env_args"]))
        env_name = env_args["env_name"]
    except (json.JSONDecodeError, TypeError, KeyError) as err:
        raise SpotError(
            f"dataset file '{path}': 'data.attrs[env_args]' must be JSON with 'env_name' ({err!r})"
        ) from None
    order = robomimic_object_order(env_args, path) if "object" in keys else None
    with_next = all("next_obs" in data[d] for d in demos)
    episodes = [_robomimic_demo(data[d], keys, with_next, path, order) for d in demos]
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in episodes[0]}
    return _raw_dataset(
        path,
        observations=cat["observations"].astype(np.float32),
        actions=cat["actions"].astype(np.float32),
        rewards=cat["rewards"].astype(np.float32),
        terminals=cat["terminals"],
        timeouts=cat["timeouts"],
        next_observations=cat["next_observations"].astype(np.float32) if with_next else None,
        name=path.stem,
        metadata={
            "format": "robomimic",
            "env_name": env_name,
            "env_args": env_args,
            "obs_keys": list(keys),
            "demos": len(demos),
            "object_reordered": order is not None,
        },
    )


def _robomimic_demo(
    demo: h5py.Group, keys: tuple[str, ...], with_next: bool, path: Path, object_order: np.ndarray | None
) -> dict[str, np.ndarray]:
    if not isinstance(demo.get("obs"), h5py.Group):
        raise SpotError(f"dataset file '{path}': missing group '{demo.name.lstrip('/')}/obs'")
    ep = {
        "observations": _concat_obs(demo["obs"], keys, path, object_order),
        "actions": read_array(demo, "actions", path, 2),
        "rewards": read_array(demo, "rewards", path, 1),
        "terminals": as_flags(read_array(demo, "dones", path, 1), f"{demo.name.lstrip('/')}/dones", path),
    }
    if with_next:
        ep["next_observations"] = _concat_obs(demo["next_obs"], keys, path, object_order)
    steps = {k: v.shape[0] for k, v in ep.items()}
    if len(set(steps.values())) != 1:
        raise SpotError(
            f"dataset file '{path}': '{demo.name.lstrip('/')}' has rows {steps}; expected the "
            "same number of steps for every key"
        )
    ep["timeouts"] = np.zeros(steps["actions"], bool)
    ep["timeouts"][-1] = True
    return ep


# --------------------------------------------------------------------------- Minari
def _flat(value: Any, steps: int, where: str) -> np.ndarray:
    """Episode observations or actions as ``[steps, dim]``; dicts flatten in sorted key order."""
    if isinstance(value, dict):
        return np.concatenate([_flat(value[k], steps, where) for k in sorted(value)], axis=1)
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_) or arr.shape[:1] != (steps,):
        raise SpotError(
            f"{where}: got an array of shape {arr.shape} and dtype {arr.dtype}; expected "
            f"{steps} numeric rows (Box, Discrete or Dict spaces)"
        )
    return arr.reshape(steps, -1).astype(np.float32)


def read_minari(dataset_id_or_path: str | Path) -> RawDataset:
    """Read a Minari dataset by id (from ``MINARI_DATASETS_PATH``, no download) or by folder.

    Each episode's ``observations`` has one more row than its steps: rows ``[:-1]`` are the
    observations and rows ``[1:]`` the next observations. ``terminations`` become ``terminals``
    and ``truncations`` become ``timeouts``; an episode that ends with neither (collection stopped
    mid-episode) gets a timeout so that episodes stay separate.
    """
    try:
        import minari
    except ImportError:
        raise SpotError(
            "reading Minari datasets needs the optional 'minari' package: pip install 'spot-pbrl[minari]'"
        ) from None
    source = str(dataset_id_or_path)
    folder = Path(dataset_id_or_path)
    try:
        if folder.is_dir():
            dataset = minari.MinariDataset(folder / "data" if (folder / "data").is_dir() else folder)
        else:
            dataset = minari.load_dataset(source)
    except (FileNotFoundError, ValueError, KeyError) as err:
        expected = (
            "a Minari dataset folder (with data/metadata.json)"
            if folder.is_dir()
            else f"a dataset id under MINARI_DATASETS_PATH (download it with `minari download {source}`)"
        )
        raise SpotError(f"Minari dataset '{source}' could not be loaded ({err}); expected {expected}") from None
    episodes = []
    for ep in dataset.iterate_episodes():
        steps = len(ep)
        where = f"Minari dataset '{source}', episode {ep.id}"
        obs = _flat(ep.observations, steps + 1, f"{where}, observations")
        timeouts = np.asarray(ep.truncations, bool).copy()
        terminals = np.asarray(ep.terminations, bool)
        timeouts[-1] |= not terminals[-1]
        episodes.append(
            {
                "observations": obs[:-1],
                "next_observations": obs[1:],
                "actions": _flat(ep.actions, steps, f"{where}, actions"),
                "rewards": np.asarray(ep.rewards, np.float32),
                "terminals": terminals,
                "timeouts": timeouts,
            }
        )
    if not episodes:
        raise SpotError(f"Minari dataset '{source}' has no episodes")
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in episodes[0]}
    try:
        return RawDataset(**cat, name=dataset.id, metadata={"format": "minari", "minari_id": dataset.id})
    except SpotError as err:
        raise SpotError(f"Minari dataset '{source}': {err}") from None


# --------------------------------------------------------------------------- dispatch
def detect_format(path: str | Path, limits: ReadLimits | None = None) -> str:
    """``minari`` for a folder, else ``robomimic`` (hdf5 with ``data/demo_*``) or ``d4rl``
    (hdf5 with ``observations``); the hdf5 file is checked first (:func:`~spot.data.hdf5_checks.check_hdf5`)."""
    path = Path(path)
    if path.is_dir():
        return "minari"
    with open_hdf5(path, limits) as f:
        return _detect(f, path)


def _detect(f: h5py.File, path: Path) -> str:
    data = f.get("data")
    if isinstance(data, h5py.Group) and any(k.startswith("demo_") for k in data.keys()):
        return "robomimic"
    if "observations" in f:
        return "d4rl"
    raise SpotError(
        f"dataset file '{path}': top-level keys {sorted(f.keys())}; expected 'observations' "
        "(D4RL layout) or 'data/demo_N' groups (robomimic layout)"
    )


def load_dataset_file(path: str | Path, format: str = "auto", limits: ReadLimits | None = None) -> RawDataset:
    """Read a dataset file in the given format, or the detected one (see :func:`detect_format`).

    ``format="minari"`` also accepts a Minari dataset id instead of a path. hdf5 files are
    checked by :func:`~spot.data.hdf5_checks.check_hdf5` against ``limits`` (default
    :data:`~spot.data.hdf5_checks.DEFAULT_LIMITS`) before anything is read.
    """
    if format not in FORMATS:
        raise SpotError(f"unknown dataset format '{format}'; expected one of {', '.join(FORMATS)}")
    if format == "auto":
        path = Path(path)
        if not path.exists():
            raise SpotError(f"dataset file '{path}' does not exist")
        if path.is_dir():
            return read_minari(path)
        with open_hdf5(path, limits) as f:  # opened and checked once, then detected and read
            if _detect(f, path) == "robomimic":
                return _read_robomimic(f, path, ROBOMIMIC_OBS_KEYS)
            return _read_d4rl(f, path)
    if format == "d4rl":
        return read_d4rl_hdf5(path, limits)
    if format == "robomimic":
        return read_robomimic_hdf5(path, limits=limits)
    return read_minari(path)
