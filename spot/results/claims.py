"""Claims files: the questions ``spot report`` answers, as data (format in docs/tables.md).

A claims file is YAML with these top-level keys (all optional but ``claims``, unless it extends
another file):

* ``extends``: ``default`` (the package's file of the paper's claims, :data:`DEFAULT`) or a path
  relative to this file. The other file's sets, filters, tables and claims come first; this file's
  sets, filters and tables replace those of the same key, its claims follow, and its ``results``
  replace the other file's.
* ``results``: results CSVs or folders of them, relative to this file: the runs the report reads.
* ``sets``: experiment sets by key: a list of MLflow experiment names read together, or a mapping
  ``{experiments: [...], label: "set P"}`` (the report then shows the label and lists the set once).
* ``filters``: named filters (:func:`spot.results.select.compile_filter`) a claim's arms refer to.
* ``claims``: the claims, in report order (:class:`Claim`, :func:`_claim`).
* ``tables``: per paper table number, the runs ``spot tables --table N STUDY_DIR`` reads:
  ``{results: [...], experiments: [...]}``.
* ``amend``: changes to claims this file's chain already has (:func:`_amended`): each entry names
  a claim by ``id`` and ``comparison`` and gives the keys that replace its own (its ``set``, its
  ``metrics``, ``paired``...), so that a study can mark the rows of a file it extends.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from spot import SpotError
from spot.results import select

DEFAULT = "paper_claims.yaml"  # inside this package: the paper's six claims and the two controls
STUDY_FILE = "claims.yaml"  # what `spot report STUDY_DIR` reads
TOP_KEYS = ("extends", "results", "sets", "filters", "claims", "tables", "amend")
TESTS = ("difference", "runner-up", "queries", "dose-response")
CLAIM_KEYS = (
    "id",
    "text",
    "comparison",
    "set",
    "test",
    "x",
    "y",
    "labels",
    "metrics",
    "direction",
    "variant",
    "datasets",
    "among",
    "by",
    "others",
    "runner_label",
    "digits",
    "paired",
    "note",
)
STATS = {"last": "metrics.eval/score_final", "best": "metrics.eval/score_best"}
OOD_METRIC = "metrics.diag/extrapolation_error_ood"
METRICS = {**STATS, "ood": OOD_METRIC}  # the short names a claim's `metrics` may use
# `lastK` (K >= 2): each run's mean of its last K periodic evaluations, from its exported curve
LAST_K = re.compile(r"last([0-9]+)")


def last_k(stat: str) -> int | None:
    """K of a ``lastK`` statistic (the mean of a run's last K evaluations), else ``None``."""
    m = LAST_K.fullmatch(stat)
    return int(m.group(1)) if m else None


def metric_column(stat: str) -> str:
    """The runs' column a statistic reads: a short name's metric, ``lastK``'s derived column
    (:func:`spot.results.compare.with_last_k`), else ``metrics.<name>``."""
    k = last_k(stat)
    if k is not None:
        return f"{CURVE_MEAN}{k}"
    return METRICS.get(stat, f"metrics.{stat}")


CURVE_MEAN = "curve.eval/score.mean_last"  # + K: the derived column of `lastK`


@dataclass(frozen=True)
class ExperimentSet:
    """MLflow experiments read together; shown by ``label`` where it has one, else by their names."""

    key: str
    experiments: tuple[str, ...]
    label: str | None = None

    @property
    def names(self) -> str:
        return "+".join(self.experiments)

    @property
    def shown(self) -> str:
        return self.label or self.names


@dataclass(frozen=True)
class Claim:
    """One question: arm ``x`` against arm ``y`` on a set's runs, with a test (:data:`TESTS`)."""

    id: str
    text: str
    comparison: str
    sets: tuple[str, ...]  # keys into the file's sets; the first with runs is read
    test: str
    x: select.Filter
    y: select.Filter
    among: select.Filter  # the set's runs the test looks at (every run by default)
    labels: tuple[str, str]
    metrics: tuple[str, ...]  # short names (METRICS) or metric names
    variant: str | None = None  # the fidelity variant every arm is under (the dose section's title)
    by: tuple[str, ...] = ()  # runner-up: the params whose other values make the other arms
    others: int | None = None  # runner-up: how many other arms the design has
    runner_label: str = ""  # runner-up: the runner-up's name, ``{KEY}`` replaced by its value
    digits: int | None = None  # decimals of the effect (default: 3 for ood, else 1)
    paired: bool = False  # seed-matched by design: the paired verdict is the row's (report: Paired verdicts)
    note: str = ""  # a line for the report's notes (what an arm is and why)


@dataclass
class ClaimsFile:
    """A loaded claims file: where its runs are, its sets and claims, and its tables' inputs."""

    path: Path | None
    results: tuple[Path, ...]
    sets: dict[str, ExperimentSet]
    claims: list[Claim]
    tables: dict[int, dict[str, tuple]] = field(default_factory=dict)

    def alternatives(self, claim: Claim) -> list[ExperimentSet]:
        return [self.sets[k] for k in claim.sets]


def default_file() -> Path:
    """The package's claims file (the paper's claims, generic experiment names)."""
    return Path(str(resources.files("spot.results").joinpath(DEFAULT)))


def study_file(study: str | Path) -> Path:
    """The claims file of a study folder (``STUDY_DIR/claims.yaml``)."""
    folder = Path(study)
    if not folder.is_dir():
        raise SpotError(f"study folder {study}: not a folder; expected experiments/<study>/ with a {STUDY_FILE}")
    path = folder / STUDY_FILE
    if not path.is_file():
        raise SpotError(f"study folder {study}: has no {STUDY_FILE}; expected a claims file there (docs/tables.md)")
    return path


def load(path: str | Path | None = None, use: Mapping[str, Sequence[str]] | None = None) -> ClaimsFile:
    """The claims file at ``path`` (the package's default file if ``None``), its ``extends`` chain
    resolved; ``use`` replaces sets by key (``--use KEY=EXPERIMENT+EXPERIMENT``: an unlabelled set)."""
    raw = _merged(Path(path) if path is not None else default_file(), ())
    where = f"claims file {raw['path']}"
    sets = {k: _set(k, v, f"{where}: sets.{k}") for k, v in raw["sets"].items()}
    for key, names in (use or {}).items():
        if key not in sets:
            raise SpotError(f"--use {key}=...: {where} has no set {key!r} (its sets: {', '.join(sets)})")
        sets[key] = ExperimentSet(key, tuple(names))
    claims = [_claim(c, raw["filters"], sets, f"{where}: claims[{i}]") for i, c in enumerate(raw["claims"])]
    tables = {n: _table(n, spec, base, f"{where}: tables.{n}") for n, (spec, base) in raw["tables"].items()}
    return ClaimsFile(raw["path"], tuple(raw["results"]), sets, claims, tables)


def _read(path: Path) -> dict[str, Any]:
    from spot import config as config_lib  # the project's strict YAML reader (size-bounded, no aliases)

    data = config_lib.read_yaml(path, f"claims file {path}")
    if not isinstance(data, Mapping):
        raise SpotError(f"claims file {path}: expected a mapping with {', '.join(TOP_KEYS)}")
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise SpotError(f"claims file {path}: unknown key {unknown[0]!r}; expected {', '.join(TOP_KEYS)}")
    return dict(data)


def _merged(path: Path, seen: tuple[Path, ...]) -> dict[str, Any]:
    """The raw file with its ``extends`` chain applied: paths resolved, sets/filters/tables merged by
    key, claims in order (the base file's first)."""
    path = path.resolve()
    if path in seen:
        raise SpotError(f"claims file {seen[-1]}: extends {path}, which extends it back")
    data = _read(path)
    where = f"claims file {path}"
    out: dict[str, Any] = {"path": path, "results": [], "sets": {}, "filters": {}, "claims": [], "tables": {}}
    if "extends" in data:
        base = data["extends"]
        if not isinstance(base, str) or not base:
            raise SpotError(f"{where}: extends: expected 'default' or a path relative to the file")
        out = _merged(default_file() if base == "default" else path.parent / base, (*seen, path))
        out["path"] = path
    elif "claims" not in data:
        raise SpotError(f"{where}: no claims; expected a list under 'claims' (or 'extends' another file)")
    if "results" in data:
        out["results"] = [path.parent / p for p in _strings(data["results"], f"{where}: results")]
    for key in ("sets", "filters", "tables"):
        part = data.get(key, {})
        if not isinstance(part, Mapping):
            raise SpotError(f"{where}: {key}: expected a mapping")
        if key == "tables":  # a table's results are relative to the file that names them
            part = {k: (v, path.parent) for k, v in part.items()}
        out[key] = {**out[key], **{str(k) if key != "tables" else k: v for k, v in part.items()}}
    claims = data.get("claims", [])
    if not isinstance(claims, list):
        raise SpotError(f"{where}: claims: expected a list of claims")
    out["claims"] = _amended([*out["claims"], *claims], data.get("amend", []), f"{where}: amend")
    return out


def _amended(claims: list[Any], amend: Any, where: str) -> list[Any]:
    """``claims`` (raw mappings) with each ``amend`` entry's keys replacing those of every claim of
    its ``id`` and ``comparison``; an entry that matches no claim is an error."""
    if not isinstance(amend, list):
        raise SpotError(f"{where}: expected a list of {{id, comparison, KEY: VALUE...}}")
    for i, entry in enumerate(amend):
        at = f"{where}[{i}]"
        if not isinstance(entry, Mapping) or "id" not in entry or "comparison" not in entry or len(entry) < 3:
            raise SpotError(f"{at}: expected {{id, comparison}} of a claim and the keys that replace its own")
        unknown = [k for k in entry if k not in CLAIM_KEYS]
        if unknown:
            raise SpotError(f"{at}: unknown key {unknown[0]!r}; a claim takes {', '.join(CLAIM_KEYS)}")
        key = (str(entry["id"]), str(entry["comparison"]))
        hits = [
            j
            for j, c in enumerate(claims)
            if isinstance(c, Mapping) and (str(c.get("id")), str(c.get("comparison"))) == key
        ]
        if not hits:
            raise SpotError(f"{at}: no claim has id {key[0]!r} and comparison {key[1]!r}")
        for j in hits:
            claims[j] = {**claims[j], **entry}
    return claims


def _strings(value: Any, where: str) -> list[str]:
    items = value if isinstance(value, list) else [value]
    if not items or not all(isinstance(v, str) and v for v in items):
        raise SpotError(f"{where}: expected a text or a list of texts")
    return items


def _set(key: str, spec: Any, where: str) -> ExperimentSet:
    if isinstance(spec, Mapping):
        unknown = [k for k in spec if k not in ("experiments", "label")]
        if unknown or "experiments" not in spec:
            raise SpotError(f"{where}: expected a list of experiments or {{experiments: [...], label: TEXT}}")
        label = spec.get("label")
        if label is not None and not isinstance(label, str):
            raise SpotError(f"{where}.label: expected a text")
        return ExperimentSet(key, tuple(_strings(spec["experiments"], f"{where}.experiments")), label)
    return ExperimentSet(key, tuple(_strings(spec, where)))


def _table(number: Any, spec: Any, base: Path, where: str) -> dict[str, tuple]:
    if not isinstance(number, int) or not isinstance(spec, Mapping) or set(spec) - {"results", "experiments"}:
        raise SpotError(f"{where}: expected a table number -> {{results: [...], experiments: [...]}}")
    results = tuple(base / p for p in _strings(spec["results"], f"{where}.results")) if "results" in spec else ()
    experiments = tuple(_strings(spec["experiments"], f"{where}.experiments")) if "experiments" in spec else ()
    return {"results": results, "experiments": experiments}


def _text(spec: Mapping[str, Any], key: str, where: str, default: str | None = None) -> str:
    value = spec.get(key, default)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and key == "id":
        value = str(value)
    if not isinstance(value, str):
        raise SpotError(f"{where}: {key}: expected a text")
    return value


def _claim(spec: Any, named: Mapping[str, Any], sets: Mapping[str, ExperimentSet], where: str) -> Claim:
    """A :class:`Claim` from its mapping (keys :data:`CLAIM_KEYS`, docs/tables.md)."""
    if not isinstance(spec, Mapping):
        raise SpotError(f"{where}: expected a mapping with {', '.join(CLAIM_KEYS)}")
    unknown = [k for k in spec if k not in CLAIM_KEYS]
    if unknown:
        raise SpotError(f"{where}: unknown key {unknown[0]!r}; a claim takes {', '.join(CLAIM_KEYS)}")
    test = _text(spec, "test", where, "difference")
    if test not in TESTS:
        raise SpotError(f"{where}: test: {test!r}; expected one of {', '.join(TESTS)}")
    dose = test == "dose-response"
    keys = _strings(spec.get("set"), f"{where}: set")
    missing = [k for k in keys if k not in sets]
    if missing:
        raise SpotError(f"{where}: set {missing[0]!r} is not in the file's sets ({', '.join(sets) or 'none'})")
    variant = _text(spec, "variant", where, "") or None
    among = _among(spec, variant, named, where)
    needs = () if dose else ("x",) if test == "runner-up" else ("x", "y")
    for key in needs:
        if key not in spec:
            raise SpotError(f"{where}: test {test} needs an arm '{key}' (a filter)")
    x = select.compile_filter(spec["x"], named, f"{where}.x") if "x" in spec else select.everything
    y = select.compile_filter(spec["y"], named, f"{where}.y") if "y" in spec else select.everything
    labels = tuple(_strings(spec.get("labels", ["x", "y"]), f"{where}: labels"))
    if len(labels) != 2:
        raise SpotError(f"{where}: labels: expected two names, x's and y's")
    direction = _text(spec, "direction", where, "higher")
    if direction not in ("higher", "lower"):
        raise SpotError(f"{where}: direction: {direction!r}; expected higher (x − y > 0) or lower (x − y < 0)")
    if direction == "lower":  # the effect is y − x: the claim holds where it is above 0
        x, y, labels = y, x, (labels[1], labels[0])
    return Claim(
        id=_text(spec, "id", where, "" if dose else None),
        text=_text(spec, "text", where, "" if dose else None),
        comparison=_text(spec, "comparison", where, "" if dose else None),
        sets=tuple(keys),
        test=test,
        x=select.both(among, x),
        y=select.both(among, y),
        among=among,
        labels=(labels[0], labels[1]),
        metrics=_metrics(spec, where, dose),
        variant=variant,
        paired=_flag(spec, "paired", where),
        note=_text(spec, "note", where, ""),
        **_runner_up(spec, where, test),
    )


def _flag(spec: Mapping[str, Any], key: str, where: str) -> bool:
    value = spec.get(key, False)
    if not isinstance(value, bool):
        raise SpotError(f"{where}: {key}: expected true or false")
    return value


def _among(spec: Mapping[str, Any], variant: str | None, named: Mapping[str, Any], where: str) -> select.Filter:
    """The runs a claim looks at: its ``variant``, ``datasets`` and ``among`` together (every run
    without any of them)."""
    parts = [select.compile_filter({"variant": variant}, named, f"{where}: variant")] if variant else []
    if "datasets" in spec:
        datasets = _strings(spec["datasets"], f"{where}: datasets")
        parts.append(select.compile_filter({"dataset": datasets}, named, f"{where}: datasets"))
    if "among" in spec:
        parts.append(select.compile_filter(spec["among"], named, f"{where}.among"))
    among = select.everything
    for part in parts:
        among = select.both(among, part)
    return among


def _metrics(spec: Mapping[str, Any], where: str, dose: bool) -> tuple[str, ...]:
    metrics = tuple(_strings(spec.get("metrics", ["last"] if dose else ["last", "best"]), f"{where}: metrics"))
    if dose and metrics != ("last",):
        raise SpotError(f"{where}: metrics: the dose-response section reads the final score only (last)")
    bad = [m for m in metrics if (k := last_k(m)) is not None and k < 2]
    if bad:
        raise SpotError(f"{where}: metrics: {bad[0]!r}; lastK takes K of 2 or more (last is the final evaluation)")
    return metrics


def _runner_up(spec: Mapping[str, Any], where: str, test: str) -> dict[str, Any]:
    """The runner-up test's fields (``by``, ``others``, ``runner_label``) and ``digits``."""
    out: dict[str, Any] = {}
    if "digits" in spec:
        if not isinstance(spec["digits"], int) or not 0 <= spec["digits"] <= 6:
            raise SpotError(f"{where}: digits: expected a whole number from 0 to 6")
        out["digits"] = spec["digits"]
    if test != "runner-up":
        extra = [k for k in ("by", "others", "runner_label") if k in spec]
        if extra:
            raise SpotError(f"{where}: {extra[0]}: only the runner-up test takes it")
        return out
    if "by" not in spec:
        raise SpotError(f"{where}: test runner-up needs 'by' (the params whose values make the other arms)")
    out["by"] = tuple(_strings(spec["by"], f"{where}: by"))
    if "others" in spec:
        if not isinstance(spec["others"], int) or spec["others"] < 1:
            raise SpotError(f"{where}: others: expected a positive whole number (the design's other arms)")
        out["others"] = spec["others"]
    out["runner_label"] = _text(spec, "runner_label", where, " ".join(f"{{{k}}}" for k in out["by"]))
    return out
