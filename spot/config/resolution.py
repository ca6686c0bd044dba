"""Resolution: the layers (defaults < method < budget < suite < variant < YAML file < overrides)
resolved into one checked :class:`~spot.config.experiment.ExperimentConfig`; loading a YAML file
with overrides, copies with changed keys, the YAML dump, and the method registry.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from spot import SpotError
from spot.config.checks import check
from spot.config.experiment import ExperimentConfig
from spot.config.keys import build, check_keys, coerce, to_flat
from spot.config.presets import (
    BUDGET_PRESETS,
    METHOD_PRESETS,
    REWARD_KINDS,
    VARIANT_PRESETS,
    pt_query_count,
    suite_preset,
    variant_method_preset,
)
from spot.config.yaml_io import load_yaml, parse_overrides


def register_method(method: str, preset: dict[str, Any]) -> None:
    """Make ``method=<method>`` a valid config with ``preset`` (flat dotted keys) as its method
    preset; a new ``reward.kind`` in the preset becomes valid too. Used by
    :func:`spot.stages.register`, which adds the method's stages."""
    if method in METHOD_PRESETS:
        raise SpotError(f"method {method!r} is already registered")
    kind = preset.get("reward.kind")
    if kind is not None and kind not in REWARD_KINDS:
        REWARD_KINDS.append(kind)
    METHOD_PRESETS[method] = dict(check_keys(preset, f"method preset {method!r}"))


def resolve(*layers: dict[str, Any]) -> ExperimentConfig:
    """Resolve flat layers (YAML file, overrides, ...) on top of method and budget presets."""
    user: dict[str, Any] = {}
    for layer in layers:
        user.update(check_keys(layer, "config"))
    method = coerce("method", user.get("method", ExperimentConfig.method))
    budget = coerce("budget", user.get("budget", ExperimentConfig.budget))
    flat = to_flat(ExperimentConfig())
    flat.update(METHOD_PRESETS[method])
    flat.update(BUDGET_PRESETS[budget])
    data_name = str(user.get("data.name", flat["data.name"]))
    flat.update(suite_preset(data_name, method, budget))
    variant = coerce("variant", user.get("variant", ExperimentConfig.variant))
    flat.update(VARIANT_PRESETS[variant])
    flat.update(variant_method_preset(variant, method, budget, data_name))
    counts = coerce("labels.query_counts", user.get("labels.query_counts", flat["labels.query_counts"]))
    if counts == "pt" and pt_query_count(data_name) is not None:
        flat["labels.num_queries"] = pt_query_count(data_name)  # below the YAML file and overrides
    flat.update(user)
    flat["method"], flat["budget"], flat["variant"] = method, budget, variant
    return check(build({k: coerce(k, v) for k, v in flat.items()}))


def load(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> ExperimentConfig:
    """YAML file (optional) + CLI overrides -> validated :class:`ExperimentConfig`."""
    layers = [load_yaml(path)] if path else []
    layers.append(parse_overrides(overrides))
    return resolve(*layers)


def replace(cfg: ExperimentConfig, **dotted: Any) -> ExperimentConfig:
    """Copy of ``cfg`` with dotted-key changes, e.g. ``replace(cfg, **{"iql.steps": 10})``."""
    flat = to_flat(cfg)
    flat.update(check_keys(dotted, "replace"))
    return check(build({k: coerce(k, v) for k, v in flat.items()}))


def to_yaml(cfg: ExperimentConfig) -> str:
    nested: dict[str, Any] = {}
    for key, value in to_flat(cfg).items():
        if isinstance(value, tuple):
            value = list(value)
        if "." in key:
            s, sub = key.split(".", 1)
            nested.setdefault(s, {})[sub] = value
        else:
            nested[key] = value
    return yaml.safe_dump(nested, sort_keys=False)
