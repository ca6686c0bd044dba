"""Run configuration: one frozen dataclass per stage, composed into :class:`ExperimentConfig`.

Resolution order (later wins): dataclass defaults (the paper's values) < method preset
(``method=spot`` etc.) < budget preset (``budget=small`` etc.) < suite preset (what the reference
implementations change for Meta-World / robomimic, chosen by ``data.name``) < variant preset
(``variant=paper|authors``, docs/fidelity.md) < YAML file < ``a.b=value`` overrides. ``method`` and
``budget`` themselves may be given in the YAML file or as overrides.

Every field carries ``help`` text and, where it applies, ``choices`` or a numeric ``range``;
:func:`resolve` validates everything and raises :class:`spot.SpotError` with the dotted key,
the bad value, what was expected and (for unknown keys) the nearest valid keys.
Configs round-trip through a flat ``{"a.b": value}`` dict (:func:`to_flat` / :func:`from_flat`),
which is what MLflow logs as params.

The package, by role (this module re-exports the public names; import them from here):

- :mod:`~spot.config.schema`: the field helper :func:`F` and the sections of data, labels and the
  preference learners; :mod:`~spot.config.experiment`: the sections of subgoals, CVAE, shaping,
  IQL, evaluation and tracking, and :class:`ExperimentConfig`.
- :mod:`~spot.config.presets`: the method, budget, suite and variant presets (tables, and the
  rules that depend on more than one of method, budget, variant and dataset).
- :mod:`~spot.config.keys`: dotted keys, the flat form, key checks, coercion and value limits.
- :mod:`~spot.config.yaml_io`: the strict YAML reader, config files and overrides.
- :mod:`~spot.config.checks`: the rules between fields and the memory bound.
- :mod:`~spot.config.resolution`: :func:`resolve`, :func:`load`, :func:`replace`,
  :func:`to_yaml` and the method registry (:func:`register_method`).
"""

from __future__ import annotations

from spot.config.checks import check, check_memory, memory_bytes, memory_needs
from spot.config.experiment import (
    BUDGETS,
    IQL_ORDERS,
    METHODS,
    VARIANTS,
    CVAEConfig,
    EvalConfig,
    ExperimentConfig,
    IQLConfig,
    ShapingConfig,
    SubgoalConfig,
    TrackingConfig,
)
from spot.config.keys import (
    FLOAT32_MAX,
    MAX_INT,
    MAX_STR,
    check_keys,
    field_info,
    from_flat,
    shown,
    to_flat,
    valid_keys,
)
from spot.config.presets import (
    BUDGET_PRESETS,
    HPL_IQL_CHOICES,
    HPL_IQL_SIZES,
    METHOD_PRESETS,
    PT_QUERY_COUNTS,
    REWARD_KINDS,
    SUITE_PRESETS,
    VARIANT_PRESETS,
    pt_query_count,
    suite_of,
    suite_preset,
    variant_method_preset,
)
from spot.config.resolution import load, register_method, replace, resolve, to_yaml
from spot.config.schema import (
    MAX_LAYERS,
    DataConfig,
    F,
    HPLConfig,
    IPLConfig,
    LabelsConfig,
    MRConfig,
    PTConfig,
    RelabelConfig,
    RewardConfig,
)
from spot.config.yaml_io import (
    MAX_YAML_BYTES,
    MAX_YAML_DEPTH,
    StrictLoader,
    TooDeep,
    flatten_yaml,
    load_yaml,
    parse_overrides,
    read_yaml,
    yaml_problem,
)

__all__ = [
    # schema
    "F",
    "MAX_LAYERS",
    "DataConfig",
    "LabelsConfig",
    "PTConfig",
    "MRConfig",
    "RewardConfig",
    "RelabelConfig",
    "SubgoalConfig",
    "CVAEConfig",
    "ShapingConfig",
    "IQL_ORDERS",
    "IQLConfig",
    "IPLConfig",
    "HPLConfig",
    "EvalConfig",
    "TrackingConfig",
    "METHODS",
    "BUDGETS",
    "VARIANTS",
    "ExperimentConfig",
    # presets
    "METHOD_PRESETS",
    "REWARD_KINDS",
    "BUDGET_PRESETS",
    "HPL_IQL_CHOICES",
    "HPL_IQL_SIZES",
    "variant_method_preset",
    "PT_QUERY_COUNTS",
    "pt_query_count",
    "VARIANT_PRESETS",
    "SUITE_PRESETS",
    "suite_of",
    "suite_preset",
    # keys
    "valid_keys",
    "field_info",
    "to_flat",
    "from_flat",
    "check_keys",
    "MAX_INT",
    "MAX_STR",
    "FLOAT32_MAX",
    "shown",
    # YAML
    "flatten_yaml",
    "MAX_YAML_BYTES",
    "MAX_YAML_DEPTH",
    "TooDeep",
    "StrictLoader",
    "read_yaml",
    "yaml_problem",
    "load_yaml",
    "parse_overrides",
    # checks
    "check",
    "memory_needs",
    "memory_bytes",
    "check_memory",
    # resolution
    "register_method",
    "resolve",
    "load",
    "replace",
    "to_yaml",
]
