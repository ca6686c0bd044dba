"""How runs look in the MLflow UI: their names, the experiment's kind, the paper's reference score.

* A run is named by what varies (:func:`run_name`): the method, then for a sweep trial each swept
  axis's short name and value (``spot λ=0.5 s1``), for a plain run the dataset (``spot
  hopper-medium-replay s0``), then the seed.
* spot's experiments are ML experiments: the tag :data:`EXPERIMENT_KIND_TAG` =
  :data:`EXPERIMENT_KIND` makes MLflow 3's UI open them, and their runs, in its model-training
  workspace (runs table, model metrics) instead of the GenAI one (traces, evaluations). The values
  are those of the installed UI's ``ExperimentKind`` (``mlflow/server/js``).
* :func:`paper_score`: the paper's Table 1 mean for the run's method and dataset, logged beside the
  run's own scores as ``eval/score_paper`` (read from ``spot/paper_tables.csv``, the file
  :mod:`spot.results.paper` reads; the standard library here, this layer imports no pandas).
"""

from __future__ import annotations

import csv
import functools
import re
from collections.abc import Mapping
from importlib import resources
from typing import Any

EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = "custom_model_development"
"""MLflow 3's kind for a model-training experiment (the UI's ``CUSTOM_MODEL_DEVELOPMENT``)."""

PAPER_METRIC = "eval/score_paper"
"""The paper's Table 1 mean for the run's (method, dataset), beside ``eval/score_final``/``_best``."""

AXIS_NAMES = {"shaping.weight": "λ", "method": "", "data.name": ""}
"""Short names of swept axes in run names (``""``: the value alone, e.g. the dataset's name)."""


def axis_label(key: str, value: str) -> str:
    """``λ=0.5`` for ``shaping.weight``; the value alone for the method and dataset; else the key's
    last part (``num_queries=100`` for ``labels.num_queries``)."""
    short = AXIS_NAMES.get(key, key.rsplit(".", 1)[-1])
    return f"{short}={value}" if short else str(value)


def run_name(method: str, dataset: str, seed: int | str, tags: Mapping[str, str]) -> str:
    """``<method> <what the sweep varies> s<seed>`` (the axes from the ``axis.<key>`` tags of a sweep
    trial, the method axis left out: it comes first anyway); ``<method> <dataset> s<seed>`` for a run
    outside a sweep."""
    axes = [axis_label(k[len("axis.") :], v) for k, v in tags.items() if k.startswith("axis.") and k != "axis.method"]
    return " ".join([method, *(axes or [dataset]), f"s{seed}"])


def _paper_key(dataset: str) -> str:
    """Our dataset name as the paper's row name (:func:`spot.results.paper.paper_dataset_name`'s rule)."""
    n = str(dataset).strip().lower().replace("_", "-")
    n = re.sub(r"-v\d+$", "", n)
    return re.sub(r"-low-dim$", "", n)


@functools.cache
def _table1() -> dict[tuple[str, str], float]:
    with resources.files("spot").joinpath("paper_tables.csv").open("r", encoding="utf-8") as fh:
        return {
            (row["dataset"], row["method"]): float(row["mean"])
            for row in csv.DictReader(fh)
            if row["table"] == "1" and not row["setting"] and row["mean"]
        }


def paper_score(method: str, dataset: str) -> float | None:
    """The paper's Table 1 mean normalised score of ``method`` on ``dataset``; None where it has none."""
    return _table1().get((_paper_key(dataset), method))


def default_name(cfg: Any, tags: Mapping[str, str]) -> str:
    """A run's name when none is given: :func:`run_name` of its config and start tags."""
    return run_name(cfg.method, tags.get("dataset", cfg.data.name), cfg.seed, tags)


def log_paper_score(tracker: Any, method: str, dataset: str) -> None:
    """The paper's Table 1 score of (method, dataset) as :data:`PAPER_METRIC` (step 0), if it has one."""
    score = paper_score(method, dataset)
    if score is not None:
        tracker.log_metrics({PAPER_METRIC: score}, step=0)
