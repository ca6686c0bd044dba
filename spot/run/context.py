"""What a stage reads and what it returns: the :class:`Context` and the typed slot outputs.

A stage is a function ``stage(ctx, *inputs) -> output`` over a :class:`Context` (config, dataset,
keys, tracker, stage cache) and the typed outputs of earlier stages (:class:`Labelled`,
:class:`RewardModel`, :class:`Rewards`, :class:`Subgoals`, :class:`Shaped`, :class:`Policy`).
:meth:`Context.stage` times a stage (``time/<stage>_s``) and :meth:`Context.cached` reads or fills
its stage-cache entry. The helpers every stage may use are here too: :func:`save_model` (a trained
model as the run's ``models/<name>`` artifacts), :func:`untimed` and :func:`dataset_deps`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from spot import SpotError, cache
from spot import config as config_lib
from spot.config import ExperimentConfig
from spot.tracking import Tracker, run_temp


# --------------------------------------------------------------------------- typed outputs
@dataclass(frozen=True)
class Labelled:
    """Preference queries: all of them, the training split, and their segment batches."""

    prefs: Any  # spot.data.labels.Preferences, all queries
    train_prefs: Any
    train_batch: dict[str, np.ndarray]
    eval_batch: dict[str, np.ndarray] | None
    deps: dict[str, Any]  # what identifies them in stage-cache keys


@dataclass(frozen=True)
class RewardModel:
    """A trained reward model: its parameters and the stage-cache key that identifies it; ``cvae``:
    the CVAE trained with it (``cvae.schedule=online``: ``{"params", "history"}``), else None."""

    kind: str
    params: Any
    cache_key: str
    cvae: Any = None


@dataclass(frozen=True)
class Rewards:
    """Per-transition rewards ``[N]``: the model's raw output and the normalised training reward."""

    model: np.ndarray
    normalised: np.ndarray
    source: RewardModel | None = None


@dataclass(frozen=True)
class Subgoals:
    """Attention subgoals of the preferred segments and the CVAE trained to propose them."""

    triplets: Any  # spot.subgoal.extract.Triplets (s, a, g)
    states: np.ndarray
    cvae_params: Any


@dataclass(frozen=True)
class Shaped:
    """The reward the policy trains on, and the cosine to the subgoal (Fig. 2's proximity axis)."""

    reward: np.ndarray
    cos_to_subgoal: np.ndarray | None = None


@dataclass(frozen=True)
class Policy:
    """The trained policy's state and its evaluation curve."""

    state: Any
    steps: list[int]
    scores: list[float]
    eval_s: float


# --------------------------------------------------------------------------- context
@dataclass
class Context:
    """Everything a stage may read besides earlier stages' outputs."""

    cfg: ExperimentConfig
    ds: Any  # spot.data.dataset.Dataset (qlearning view)
    card: dict[str, Any]
    env_name: str
    tracker: Tracker
    keys: dict[str, Any]  # PRNG keys per stage: reward, cvae, shaping, policy
    progress: bool = True
    on_eval: Callable[[dict[str, float]], None] | None = None
    artifacts: Path = field(default_factory=lambda: run_temp.run_temp_dir())  # $SPOT_CACHE_DIR/tmp
    times: dict[str, float] = field(default_factory=dict)
    cache_hits: list[str] = field(default_factory=list)  # stage-cache keys read (hits), in order
    # stage -> (key, value) computed for this run outside its stage (seed_mode vmap: the seeds'
    # reward models as one program); the stage stores and logs it as computed (:meth:`cached`)
    precomputed: dict[str, tuple[str, Any]] = field(default_factory=dict)
    # added to every stage's deps: ``{"seed_mode": "vmap"}`` in a vmap trial, whose reward models
    # and CVAEs differ from one-seed training in the last bits (more after Adam): kept apart, so a
    # one-seed run never depends on whether a vmap trial filled the cache first
    key_extra: dict[str, Any] = field(default_factory=dict)

    def log(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        self.tracker.log_metrics(metrics, step=step)

    @contextmanager
    def timed(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            k = f"time/{name}_s"
            self.times[k] = self.times.get(k, 0.0) + time.perf_counter() - t0

    def stage(self, name: str, fn: Callable[..., Any], *inputs: Any) -> Any:
        """Run one stage, timed as ``time/<name>_s`` (stages marked :func:`untimed` are not)."""
        if getattr(fn, "untimed", False):
            return self._run_evicting(name, fn, inputs)
        with self.timed(name):
            return self._run_evicting(name, fn, inputs)

    def _run_evicting(self, name: str, fn: Callable[..., Any], inputs: tuple) -> Any:
        """``fn(self, *inputs)``; when it fails on a value its stage-cache hits returned (an entry
        that decodes, digest and all, to a value of the wrong structure: KeyError, TypeError...),
        those entries are deleted and the stage runs once more, computing them again."""
        before = len(self.cache_hits)
        try:
            return fn(self, *inputs)
        except SpotError:
            raise
        except (KeyError, TypeError, AttributeError, IndexError, ValueError) as e:
            hits = self.cache_hits[before:]
            if not hits:
                raise
            del self.cache_hits[before:]
            import warnings

            warnings.warn(
                f"stage '{name}': cached entries {hits} do not fit it ({type(e).__name__}: {e}); "
                "deleting and recomputing them",
                stacklevel=2,
            )
            for k in hits:
                cache._store().delete(f"{k}.npz")  # the entry's store (local folder or spot.store URI)
            return fn(self, *inputs)

    def _precomputed(self, name: str, key: str, compute: Callable[[], Any]) -> Callable[[], Any]:
        """What computes stage ``name``'s entry ``key`` on a miss: the value computed for it outside
        the stage when its key is this one, else ``compute`` (with a warning: the two computed the
        key differently, so the value was not used)."""
        pre_key, value = self.precomputed.pop(name)
        if pre_key == key:
            return lambda: value
        import warnings

        warnings.warn(
            f"stage '{name}': a value computed for key {pre_key} does not fit key {key}; computing it here",
            stacklevel=3,
        )
        return compute

    def cached(
        self, name: str, deps: dict[str, Any], compute: Callable[[], Any], code: str | None = None
    ) -> tuple[Any, str]:
        """``(value, key)`` of stage ``name`` from the stage cache (computed and stored on a miss);
        tags the run ``spot.cache.<name>`` = ``hit`` or ``miss`` (a tag, not a metric: it is a fact
        about the run, not a measurement) and ``stage.<name>.source`` = ``computed`` or ``reused`` and
        ``stage.<name>.key`` = the entry's key (the run that computed an entry others reused: the one
        with the same key and ``computed``). ``code``: the stage's code version (default: that of
        ``compute``'s stage function, :func:`spot.cache.code_version`); ``deps`` get :attr:`key_extra`."""
        deps = {**deps, **self.key_extra}
        if name in self.precomputed:
            code = code if code is not None else cache.code_version(compute)
            compute = self._precomputed(name, cache.key(name, deps, code), compute)
        value, hit, key = cache.cached(name, deps, compute, code)
        if hit:
            self.cache_hits.append(key)
        self.tracker.set_tags(
            {
                f"cache.{name}": "hit" if hit else "miss",
                f"stage.{name}.source": "reused" if hit else "computed",
                f"stage.{name}.key": key,
            }
        )
        return value, key


def save_model(ctx: Context, name: str, what: str, value: Any, sections: tuple[str, ...], **extra: Any) -> None:
    """Save a trained model as the run's ``models/<name>`` artifacts (:mod:`spot.tracking.models`),
    its header naming the config ``sections`` it was built with."""
    from spot import tracking

    cfg = config_lib.to_flat(ctx.cfg)
    section_cfg = {s: {k.split(".", 1)[1]: v for k, v in cfg.items() if k.startswith(f"{s}.")} for s in sections}
    tracking.save_model(
        ctx.tracker,
        ctx.artifacts / "models",
        name,
        what,
        value,
        {"method": ctx.cfg.method, **section_cfg},
        dataset=ctx.card.get("name", ctx.cfg.data.name),
        **extra,
    )


def untimed(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Mark a stage that computes nothing worth timing (e.g. the Oracle's "reward model"), so that
    Table 8 charges no reward-model time to methods without one."""
    fn.untimed = True  # type: ignore[attr-defined]
    return fn


def dataset_deps(ds: Any) -> dict[str, Any]:
    """What identifies the dataset in stage-cache keys: the fingerprint of all its arrays
    (:meth:`spot.data.dataset.Dataset.fingerprint`: episode ends, next observations and infos too)."""
    return {"dataset": ds.fingerprint()}
