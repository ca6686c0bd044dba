"""Dotted keys: the flat ``{"a.b": value}`` form of a config (:func:`to_flat` / :func:`from_flat`,
what MLflow logs as params), the list of valid keys with their types and metadata, the unknown-key
check (nearest keys as a hint) and the coercion of a value (strings from the CLI or MLflow
included) to its field's type, choices and range, with the limits on integers, floats and strings.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import typing
from typing import Any

from spot import SpotError
from spot.config.experiment import STAGES, ExperimentConfig
from spot.config.presets import METHOD_PRESETS, REWARD_KINDS
from spot.config.schema import MAX_LAYERS


# --------------------------------------------------------------------------- flat dicts
def fields_of(cls: type) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(cls)}


def valid_keys() -> list[str]:
    keys = []
    for name, _f in fields_of(ExperimentConfig).items():
        if name in STAGES:
            keys += [f"{name}.{sub}" for sub in fields_of(STAGES[name])]
        else:
            keys.append(name)
    return keys


def field_info(key: str) -> tuple[Any, dict]:
    """``(type, metadata)`` of a dotted key."""
    parts = key.split(".")
    if len(parts) == 1:
        f = fields_of(ExperimentConfig)[parts[0]]
    else:
        f = fields_of(STAGES[parts[0]])[parts[1]]
    return _hints(STAGES[parts[0]] if len(parts) > 1 else ExperimentConfig)[parts[-1]], dict(f.metadata)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """``typing.get_type_hints(cls)``, once per class: it evaluates every annotation string anew,
    ~95 % of a :func:`resolve` (13 ms of 14) before it was cached, which bounds how many trials a
    sweep can check."""
    return typing.get_type_hints(cls)


def to_flat(cfg: ExperimentConfig) -> dict[str, Any]:
    """``{"iql.steps": 1000, ...}`` for every field (MLflow params)."""
    flat: dict[str, Any] = {}
    for name in fields_of(ExperimentConfig):
        value = getattr(cfg, name)
        if dataclasses.is_dataclass(value):
            for sub in fields_of(type(value)):
                flat[f"{name}.{sub}"] = getattr(value, sub)
        else:
            flat[name] = value
    return flat


def from_flat(flat: dict[str, Any]) -> ExperimentConfig:
    """Inverse of :func:`to_flat`; values may be strings (as MLflow returns params)."""
    return build({k: coerce(k, v) for k, v in check_keys(flat, "config").items()})


def build(flat: dict[str, Any]) -> ExperimentConfig:
    top: dict[str, Any] = {}
    stages: dict[str, dict[str, Any]] = {s: {} for s in STAGES}
    for key, value in flat.items():
        if "." in key:
            s, sub = key.split(".", 1)
            stages[s][sub] = value
        else:
            top[key] = value
    return ExperimentConfig(**top, **{s: STAGES[s](**kw) for s, kw in stages.items()})


# --------------------------------------------------------------------------- validation
# The choices of these keys grow by spot.config.register_method.
_REGISTERED_CHOICES = {"method": lambda: tuple(METHOD_PRESETS), "reward.kind": lambda: tuple(REWARD_KINDS)}


def check_keys(flat: dict[str, Any], where: str) -> dict[str, Any]:
    """``flat``, or SpotError on its first unknown key with the nearest valid keys as a hint (also
    for sweep files' blocks, :mod:`spot.sweep.spec`)."""
    keys = valid_keys()
    for key in flat:
        if key not in keys:
            close = difflib.get_close_matches(key, keys, n=3, cutoff=0.5)
            hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
            raise SpotError(f"{where}: unknown config key '{key}'{hint} (see `spot config keys`)")
    return flat


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


MAX_INT = 2**31 - 1
"""Largest integer a config value may take (seeds, steps, sizes): beyond it JAX's int32 and
PRNG seeds overflow."""


def _to_int(value: Any) -> int:
    """An exact integer from an int, an integral float or a decimal/scientific string; ValueError
    or OverflowError otherwise (bools, fractions, NaN, infinities)."""
    if isinstance(value, bool):
        raise ValueError
    if isinstance(value, float) and not value.is_integer():
        raise ValueError
    if isinstance(value, str) and "e" in value.lower():
        number = float(value)
        if not number.is_integer():
            raise ValueError
        return int(number)
    return int(value)


MAX_STR = 4096
"""Longest string value (paths, names): PATH_MAX on Linux."""
FLOAT32_MAX = 3.4028234663852886e38
"""Largest float32: JAX computes in float32, where a larger config value is already inf."""
_SHOWN = 60


def shown(value: Any) -> str:
    """``repr(value)`` for an error line, cut to about 60 characters (a value may be megabytes)."""
    text = repr(value)
    return text if len(text) <= _SHOWN else f"{text[: _SHOWN - 15]}... ({len(text)} characters)"


def _coerce_tuple(key: str, tp: Any, value: Any) -> tuple:
    inner = typing.get_args(tp)[0]
    if isinstance(value, str):
        text = value.strip().strip("()[]")
        value = [v for v in (p.strip() for p in text.split(",")) if v]
    if not isinstance(value, (list, tuple)):
        raise ValueError
    if len(value) > MAX_LAYERS:
        raise SpotError(f"config key '{key}': {len(value)} layer sizes; expected at most {MAX_LAYERS}")
    out = tuple(_to_int(v) if inner is int else inner(v) for v in value)
    if inner is int and (not out or min(out) < 1 or max(out) > MAX_INT):
        raise SpotError(
            f"config key '{key}': value {shown(value)}: expected one or more layer sizes, each 1 <= size <= {MAX_INT}"
        )
    return out


def _coerce_bool(value: Any) -> bool:
    if isinstance(value, str):
        if value.lower() in ("true", "1", "yes", "on"):
            return True
        if value.lower() in ("false", "0", "no", "off"):
            return False
        raise ValueError
    if isinstance(value, (bool, int)) and value in (0, 1):
        return bool(value)
    raise ValueError


def _coerce_float(key: str, value: Any) -> float:
    if isinstance(value, bool):
        raise ValueError
    out = float(value)
    if not math.isfinite(out):
        raise SpotError(f"config key '{key}': value {shown(value)} is not a finite number")
    if abs(out) > FLOAT32_MAX:
        raise SpotError(
            f"config key '{key}': value {shown(value)} is beyond float32 (|value| <= {FLOAT32_MAX:.4g}); "
            "JAX computes in float32, where it is inf"
        )
    return out


def _coerce_str(key: str, value: Any) -> str:
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise ValueError
    out = str(value)
    if len(out) > MAX_STR:
        raise SpotError(f"config key '{key}': a string of {len(out)} characters; expected at most {MAX_STR}")
    bad = next((c for c in out if ord(c) < 32 or ord(c) == 127), None)
    if bad is not None:
        raise SpotError(
            f"config key '{key}': value {shown(out)} holds the control character {bad!r}; expected printable text"
        )
    return out


def coerce(key: str, value: Any) -> Any:
    """Convert ``value`` to the field's type (strings from the CLI or MLflow included) and validate."""
    tp, meta = field_info(key)
    origin = typing.get_origin(tp)
    try:
        if origin is tuple:
            out = _coerce_tuple(key, tp, value)
        elif tp is bool:
            out = _coerce_bool(value)
        elif tp is int:
            out = _to_int(value)
        elif tp is float:
            out = _coerce_float(key, value)
        elif tp is str:
            out = _coerce_str(key, value)
        else:  # pragma: no cover - every field has one of the types above
            raise TypeError(f"unsupported field type {tp}")
    except (ValueError, TypeError, OverflowError):
        expected = f"a tuple of {_type_name(typing.get_args(tp)[0])}" if origin is tuple else _type_name(tp)
        raise SpotError(f"config key '{key}': value {shown(value)} is not {expected}") from None
    choices = _REGISTERED_CHOICES[key]() if key in _REGISTERED_CHOICES else meta.get("choices")
    if choices and out not in choices:
        raise SpotError(f"config key '{key}': value {shown(out)} is not one of {', '.join(map(repr, choices))}")
    if tp is int and abs(out) > MAX_INT:
        raise SpotError(f"config key '{key}': value {shown(value)} is too large; expected at most {MAX_INT}")
    rng = meta.get("range")
    if rng is not None:
        lo, hi = rng
        if (lo is not None and out < lo) or (hi is not None and out > hi):
            raise SpotError(
                f"config key '{key}': value {out!r} is out of range; expected "
                f"{lo if lo is not None else '-inf'} <= value <= {hi if hi is not None else 'inf'}"
            )
    return out
