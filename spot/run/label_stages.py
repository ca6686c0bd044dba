"""The labels slot: the run's preference queries (scripted teacher or the shipped PT human label
files), their train/evaluation split and segment batches (:func:`labels_stage`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from spot import SpotError
from spot.config import ExperimentConfig
from spot.run.context import Context, Labelled

PT_HUMAN_LABELS = Path(__file__).resolve().parents[1] / "data" / "pt_human_labels"
"""The PT repo's human label files (csmile-1006/PreferenceTransformer f71647b ``human_label/``,
MIT), shipped unchanged with spot; ``PROVENANCE.md`` there says where they come from."""


def human_label_folder(card: Mapping[str, Any]) -> Path | None:
    """The shipped PT human label folder that indexes this dataset, or None.

    Only a real D4RL/robomimic file qualifies: a dataset read from a file (``card["source"] ==
    "file"``) whose card names no spot recipe (a locally built dataset's card says which recipe
    built it, and PT's indices point into the real file's rows). The file is matched by name:
    D4RL ``hopper_medium_replay-v2.hdf5`` (or with hyphens) -> ``hopper-medium-replay-v2``;
    robomimic ``lift/ph/low_dim*.hdf5`` -> ``Lift_ph``.
    """
    if card.get("source") != "file" or "recipe" in card:
        return None
    from spot.data.labels import pt_label_folder

    by_name = pt_label_folder(str(card.get("name") or ""), PT_HUMAN_LABELS)  # a resolved real name (registry)
    if by_name is not None:
        return by_name
    path = Path(str(card.get("path") or card.get("name") or ""))
    names = [path.stem.replace("_", "-")]
    if path.stem.startswith("low_dim") and len(path.parts) >= 3:
        names.append(f"{path.parts[-3].lower().capitalize()}_{path.parts[-2].lower()}")
    for name in names:
        if name and (PT_HUMAN_LABELS / name / "label_human").is_file():
            return PT_HUMAN_LABELS / name
    return None


def label_source(cfg: ExperimentConfig, card: Mapping[str, Any] | None) -> tuple[str, str]:
    """``(source, path)`` the run's labels come from: ``labels.source=auto`` resolves to the shipped
    PT human files when :func:`human_label_folder` finds them, to the scripted teacher otherwise."""
    lc = cfg.labels
    if lc.source == "auto":
        folder = human_label_folder(card or {})
        return ("human", str(folder)) if folder is not None else ("script", "")
    return lc.source, lc.path


def make_preferences(cfg: ExperimentConfig, ds: Any, card: Mapping[str, Any] | None = None) -> Any:
    """The run's preference queries (scripted teacher or PT human label files), checked against
    ``ds``; ``card`` (the dataset's) decides ``labels.source=auto`` (:func:`label_source`)."""
    from spot.data import labels

    lc = cfg.labels
    source, path = label_source(cfg, card)
    if source == "human":
        if not path:
            raise SpotError("labels.source=human needs labels.path (a folder of PT label files)")
        prefs = labels.read_pt_labels(path, num_queries=lc.num_queries)
        labels.check_against(prefs, ds, allow_cross_episode=True)
        return prefs
    return labels.scripted_teacher(
        ds,
        lc.num_queries,
        lc.segment_length,
        teacher=lc.teacher,
        discount=lc.discount,
        tie_threshold=lc.tie_threshold,
        mistake_rate=lc.mistake_rate,
        allow_cross_episode=lc.allow_cross_episode,
        seed=lc.seed,
        score=lc.score,
    )


def pt_eval_subset(prefs: Any, fraction: float) -> Any:
    """The PT repo's reward-model evaluation queries: the last ``int(fraction * Q)`` of them (at
    least one when ``fraction > 0``), which the model also trains on (``labels.eval_split=pt_subset``)."""
    n_eval = max(1, int(fraction * len(prefs))) if fraction > 0 else 0
    return prefs.subset(np.arange(len(prefs) - n_eval, len(prefs)))


def split_queries(prefs: Any, cfg: ExperimentConfig) -> tuple[Any, Any]:
    """``(train, eval)`` queries by ``labels.eval_split``: ``holdout`` = a random disjoint split;
    ``pt_subset`` = all queries for training and :func:`pt_eval_subset` for evaluation."""
    from spot.data import labels

    lc = cfg.labels
    if lc.eval_split == "pt_subset":
        return prefs, pt_eval_subset(prefs, lc.eval_fraction)
    return labels.split_eval(prefs, lc.eval_fraction, lc.seed)


def labels_stage(ctx: Context) -> Labelled:
    """Queries, their train/evaluation split (``labels.eval_split``) and segment batches."""
    from spot.data import labels

    cfg, ds = ctx.cfg, ctx.ds
    source, path = label_source(cfg, ctx.card)
    ctx.tracker.set_tags({"labels.resolved_source": source, **({"labels.resolved_path": path} if path else {})})
    prefs = make_preferences(cfg, ds, ctx.card)
    train_prefs, eval_prefs = split_queries(prefs, cfg)
    train_batch = labels.segment_batch(ds, train_prefs)
    eval_batch = labels.segment_batch(ds, eval_prefs) if len(eval_prefs) else None
    ctx.log(
        {
            "labels/queries": len(prefs),
            "labels/ties": float(np.sum(prefs.labels == 0.5)),
            "labels/segment_length": prefs.segment_length,
        }
    )
    deps = {
        "s1": prefs.starts_1,
        "s2": prefs.starts_2,
        "y": prefs.labels,
        "length": prefs.segment_length,
        "split": (cfg.labels.eval_fraction, cfg.labels.seed),
        **({"eval_split": cfg.labels.eval_split} if cfg.labels.eval_split != "holdout" else {}),
    }
    return Labelled(prefs, train_prefs, train_batch, eval_batch, deps)
