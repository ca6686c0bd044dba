"""Datasets shipped inside the package, byte-equal to what their recipe builds, and the build facts
their bytes depend on.

The quickstart's dataset (``hopper-medium-replay``, size ``small``, seed 0) takes minutes to build
(SAC on Hopper in MuJoCo), yet it is a 1.4 MB file. Its build is shipped in this folder as
``<name>__<size>__seed<seed>.hdf5`` with its card (``.card.json``, the card the recipe wrote, with
``sha256`` and ``bytes``). When a dataset is needed and ``$SPOT_DATA_DIR`` lacks it,
:func:`spot.data.registry.build` asks :func:`copy_in`, which copies the shipped file in (under the
registry's build lock; written to a temporary name and renamed) when

* the card's ``recipe`` and ``recipe_version`` are the recipe's, and the versions of
  :data:`PACKAGES` it records are the installed ones (otherwise the recipe builds it, and one line
  on stderr says why), and
* the file's SHA-256 and size are the card's (otherwise: :class:`spot.SpotError` naming the
  shipped file; nothing is written).

The copy's card is the shipped card with ``"obtained": "embedded"`` (a build here says
``"built"``); its ``source`` stays ``recipe``: the bytes are the recipe's, so runs on the copy and
on a build here carry the same ``dataset_source`` tag and the same data digest. Nothing shipped
executes code: an hdf5 file and a JSON card.

Only data go into the hdf5 file, so that equal data give equal bytes: :func:`data_card` is the
card the file holds, without the build's facts (:data:`BUILD_FACTS`: times, memory, cache hits,
where it was built), which the card file beside it records. :func:`host_facts` are the host facts
the bytes may depend on (XLA compiles for the host's CPU features): a recipe build records them in
its card as ``host``, so that a build whose digest differs from the shipped one's can be explained
(docs/datasets.md, "The embedded quickstart dataset").
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from spot import SpotError, store

FOLDER = Path(__file__).resolve().parent
"""Where the shipped datasets are (tests point it elsewhere)."""
PACKAGES = ("gymnasium", "mujoco", "jax", "flax")
"""The packages whose versions must match the shipped card's for the copy to be used."""
BUILD_FACTS = frozenset(
    {"build_time_s", "train_time_s", "peak_rss_mb", "sac_cache_hit", "resumed_from", "host", "xla_flags", "obtained"}
)
"""Card keys (at any depth) that describe one build rather than its data: the card file has them,
the hdf5 file's card does not (:func:`data_card`)."""
MAX_BYTES = 8 * 1024 * 1024  # a shipped file larger than this is not read (the quickstart's: 1.4 MB)

# The CPU features (as /proc/cpuinfo names them) that compiled code may use: SIMD widths, fused
# multiply-add and the bit-manipulation extensions LLVM selects instructions from for the host.
_X86_ISA = (
    "sse",
    "ssse3",
    "avx",
    "fma",
    "f16c",
    "bmi",
    "amx",
    "popcnt",
    "abm",
    "movbe",
    "adx",
    "aes",
    "pclmulqdq",
    "vaes",
    "vpclmulqdq",
    "gfni",
    "sha_ni",
)


def _cpuinfo() -> dict[str, str]:
    """The first processor's fields of ``/proc/cpuinfo`` (empty where there is none)."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for line in text.split("\n\n", 1)[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_features() -> list[str]:
    """The CPU features XLA's compiled code may use on this host, sorted: the SIMD and
    bit-manipulation flags of x86 (:data:`_X86_ISA` prefixes), or every ``Features`` flag of an
    ARM CPU."""
    info = _cpuinfo()
    if "flags" in info:
        return sorted(f for f in info["flags"].split() if f.startswith(_X86_ISA))
    return sorted(info.get("Features", "").split())


def host_facts() -> dict[str, str]:
    """The facts of this host a build's bytes may depend on: ``machine`` (the architecture),
    ``cpu`` (model name, with family, model and stepping where the kernel gives them) and
    ``cpu_features``, a short hash (12 hex digits of SHA-256) of :func:`cpu_features`."""
    info = _cpuinfo()
    cpu = info.get("model name") or platform.processor() or "unknown"
    ids = [f"{k} {info[k]}" for k in ("cpu family", "model", "stepping") if k in info]
    if ids:
        cpu = f"{cpu} ({', '.join(ids)})"
    digest = hashlib.sha256(" ".join(cpu_features()).encode()).hexdigest()[:12]
    return {"machine": platform.machine(), "cpu": cpu, "cpu_features": digest}


def data_card(card: dict[str, Any]) -> dict[str, Any]:
    """``card`` without :data:`BUILD_FACTS` (at any depth): what the hdf5 file stores, so that two
    builds of equal data write equal bytes."""
    return {k: data_card(v) if isinstance(v, dict) else v for k, v in card.items() if k not in BUILD_FACTS}


def installed_versions() -> dict[str, str | None]:
    """The installed versions of :data:`PACKAGES` (None for one not installed)."""
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def shipped(name: str, size: str, seed: int, folder: Path | None = None) -> Path | None:
    """The shipped hdf5 file of ``(name, size, seed)``, or None when none is shipped."""
    path = (folder or FOLDER) / f"{name}__{size}__seed{seed}.hdf5"
    return path if path.is_file() else None


def read_card(path: Path) -> dict[str, Any]:
    """The card of the shipped file ``path``: a JSON object with ``sha256`` and ``bytes``;
    :class:`SpotError` naming the card otherwise."""
    cp = path.with_suffix(".card.json")
    try:
        card = json.loads(cp.read_text())
    except (OSError, ValueError) as err:
        raise SpotError(f"embedded dataset card '{cp}' does not read as JSON ({err}); reinstall spot") from None
    if not isinstance(card, dict) or not isinstance(card.get("sha256"), str) or not isinstance(card.get("bytes"), int):
        raise SpotError(
            f"embedded dataset card '{cp}': expected a JSON object with 'sha256' and 'bytes'; reinstall spot"
        )
    return card


def mismatch(card: dict[str, Any], recipe: str | None, recipe_version: Any) -> str | None:
    """Why the shipped build of ``card`` is not what the installed recipe and packages would build,
    or None: another recipe or recipe version, or another version of one of :data:`PACKAGES`."""
    if card.get("recipe") != recipe:
        return f"it was built by recipe {card.get('recipe')!r}, not {recipe!r}"
    if card.get("recipe_version") != recipe_version:
        return f"it was built by recipe version {card.get('recipe_version')}, not {recipe_version}"
    recorded = card.get("versions") if isinstance(card.get("versions"), dict) else {}
    for name, have in installed_versions().items():
        if recorded.get(name) != have:
            return f"it was built with {name} {recorded.get(name)}, and {name} {have} is installed"
    return None


def read_verified(path: Path, card: dict[str, Any]) -> bytes:
    """The bytes of the shipped file ``path``, checked against its ``card``'s size and SHA-256;
    :class:`SpotError` naming the file when they differ."""
    size = path.stat().st_size
    if size != card["bytes"] or size > MAX_BYTES:
        raise SpotError(
            f"embedded dataset '{path}' has {size} bytes; its card records {card['bytes']} "
            f"(at most {MAX_BYTES} are read); reinstall spot"
        )
    data = path.read_bytes()
    got = hashlib.sha256(data).hexdigest()
    if got != card["sha256"]:
        raise SpotError(
            f"embedded dataset '{path}' has sha256 {got}; its card records {card['sha256']}; reinstall spot"
        )
    return data


def copy_in(
    name: str, size: str, seed: int, dest: Path, recipe: str | None, recipe_version: Any, *, progress: bool = True
) -> dict[str, Any] | None:
    """Put the shipped build of ``(name, size, seed)`` at ``dest`` (the caller holds the build lock)
    and return its card (written beside ``dest``, with ``"obtained": "embedded"``); None when none
    is shipped, or when it does not match ``recipe``, ``recipe_version`` and the installed
    packages (:func:`mismatch`; one line on stderr says why, and the caller builds). A shipped file
    that fails its check raises :class:`SpotError` and writes nothing."""
    path = shipped(name, size, seed)
    if path is None:
        return None
    card = read_card(path)
    why = mismatch(card, recipe, recipe_version)
    if why is not None:
        print(
            f"spot: building {name} ({size}, seed {seed}) from its recipe, not the embedded copy: {why}",
            file=sys.stderr,
        )
        return None
    data = read_verified(path, card)
    card = {**card, "obtained": "embedded"}
    store.write_atomic(dest, data)
    try:
        store.write_atomic(dest.with_suffix(".card.json"), json.dumps(card, indent=2, default=str).encode())
    except SpotError:
        dest.unlink(missing_ok=True)
        raise
    if progress:
        print(f"spot: {dest.name}: the embedded copy (sha256 {card['sha256'][:12]}, verified)", file=sys.stderr)
    return card
