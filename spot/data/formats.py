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

Every bad input raises :class:`SpotError` naming the file, the key and what was expected.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from spot import SpotError
from spot.data.dataset import RAW_KEYS, RawDataset

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
@dataclass(frozen=True)
class ReadLimits:
    """What an hdf5 dataset file may make the reader allocate, checked from the file's declared
    shapes and dtypes before any array is read (:func:`check_hdf5`).

    Attributes:
      memory_bytes: memory the arrays may take; None = the memory available now
        (:func:`available_memory`). The file's datasets need twice their declared size (the arrays
        read and their float32 copies).
      max_expansion: most declared bytes per byte a dataset stores in the file, for datasets over
        ``expansion_floor``. gzip cannot exceed about 1032:1, so only a compression bomb or chunks
        never written (read back as fill values) pass it.
      expansion_floor: datasets up to this many declared bytes are not ratio-checked (a small
        all-zero array compresses to almost nothing).
      max_links: most links (groups, datasets, soft links) a file may hold; robomimic's mh files
        hold about 15,000.
    """

    memory_bytes: int | None = None
    max_expansion: float = 1100.0
    expansion_floor: int = 64 << 20
    max_links: int = 200_000


DEFAULT_LIMITS = ReadLimits()
# HDF5's own filters (gzip, shuffle, fletcher32, szip, nbit, scaleoffset) and h5py's lzf: a file
# naming another filter would make HDF5 look for a plugin library to run.
_BUILTIN_FILTERS = {1: "gzip", 2: "shuffle", 3: "fletcher32", 4: "szip", 5: "nbit", 6: "scaleoffset", 32000: "lzf"}


def available_memory() -> int:
    """Bytes of memory available to this process now: psutil's ``available`` (else free pages from
    ``os.sysconf``), lowered to what the cgroup (a container's limit) still allows."""
    try:
        import psutil

        avail = int(psutil.virtual_memory().available)
    except ImportError:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            avail = min(avail, max(int(limit) - used, 0))
    except (OSError, ValueError):
        pass
    return avail


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"


def _soft_target_error(f: h5py.File, name: str, target: str, depth: int = 0) -> str | None:
    """Why the soft link ``name`` -> ``target`` may not be read (it dangles, loops, or reaches
    another file through an external link), or None: it names an object of this file."""
    if depth > 16:
        return "is a chain of more than 16 soft links (a loop)"
    parent = name.rsplit("/", 1)[0] if "/" in name else ""
    where = "" if target.startswith("/") else parent
    for part in [p for p in target.split("/") if p not in ("", ".")]:
        here = f"{where}/{part}" if where else part
        group = f[where] if where else f
        link = group.get(part, getlink=True) if isinstance(group, h5py.Group) else None
        if link is None:
            return f"points to '{target}', which does not exist in the file (a dangling link)"
        if isinstance(link, h5py.ExternalLink):
            return f"points to '{target}', which passes through an external link to file '{link.filename}'"
        if isinstance(link, h5py.SoftLink):
            why = _soft_target_error(f, here, link.path, depth + 1)
            if why is not None:
                return why
        where = here  # a checked soft link is then followed by HDF5 itself
    return None


def _link_error(f: h5py.File, name: str) -> str | None:
    """Why the link ``name`` may not be read, or None."""
    link = f.get(name, getlink=True)
    if isinstance(link, h5py.ExternalLink):
        return (
            f"'{name}' is an external link to '{link.filename}:{link.path}'; expected every array inside "
            "the file (external links are refused)"
        )
    if isinstance(link, h5py.SoftLink):
        why = _soft_target_error(f, name, link.path)
        if why is not None:
            return f"soft link '{name}' {why}; expected links inside the file"
    return None


def _check_links(f: h5py.File, path: Path, limits: ReadLimits) -> None:
    """Refuse external links, soft links that dangle or leave the file, and too many links.

    The walk is HDF5's own (``H5Lvisit``, which follows no soft or external link), through h5py's
    low-level API: a robomimic mh file's 15,000 links take a tenth of a second. Its callback must
    not raise, so the walk stops at the first problem, which is raised after it.
    """
    count, problem = 0, []
    soft_or_external = (h5py.h5l.TYPE_SOFT, h5py.h5l.TYPE_EXTERNAL)

    def visit(name: bytes, info: Any) -> bool | None:
        nonlocal count
        count += 1
        if count > limits.max_links:
            return True
        if info.type in soft_or_external:
            why = _link_error(f, name.decode("utf-8", errors="replace"))
            if why is not None:
                problem.append(why)
                return True
        return None

    f.id.links.visit(visit, info=True)
    if problem:
        raise SpotError(f"dataset file '{path}': {problem[0]}")
    if count > limits.max_links:
        raise SpotError(
            f"dataset file '{path}' holds more than {limits.max_links} links (groups and arrays); "
            "expected a D4RL or robomimic file"
        )


def _check_layout(name: str, dsid: Any, path: Path) -> None:
    """Refuse a virtual dataset, external storage and unknown filters. ``dsid``: the dataset's
    low-level ``h5py.h5d.DatasetID``."""
    plist = dsid.get_create_plist()
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        raise SpotError(
            f"dataset file '{path}': '{name}' is a virtual dataset (VDS) mapping other files; "
            "expected arrays stored in the file"
        )
    if plist.get_external_count() > 0:
        target = plist.get_external(0)[0].decode(errors="replace")
        raise SpotError(
            f"dataset file '{path}': '{name}' stores its data in the external file '{target}'; "
            "expected arrays stored in the file (HDF5 external storage is refused)"
        )
    for i in range(plist.get_nfilters()):
        code = plist.get_filter(i)[0]
        if code not in _BUILTIN_FILTERS:
            raise SpotError(
                f"dataset file '{path}': '{name}' is compressed with HDF5 filter {code}; expected one of "
                f"{', '.join(sorted(_BUILTIN_FILTERS.values()))} (filter plugins are not loaded)"
            )


def check_hdf5(f: h5py.File, path: Path, limits: ReadLimits = DEFAULT_LIMITS) -> None:
    """Check an open hdf5 file before reading anything from it; :class:`SpotError` names the file
    and the dataset path.

    Refused: external links, soft links that dangle or reach another file, datasets with HDF5
    external storage, virtual datasets, filters other than HDF5's built-in ones and lzf, a
    dataset whose declared size exceeds ``limits.max_expansion`` times what it stores, and files
    whose datasets declare more than the memory available (``limits.memory_bytes``) can hold.
    Every dataset of the file counts, read or not.
    """
    _check_links(f, path, limits)
    names: list[bytes] = []

    def visit(name: bytes, info: Any) -> None:  # H5Ovisit: each object once, hard links only
        if info.type == h5py.h5o.TYPE_DATASET:
            names.append(name)

    h5py.h5o.visit(f.id, visit, info=True)
    sizes = {}  # name -> (declared bytes, stored bytes, shape, dtype)
    for raw_name in names:
        dsid = h5py.h5d.open(f.id, raw_name)
        name = raw_name.decode("utf-8", errors="replace")
        _check_layout(name, dsid, path)
        declared = int(np.prod(dsid.shape, dtype=object)) * int(dsid.dtype.itemsize)  # exact: no overflow
        sizes[name] = (declared, int(dsid.get_storage_size()), dsid.shape, dsid.dtype)
    total = sum(size[0] for size in sizes.values())
    budget = limits.memory_bytes if limits.memory_bytes is not None else available_memory()
    if sizes and 2 * total > budget:
        name, (declared, _, shape, dtype) = max(sizes.items(), key=lambda kv: kv[1][0])
        raise SpotError(
            f"dataset file '{path}': '{name}' declares shape {shape} of {dtype} ({_size(declared)}); "
            f"reading the file's arrays needs {_size(2 * total)} (twice their {_size(total)}) but "
            f"{_size(budget)} of memory is available; expected a file that fits in memory"
        )
    for name, (declared, stored, shape, dtype) in sizes.items():
        if declared > limits.expansion_floor and declared > limits.max_expansion * stored:
            raise SpotError(
                f"dataset file '{path}': '{name}' declares shape {shape} of {dtype} ({_size(declared)}) but "
                f"stores {_size(stored)} in the file; expected at most {limits.max_expansion:g} times its "
                "stored size (a compression bomb, or chunks never written)"
            )


def _open_hdf5(path: Path, limits: ReadLimits | None = None) -> h5py.File:
    """Open ``path`` read-only and run :func:`check_hdf5` on it before anything else reads it."""
    if not path.exists():
        raise SpotError(f"dataset file '{path}' does not exist")
    if not path.is_file():
        raise SpotError(f"dataset file '{path}' is not a regular file; expected an hdf5 file")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise SpotError(f"dataset file '{path}' is not a readable hdf5 file ({err})") from None
    try:
        check_hdf5(f, path, limits or DEFAULT_LIMITS)
    except BaseException:
        f.close()
        raise
    return f


def _array(group: h5py.Group, key: str, path: Path, rank: int | None = None) -> np.ndarray:
    """A real numeric array ``group[key]`` (integers, floats or bools), or :class:`SpotError`
    naming file and key. The file has passed :func:`check_hdf5` (opened by :func:`_open_hdf5`)."""
    where = f"{group.name.rstrip('/')}/{key}".lstrip("/")
    if key not in group:
        raise SpotError(f"dataset file '{path}': missing key '{where}'; found {sorted(group.keys())}")
    node = group[key]
    if not isinstance(node, h5py.Dataset):
        raise SpotError(f"dataset file '{path}': '{where}' is a group; expected an array")
    if node.dtype.kind not in "biuf":
        raise SpotError(
            f"dataset file '{path}': '{where}' has dtype {node.dtype}; expected numbers (real: integers, "
            "floats or bools)"
        )
    if rank is not None and node.ndim != rank:
        raise SpotError(f"dataset file '{path}': '{where}' has shape {node.shape}; expected rank {rank}")
    try:
        return node[()]
    except OSError as err:  # damaged chunks, a filter that fails
        raise SpotError(f"dataset file '{path}': '{where}' cannot be read ({err})") from None


def _check_rows(group: h5py.Group, keys: list[str], path: Path) -> None:
    """The declared first dimension of every array ``keys`` present in ``group`` is the same
    (checked before reading: a file whose arrays disagree is refused without loading them)."""
    rows = {k: group[k].shape[0] for k in keys if isinstance(group.get(k), h5py.Dataset) and group[k].ndim >= 1}
    first = next(iter(rows.items()), None)
    for key, n in rows.items():
        if first is not None and n != first[1]:
            raise SpotError(
                f"dataset file '{path}': '{key}' has {n} rows but '{first[0]}' has {first[1]}; "
                "expected one row per step in every array"
            )


def _flags(arr: np.ndarray, key: str, path: Path) -> np.ndarray:
    """A 0/1 flag array (terminals, timeouts, dones) as bool; any other value is an error (a 3.5
    would otherwise read as True)."""
    if arr.dtype != np.bool_:
        bad = np.flatnonzero((arr != 0) & (arr != 1))
        if bad.size:
            raise SpotError(
                f"dataset file '{path}': '{key}' has the value {arr[bad[0]].item()!r} at row {int(bad[0])} "
                f"({bad.size} rows not 0/1); expected flags 0 or 1"
            )
    return arr.astype(bool)


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
    """Read a D4RL-layout hdf5 file, checked first by :func:`check_hdf5`.

    Args:
      path: the ``.hdf5`` file.
      limits: what the file may make the reader allocate; default :data:`DEFAULT_LIMITS`.

    Returns:
      The raw dataset named after the file stem, observations/actions/rewards as float32 and the
      flags as bool; ``metadata`` holds the file's attributes and ``metadata`` group scalars.
    """
    path = Path(path)
    with _open_hdf5(path, limits) as f:
        return _read_d4rl(f, path)


def _read_d4rl(f: h5py.File, path: Path) -> RawDataset:
    """:func:`read_d4rl_hdf5` of a file opened and checked by :func:`_open_hdf5`."""
    ranks = {"observations": 2, "actions": 2, "rewards": 1, "terminals": 1, "timeouts": 1}
    _check_rows(f, [*ranks, "next_observations"], path)
    arrays = {key: _array(f, key, path, rank) for key, rank in ranks.items()}
    next_obs = _array(f, "next_observations", path, 2) if "next_observations" in f else None
    infos = _d4rl_infos(f, arrays["rewards"].shape[0], path)
    metadata = _d4rl_metadata(f, path)
    return _raw_dataset(
        path,
        observations=arrays["observations"].astype(np.float32),
        actions=arrays["actions"].astype(np.float32),
        rewards=arrays["rewards"].astype(np.float32),
        terminals=_flags(arrays["terminals"], "terminals", path),
        timeouts=_flags(arrays["timeouts"], "timeouts", path),
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
        key: _array(group, key, path)
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
        part = _array(group, k, path)
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
      limits: what the file may make the reader allocate (:func:`check_hdf5`); default
        :data:`DEFAULT_LIMITS`.

    Returns:
      The raw dataset; ``metadata`` has ``env_name``, ``env_args``, ``obs_keys`` and
      ``object_reordered`` (whether the ``object`` block was reordered).
    """
    path = Path(path)
    keys = tuple(obs_keys) if obs_keys is not None else ROBOMIMIC_OBS_KEYS
    with _open_hdf5(path, limits) as f:
        return _read_robomimic(f, path, keys)


def _read_robomimic(f: h5py.File, path: Path, keys: tuple[str, ...]) -> RawDataset:
    """:func:`read_robomimic_hdf5` of a file opened and checked by :func:`_open_hdf5`."""
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
        "actions": _array(demo, "actions", path, 2),
        "rewards": _array(demo, "rewards", path, 1),
        "terminals": _flags(_array(demo, "dones", path, 1), f"{demo.name.lstrip('/')}/dones", path),
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
    (hdf5 with ``observations``); the hdf5 file is checked first (:func:`check_hdf5`)."""
    path = Path(path)
    if path.is_dir():
        return "minari"
    with _open_hdf5(path, limits) as f:
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
    checked by :func:`check_hdf5` against ``limits`` (default :data:`DEFAULT_LIMITS`) before
    anything is read.
    """
    if format not in FORMATS:
        raise SpotError(f"unknown dataset format '{format}'; expected one of {', '.join(FORMATS)}")
    if format == "auto":
        path = Path(path)
        if not path.exists():
            raise SpotError(f"dataset file '{path}' does not exist")
        if path.is_dir():
            return read_minari(path)
        with _open_hdf5(path, limits) as f:  # opened and checked once, then detected and read
            if _detect(f, path) == "robomimic":
                return _read_robomimic(f, path, ROBOMIMIC_OBS_KEYS)
            return _read_d4rl(f, path)
    if format == "d4rl":
        return read_d4rl_hdf5(path, limits)
    if format == "robomimic":
        return read_robomimic_hdf5(path, limits=limits)
    return read_minari(path)
