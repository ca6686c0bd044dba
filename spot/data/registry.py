"""Dataset names -> local recipes or files, and the dataset cache.

A name like ``hopper-medium-replay`` (a trailing ``-v2`` is accepted) resolves to a local recipe
that builds the dataset in the real simulator and writes it, in the D4RL hdf5 layout, to the cache
dir ``$SPOT_DATA_DIR`` (default ``~/.cache/spot/data``). A path to an existing file is read as
it is (D4RL hdf5, robomimic hdf5). Built files are keyed by ``(name, size, seed)`` and built once;
a build writes to a temporary name and renames, under a file lock, so concurrent trials of a sweep
neither corrupt nor duplicate it. A recipe module that defines ``RECIPE_VERSION`` stores it in the
card, and a cached build whose card holds another version (or none) is stale and rebuilt; a recipe
whose datasets differ in version (e.g. by size) defines ``recipe_version(name, size)`` instead.

A build spot ships (:mod:`spot.data.embedded`: the quickstart's ``hopper-medium-replay``, size
``small``, seed 0) is copied in instead of built, when its card's recipe, recipe version and package
versions are the installed ones and its sha256 checks; ``build(..., from_recipe=True)`` (``spot data
build --from-recipe``) runs the recipe all the same. A card says how its file was ``obtained``:
``built`` here or copied from the ``embedded`` build; the hdf5 file holds only the data and the
card's data fields, so two builds of equal data are equal bytes.
"""

from __future__ import annotations

import difflib
import fcntl
import importlib
import json
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spot import SpotError, runtime, store
from spot.data import build_child, embedded
from spot.data.dataset import Dataset, RawDataset


@dataclass(frozen=True)
class Entry:
    name: str
    family: str  # locomotion | metaworld | robosuite
    recipe: str  # module under spot.recipes
    description: str
    pt_label_folder: str = ""  # folder name of the PT human labels for the real D4RL dataset


_LOCO = {
    "medium": "rollouts of the SAC snapshot at ~1/3 of the expert return",
    "medium-replay": "SAC replay buffer up to the medium snapshot",
    "expert": "rollouts of the final SAC policy",
    "medium-expert": "medium + expert",
    "full-replay": "SAC replay buffer up to the expert snapshot (D4RL's full-replay)",
}
_MW = {
    "drawer-open": "Meta-World drawer-open-v3, IPL recipe (scripted expert + noise, random, other tasks)",
    "plate-slide": "Meta-World plate-slide-v3, IPL recipe",
    "button-press": "Meta-World button-press-v3, IPL recipe",
}
_ROBO = {
    "lift-ph": "robosuite Lift, one proficient scripted operator (robomimic ph style, 200 demos)",
    "lift-mh": "robosuite Lift, six scripted operators of mixed skill (robomimic mh style, 300 demos)",
    "can-ph": "robosuite PickPlaceCan, one proficient scripted operator (ph style, 200 demos)",
    "can-mh": "robosuite PickPlaceCan, six scripted operators of mixed skill (mh style, 300 demos)",
}

REGISTRY: dict[str, Entry] = {}
for _env in ("hopper", "walker2d"):
    for _kind, _desc in _LOCO.items():
        _name = f"{_env}-{_kind}"
        _folder = f"{_name}-v2" if _kind in ("medium-replay", "medium-expert") else ""
        REGISTRY[_name] = Entry(_name, "locomotion", "locomotion", f"{_env} (gymnasium v5): {_desc}", _folder)
for _name, _desc in _MW.items():
    REGISTRY[_name] = Entry(_name, "metaworld", "metaworld", _desc)
for _name, _desc in _ROBO.items():
    REGISTRY[_name] = Entry(_name, "robosuite", "robosuite", _desc)

SIZES = ("tiny", "small", "paper", "paper-fast")  # paper-fast: locomotion only


# The real files' names, as their publishers name them and `spot data fetch` writes them
# (spot/data/sources.json, docs/datasets.md): D4RL's ``<env>_<kind>-v2.hdf5``, the kind's hyphens
# written as underscores (gym_mujoco_v2 on D4RL's server: ``hopper_medium_replay-v2.hdf5``), and
# robomimic's ``<task>/<ph|mh>/low_dim.hdf5`` (v0.1; robosuite 1.5 files: ``low_dim_v15.hdf5``).
D4RL_FILE_STEMS: dict[str, str] = {
    f"{env}_{kind.replace('-', '_')}-v2": f"{env}-{kind}-v2"
    for env in ("hopper", "walker2d", "halfcheetah")
    for kind in ("random", "medium", "expert", "medium-replay", "medium-expert", "full-replay")
}
ROBOMIMIC_ENV_NAMES = {"lift": "Lift", "can": "PickPlaceCan"}  # task folder -> env_args["env_name"]
ROBOMIMIC_KINDS = ("ph", "mh")


def canonical(name: str) -> str:
    """``hopper-medium-replay-v2`` (or D4RL's file stem ``hopper_medium_replay-v2``) ->
    ``hopper-medium-replay``."""
    name = D4RL_FILE_STEMS.get(name.strip(), name)
    base = name[:-3] if name.endswith(("-v2", "-v3")) else name
    return base


def file_dataset_name(path: str | Path) -> str | None:
    """The dataset a real file is, from its name and folders; None for any other file.

    D4RL ``.../hopper_medium_replay-v2.hdf5`` (or ``hopper-medium-replay-v2.hdf5``) ->
    ``hopper-medium-replay-v2``; robomimic ``.../lift/ph/low_dim.hdf5`` -> ``lift-ph``.
    """
    path = Path(path)
    if path.stem in D4RL_FILE_STEMS:
        return D4RL_FILE_STEMS[path.stem]
    if path.stem in D4RL_FILE_STEMS.values():
        return path.stem
    if path.stem.startswith("low_dim"):
        task, kind = path.parent.parent.name.lower(), path.parent.name.lower()
        if task in ROBOMIMIC_ENV_NAMES and kind in ROBOMIMIC_KINDS:
            return f"{task}-{kind}"
    return None


def entry(name: str) -> Entry:
    base = canonical(name)
    if base not in REGISTRY:
        close = difflib.get_close_matches(base, list(REGISTRY), n=3, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise SpotError(
            f"unknown dataset '{name}'{hint} Known names: {', '.join(REGISTRY)} "
            "(or give a path to a D4RL/robomimic hdf5 file)"
        )
    return REGISTRY[base]


def data_dir() -> Path:
    return runtime.data_dir()


def dataset_path(name: str, size: str, seed: int) -> Path:
    return data_dir() / f"{canonical(name)}__{size}__seed{seed}.hdf5"


def card_path(path: Path) -> Path:
    return path.with_suffix(".card.json")


@contextmanager
def _lock(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".lock"), "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


STALE_TEMP_S = 600.0  # a temp file of a dead process is removed once this old (another host may share the dir)
_VERIFIED: set[tuple[str, int, int]] = set()  # (path, mtime_ns, size) of files this process verified


def clean_stale_temp(folder: Path, min_age_s: float = STALE_TEMP_S) -> list[Path]:
    """Remove ``*.tmp-<pid>`` files in ``folder`` left by killed writers: the process ``pid`` no
    longer runs here and the file is older than ``min_age_s`` (the age guards a writer on another
    host sharing the folder). Returns the removed paths."""
    import re

    removed = []
    if not folder.is_dir():
        return removed
    for tmp in folder.iterdir():
        m = re.search(r"\.tmp-(\d+)$", tmp.name)
        if m is None or not tmp.is_file() or int(m[1]) == os.getpid():
            continue
        if runtime.pid_alive(int(m[1])):
            continue
        try:
            if time.time() - tmp.stat().st_mtime >= min_age_s:
                tmp.unlink()
                removed.append(tmp)
        except FileNotFoundError:
            pass
    return removed


def _damage(path: Path, card: dict[str, Any], record: bool = True) -> str | None:
    """Why the built file ``path`` cannot be used, or None. A card with ``sha256`` is checked against
    the file's; a card from before checksums (none recorded) is checked by reading the file, and
    gets the checksum recorded when it reads."""
    from spot.data import formats
    from spot.data.fetch import sha256_file

    st = path.stat()
    stamp = (str(path), st.st_mtime_ns, st.st_size)
    if stamp in _VERIFIED:
        return None
    want = card.get("sha256")
    if want is not None:
        if card.get("bytes") is not None and card["bytes"] != st.st_size:
            return f"{st.st_size} bytes; its card records {card['bytes']}"
        got = sha256_file(path)
        if got != want:
            return f"sha256 {got}; its card records {want}"
    else:
        try:
            formats.read_d4rl_hdf5(path)
        except SpotError as err:
            return str(err)
        if not record:  # a listing reads without the build lock: it leaves the card alone
            return None
        _write_card(path, {**card, "sha256": sha256_file(path), "bytes": st.st_size})
    _VERIFIED.add(stamp)
    return None


def _write_card(path: Path, card: dict[str, Any]) -> None:
    """Write the card of ``path`` atomically (a full disk: SpotError, no temporary file left)."""
    store.write_atomic(card_path(path), json.dumps(card, indent=2, default=str).encode())


def build(
    name: str,
    size: str = "small",
    seed: int = 0,
    *,
    progress: bool = True,
    force: bool = False,
    from_recipe: bool = False,
) -> Path:
    """Make a registered dataset (once) and return the file path: the embedded copy where spot
    ships this build (:mod:`spot.data.embedded`, byte-equal to the recipe's, verified), else a build
    with its local recipe.

    A cached file is reused unless ``force``, its card's ``recipe_version`` differs from the
    recipe's (:func:`_version`: its ``recipe_version(name, size)`` or ``RECIPE_VERSION``; recipes
    without either are never stale), the file is damaged (its sha256, recorded in the card,
    differs, or, for a card from before checksums, it does not read), or ``from_recipe`` and the
    file is the embedded copy. ``force`` and ``from_recipe`` run the recipe instead of copying the
    embedded file. Temp files of killed builds are removed first. Where ``SPOT_FAST_COMPILE``'s
    XLA flags are on, the recipe runs in a child process without them (:mod:`spot.data.build_child`)
    while this process holds the locks.
    """
    e = entry(name)
    if size not in SIZES:
        raise SpotError(f"unknown size '{size}'; expected one of {', '.join(SIZES)}")
    recipe_sizes = getattr(importlib.import_module(f"spot.recipes.{e.recipe}"), "SIZES", SIZES)
    if size not in recipe_sizes:
        raise SpotError(
            f"size '{size}' is not built for dataset '{e.name}' ({e.recipe} recipe); its sizes: "
            f"{', '.join(recipe_sizes)}"
        )
    path = dataset_path(e.name, size, seed)
    store.writable_dir(path.parent, "$SPOT_DATA_DIR")  # read-only, or a file: one clear error
    with _lock(path), store.dataset_lock(path):  # the shared store (spot.store): built once, on one node
        clean_stale_temp(path.parent)
        store.fetch_dataset(path, card_path(path))  # a build another node uploaded
        recipe = importlib.import_module(f"spot.recipes.{e.recipe}")
        version = _version(recipe, e.name, size)
        if path.exists() and card_path(path).exists() and not force:
            card, why = _reusable(path, version)
            if why is None and from_recipe and card is not None and card.get("obtained") == "embedded":
                why = "it is the embedded copy, and a build from the recipe was asked for"
            if why is None:
                store.publish_dataset(path, card_path(path), if_missing=True)  # built before the store was named
                return path
            if progress or "damaged" in why:
                print(f"spot: rebuilding {path.name}: {why}", file=sys.stderr)
        copied = None
        if not (force or from_recipe):
            copied = embedded.copy_in(
                e.name, size, seed, path, getattr(recipe, "RECIPE", None), version, progress=progress
            )
        if copied is None and build_child.needed():  # fast compile's XLA flags change the data
            build_child.run(e.name, size, seed, progress)
            if not (path.exists() and card_path(path).exists()):
                raise SpotError(f"dataset {e.name} ({size}, seed {seed}): its build process wrote no {path}")
        elif copied is None:
            _build_here(recipe, e.name, size, seed, path, version, progress)
        st = path.stat()
        _VERIFIED.add((str(path), st.st_mtime_ns, st.st_size))
        store.publish_dataset(path, card_path(path))
    return path


def _build_here(recipe: Any, name: str, size: str, seed: int, path: Path, version: Any, progress: bool) -> None:
    """Run the recipe (or join the built parts of a composite) and write ``path`` and its card: the
    hdf5 file holds the data and :func:`spot.data.embedded.data_card` (equal data, equal bytes), the
    card file also the build's facts (times, memory, :func:`spot.data.embedded.host_facts`, the
    ``XLA_FLAGS`` it ran under: ``SPOT_FAST_COMPILE``'s flags change the data)."""
    from spot.data import formats
    from spot.data.fetch import sha256_file

    joined = _join_parts(recipe, name, size, seed, progress)
    raw, card = joined or recipe.build(name, size, seed, data_dir() / "_work", progress=progress)
    card = {**card, "name": name, "size": size, "seed": seed, "source": "recipe"}
    if version is not None:
        card["recipe_version"] = version
    formats.write_d4rl_hdf5(raw, path, embedded.data_card(card))
    facts = {"obtained": "built", "host": embedded.host_facts(), "xla_flags": os.environ.get("XLA_FLAGS", "")}
    _write_card(path, {**card, **facts, "sha256": sha256_file(path), "bytes": path.stat().st_size})


def build_unlocked(name: str, size: str, seed: int, progress: bool = True) -> None:
    """Build ``name`` with its recipe here, taking no lock: for :mod:`spot.data.build_child`, whose
    parent holds the dataset's locks (anyone else calls :func:`build`)."""
    e = entry(name)
    recipe = importlib.import_module(f"spot.recipes.{e.recipe}")
    _build_here(recipe, e.name, size, seed, dataset_path(e.name, size, seed), _version(recipe, e.name, size), progress)


def _version(recipe: Any, name: str, size: str) -> Any:
    """The recipe version a build of ``name`` at ``size`` records: the recipe's
    ``recipe_version(name, size)`` if it has one, else its ``RECIPE_VERSION`` (None: never stale)."""
    per_dataset = getattr(recipe, "recipe_version", None)
    return per_dataset(name, size) if per_dataset is not None else getattr(recipe, "RECIPE_VERSION", None)


def _reusable(path: Path, version: Any) -> tuple[dict[str, Any] | None, str | None]:
    """The card of the built file ``path`` (file and card present) and why it cannot be reused:
    a card that is not a JSON object, another recipe version, or damage; None when it can."""
    card = _card_or_none(path)
    if card is None:
        return None, f"its card {card_path(path)} is not a JSON object"
    built = card.get("recipe_version")
    if version is not None and built != version:
        return card, f"it was built by recipe version {built}; rebuilding with version {version}"
    why = _damage(path, card)
    return card, None if why is None else f"it is damaged ({why})"


def _join_parts(
    recipe: Any, name: str, size: str, seed: int, progress: bool
) -> tuple[RawDataset, dict[str, Any]] | None:
    """A composite dataset (one the recipe's ``composite_parts`` names parts for, e.g.
    ``hopper-medium-expert``) joined from its parts when every part is built (here, or in the shared
    store: fetched), current and undamaged; None otherwise, and then the recipe builds it whole.
    The card's ``build_time_s`` covers reading and checking the parts too."""
    from spot.data import formats

    parts_of = getattr(recipe, "composite_parts", None)
    names = parts_of(name) if parts_of is not None else []
    if not names:
        return None
    start = time.perf_counter()
    parts = []
    for part in names:
        version = _version(recipe, part, size)
        path = dataset_path(part, size, seed)
        with _lock(path), store.dataset_lock(path):
            store.fetch_dataset(path, card_path(path))
            if not (path.exists() and card_path(path).exists()):
                return None
            card, why = _reusable(path, version)
            if why is not None:
                return None
            parts.append((formats.read_d4rl_hdf5(path), card))
    joined = recipe.join(name, size, seed, data_dir() / "_work", parts, progress=progress)
    if joined is None:
        return None
    joined[1]["build_time_s"] = round(time.perf_counter() - start, 2)
    if progress:
        print(f"spot: {name} ({size}, seed {seed}) joined from the built {' and '.join(names)}", file=sys.stderr)
    return joined


def _card_or_none(path: Path) -> dict[str, Any] | None:
    try:
        card = json.loads(card_path(path).read_text())
    except (OSError, ValueError):
        return None
    return card if isinstance(card, dict) else None


def read_card(path: Path) -> dict[str, Any]:
    """The card of a built file (``{}`` if none); :class:`SpotError` if it is not a JSON object."""
    cp = card_path(path)
    if not cp.exists():
        return {}
    card = _card_or_none(path)
    if card is None:
        raise SpotError(f"dataset card '{cp}' is not a JSON object; rebuild with `spot data build --force`")
    return card


def load_raw(
    name: str, size: str = "small", seed: int = 0, *, source: str = "auto", progress: bool = True
) -> tuple[RawDataset, dict[str, Any]]:
    """A registered name (built if missing) or a file path -> (raw dataset, card)."""
    from spot.data import formats

    as_path = Path(name).expanduser()
    if source == "file" or (source == "auto" and as_path.exists()):
        if not as_path.exists():
            raise SpotError(f"dataset file '{name}' does not exist")
        from spot.data.fetch import verify_fetched

        verify_fetched(as_path)  # a file from `spot data fetch`: recheck its size and sha256
        raw = formats.load_dataset_file(as_path)
        real = file_dataset_name(as_path)
        _check_robomimic_task(raw, real, as_path)
        card = {
            "name": real or as_path.stem,  # D4RL's and robomimic's file names resolve (evaluation env, labels)
            "source": "file",
            "path": str(as_path.resolve()),
            **raw.metadata.get("spot_card", {}),
        }
        card["source"] = "file"
        return raw, card
    path = build(name, size, seed, progress=progress)
    raw = formats.read_d4rl_hdf5(path)
    return raw, read_card(path)


def _check_robomimic_task(raw: RawDataset, real: str | None, path: Path) -> None:
    """A robomimic file under ``<task>/<kind>/`` must record that task's env in its ``env_args``."""
    if real is None or raw.metadata.get("format") != "robomimic":
        return
    want = ROBOMIMIC_ENV_NAMES[real.split("-")[0]]
    if raw.metadata.get("env_name") != want:
        raise SpotError(
            f"dataset file '{path}': 'data.attrs[env_args]' names env {raw.metadata.get('env_name')!r}; "
            f"expected '{want}' for a file under {path.parent.parent.name}/{path.parent.name}/"
        )


def load(
    name: str, size: str = "small", seed: int = 0, *, source: str = "auto", progress: bool = True
) -> tuple[Dataset, dict[str, Any]]:
    """Like :func:`load_raw` but returns the ``qlearning_dataset`` view."""
    raw, card = load_raw(name, size, seed, source=source, progress=progress)
    try:
        ds = raw.qlearning()
    except SpotError as err:
        raise SpotError(f"dataset file '{card['path']}': {err}" if card.get("path") else str(err)) from None
    return ds.replace(name=card.get("name") or ds.name), card


def cached() -> list[dict[str, Any]]:
    """Every built dataset in the cache dir, with its card and ``status``: ``ok``, or why it is
    unusable (no card, damaged: it is rebuilt when next used)."""
    out = []
    for path in sorted(data_dir().glob("*.hdf5")):
        card = _card_or_none(path)
        if card is None:
            status = "no readable card (rebuilt when used)"
        else:
            why = _damage(path, card, record=False)
            status = "ok" if why is None else f"damaged: {why} (rebuilt when used)"
        card = card or {}
        keys = ("name", "size", "seed", "transitions", "episodes", "obtained")
        out.append({"path": str(path), **{k: card.get(k) for k in keys}, "status": status})
    return out
