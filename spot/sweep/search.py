"""Search and early stopping in a sweep file: ``metric``/``mode``, ``search:`` and ``scheduler:``.

``search:`` replaces the grid by a Ray Tune searcher (Optuna's TPE through
``ray.tune.search.optuna.OptunaSearch``, or HyperOpt's through
``ray.tune.search.hyperopt.HyperOptSearch``) that proposes ``num_samples`` configs from ranges and
choices over dotted config keys. ``scheduler:`` stops trials early on the declared ``metric``
(ASHA, ``ray.tune.schedulers.ASHAScheduler``, or median stopping,
``ray.tune.schedulers.MedianStoppingRule``), counting time in Tune's ``training_iteration``: one
result per evaluation (module :mod:`spot.sweep.trial`). The blocks are validated here (one
:class:`spot.SpotError` line naming the key); the Tune objects are built by :func:`searcher`,
:func:`scheduler` and :func:`space`, which import Ray, Optuna and HyperOpt only when called.
Format: docs/sweeps.md, "Search and early stopping".
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

from spot import SpotError
from spot import config as config_lib

METRICS = ("eval/score", "reward/best_eval_acc", "reward/best_eval_loss")
"""What a trial reports to Tune: the online evaluation's score at each evaluation, and the reward
model's held-out accuracy and loss (of the checkpoint kept) once the reward stage is done."""
OFFLINE_SAFE = ("reward/best_eval_acc", "reward/best_eval_loss")
"""Metrics that need no environment: the reward model's held-out preference accuracy and loss."""
MODES = ("max", "min")
ALGORITHMS = ("optuna", "hyperopt")
SEARCH_KEYS = ("algorithm", "num_samples", "space", "seed")
DOMAINS = ("uniform", "loguniform", "randint", "choice")
SCHEDULERS = ("asha", "median")
SCHEDULER_KEYS = {
    "asha": ("name", "grace_period", "reduction_factor", "max_t"),
    "median": ("name", "grace_period", "min_samples_required"),
}
MAX_SAMPLES = 10_000
"""Most configs a searcher may propose (the grid's limit, spot.sweep.spec.MAX_RUNS)."""
STOPPER_NAMES = {"asha": "ASHA", "median": "median stopping"}
SEARCHER_NAMES = {
    "optuna": "Optuna's TPE (ray.tune.search.optuna.OptunaSearch)",
    "hyperopt": "HyperOpt's TPE (ray.tune.search.hyperopt.HyperOptSearch)",
}
SCHEDULER_CLASSES = {"asha": "ray.tune.schedulers.ASHAScheduler", "median": "ray.tune.schedulers.MedianStoppingRule"}
SCHEDULER_DEFAULTS = {
    "asha": {"grace_period": 1, "reduction_factor": 2, "max_t": 1000},
    "median": {"grace_period": 1, "min_samples_required": 3},
}
"""The options spot gives a scheduler the file leaves out (time: Tune's ``training_iteration``)."""
SMOKE_SEARCH_KEYS = ("num_samples",)


@dataclass(frozen=True)
class Search:
    algorithm: str
    num_samples: int
    space: dict[str, tuple[str, list[Any]]]
    """config key -> (domain, arguments): ``("loguniform", [0.5, 10])``, ``("choice", [0.1, 0.5])``."""
    seed: int = 0


@dataclass(frozen=True)
class Scheduler:
    name: str
    options: dict[str, int]


def _err(where: str, key: str, msg: str) -> SpotError:
    return SpotError(f"{where}: '{key}': {msg}")


def _known(block: Any, allowed: tuple[str, ...], where: str, key: str) -> dict[str, Any]:
    import difflib

    if not isinstance(block, dict):
        raise _err(where, key, f"expected a mapping with keys {', '.join(allowed)}, got {config_lib.shown(block)}")
    for k in block:
        if k not in allowed:
            close = difflib.get_close_matches(str(k), allowed, n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise _err(where, f"{key}.{k}", f"unknown key{hint} (expected {', '.join(allowed)})")
    return block


def _int(value: Any, where: str, key: str, low: int, high: int | None = None) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < low or (high is not None and value > high):
        bound = f"an integer >= {low}" + (f" and <= {high:,}" if high is not None else "")
        raise _err(where, key, f"expected {bound}, got {config_lib.shown(value)}")
    return value


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _domain(value: Any, where: str, key: str) -> tuple[str, list[Any]]:
    """``{loguniform: [lo, hi]}`` and the like -> ``("loguniform", [lo, hi])``."""
    if not isinstance(value, dict) or len(value) != 1 or next(iter(value)) not in DOMAINS:
        raise _err(where, key, f"expected one of {', '.join(f'{{{d}: [...]}}' for d in DOMAINS)}, got {value!r}")
    ((kind, args),) = value.items()
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise _err(where, f"{key}.choice", f"expected a non-empty list of values, got {args!r}")
        return kind, args
    if not isinstance(args, list) or len(args) != 2 or not all(_number(a) for a in args):
        raise _err(where, f"{key}.{kind}", f"expected [low, high] (two finite numbers), got {args!r}")
    low, high = args
    if low >= high:
        raise _err(where, f"{key}.{kind}", f"expected low < high, got [{low}, {high}]")
    if kind == "loguniform" and low <= 0:
        raise _err(where, f"{key}.{kind}", f"expected low > 0 (a log scale), got {low}")
    if kind == "randint" and not all(isinstance(a, int) for a in args):
        raise _err(where, f"{key}.{kind}", f"expected two integers (high excluded), got {args!r}")
    return kind, [low, high]


def check_search(block: Any, where: str, reserved: tuple[str, ...]) -> Search:
    """The ``search:`` block, its ``space`` keys checked as config keys (not ``reserved`` ones)."""
    block = _known(block, SEARCH_KEYS, where, "search")
    algorithm = block.get("algorithm")
    if algorithm not in ALGORITHMS:
        raise _err(where, "search.algorithm", f"expected one of {', '.join(ALGORITHMS)}, got {algorithm!r}")
    if "num_samples" not in block:
        raise _err(where, "search.num_samples", "missing (how many configs the searcher proposes)")
    num_samples = _int(block["num_samples"], where, "search.num_samples", 1, MAX_SAMPLES)
    seed = _int(block.get("seed", 0), where, "search.seed", 0)
    raw = block.get("space")
    if not isinstance(raw, dict) or not raw:
        raise _err(where, "search.space", f"expected a mapping of config keys to ranges, got {raw!r}")
    at = f"{where}: 'search.space'"
    # the domains are mappings themselves: flatten_yaml would descend into them
    flat = {k: v for k, v in config_lib.flatten_yaml({k: 0 for k in raw}, at).items()}
    config_lib.check_keys(flat, at)
    for key in flat:
        if key in reserved:
            raise _err(where, f"search.space.{key}", "may not be searched (set by the sweep)")
    space = {str(k): _domain(v, where, f"search.space.{k}") for k, v in raw.items()}
    return Search(algorithm, num_samples, space, seed)


def check_scheduler(block: Any, where: str) -> Scheduler:
    name = block.get("name") if isinstance(block, dict) else None
    if name not in SCHEDULERS:
        raise _err(where, "scheduler.name", f"expected one of {', '.join(SCHEDULERS)}, got {name!r}")
    _known(block, SCHEDULER_KEYS[name], where, "scheduler")
    return Scheduler(name, _scheduler_values(name, block, {}, where, "scheduler"))


def _scheduler_values(name: str, block: dict[str, Any], under: dict[str, int], where: str, key: str) -> dict[str, int]:
    """``block``'s options but ``name``, checked, over ``under``; the ``max_t`` it runs with (given or
    spot's default) at least its ``grace_period``. Errors name ``<key>.<option>``."""
    given = {
        k: _int(v, where, f"{key}.{k}", 2 if k == "reduction_factor" else 1) for k, v in block.items() if k != "name"
    }
    options = {**under, **given}
    ran = {**SCHEDULER_DEFAULTS[name], **options}
    if "max_t" in ran and ran["max_t"] < ran["grace_period"]:
        if "max_t" in given or "grace_period" not in given:
            raise _err(where, f"{key}.max_t", f"expected at least grace_period ({ran['grace_period']})")
        raise _err(where, f"{key}.grace_period", f"expected at most max_t ({ran['max_t']})")
    return options


def check_objective(data: dict[str, Any], where: str) -> tuple[str | None, str | None]:
    """``metric`` and ``mode``: both needed with ``search:`` or ``scheduler:``, neither without."""
    metric, mode = data.get("metric"), data.get("mode")
    uses = [k for k in ("search", "scheduler") if k in data]
    if not uses:
        if metric is not None or mode is not None:
            raise _err(where, "metric" if metric is not None else "mode", "only goes with 'search:' or 'scheduler:'")
        return None, None
    if metric is None:
        raise _err(where, "metric", f"missing: '{uses[0]}:' needs the metric to act on ({', '.join(METRICS)})")
    if metric not in METRICS:
        raise _err(where, "metric", f"expected one of {', '.join(METRICS)}, got {config_lib.shown(metric)}")
    if mode not in MODES:
        raise _err(where, "mode", f"expected max or min, got {config_lib.shown(mode)}")
    return metric, mode


def endpoints(search: Search) -> list[dict[str, Any]]:
    """Configs at the space's ends (each range's low and high, each choice): checked by resolving
    them before anything starts (one per value, the other keys at their first)."""
    first = {k: args[0] for k, (_, args) in search.space.items()}
    out = [first]
    for key, (kind, args) in search.space.items():
        values = args[1:] if kind == "choice" else [args[1] - 1 if kind == "randint" else args[1]]
        out.extend({**first, key: v} for v in values)
    return out


def domain_text(kind: str, args: list[Any]) -> str:
    """A searched key's domain as the file gives it: ``loguniform [0.5, 10]``, ``choice ["a", "b"]``."""
    return f"{kind} {json.dumps(args)}"


def counts(sweep: Any) -> tuple[int, int]:
    """``(trials, runs)`` a launch of ``sweep`` (:class:`spot.sweep.spec.Sweep`) makes: a searcher's
    ``num_samples`` trials, each running every seed; else the grid's trials and (config, seed) runs."""
    if sweep.search is not None:
        return sweep.search.num_samples, sweep.search.num_samples * len(sweep.seeds)
    return len(sweep.trials()), len(sweep.runs())


def parent_params(sweep: Any) -> dict[str, Any]:
    """The search setup as params of the launch's parent run: ``sweep.metric``/``sweep.mode``,
    ``search.algorithm|num_samples|seed``, ``search.space.<key>`` (its domain), ``scheduler.name``
    and every option the scheduler runs with (spot's defaults included), and for a search sweep the
    ``sweep.trials``/``sweep.runs`` it makes (the trial list holds only the template the searcher
    completes). Empty for a grid sweep without a scheduler."""
    out: dict[str, Any] = {}
    if sweep.metric is not None:
        out.update({"sweep.metric": sweep.metric, "sweep.mode": sweep.mode})
    if sweep.search is not None:
        found = sweep.search
        out.update(dict(zip(("sweep.trials", "sweep.runs"), counts(sweep), strict=True)))
        out.update(
            {"search.algorithm": found.algorithm, "search.num_samples": found.num_samples, "search.seed": found.seed}
        )
        out.update({f"search.space.{k}": domain_text(kind, args) for k, (kind, args) in found.space.items()})
    if sweep.scheduler is not None:
        out["scheduler.name"] = sweep.scheduler.name
        out.update({f"scheduler.{k}": v for k, v in scheduler_options(sweep.scheduler).items()})
        out["scheduler.time_attr"] = "training_iteration"
    return out


# --------------------------------------------------------------------------- the Tune objects
def space(search: Search) -> dict[str, Any]:
    from ray import tune

    build = {"uniform": tune.uniform, "loguniform": tune.loguniform, "randint": tune.randint}
    return {
        k: tune.choice(args) if kind == "choice" else build[kind](*args) for k, (kind, args) in search.space.items()
    }


def searcher(search: Search) -> Any:
    """Tune's searcher for ``search`` (its own ``seed``: the same file proposes the same configs)."""
    try:
        if search.algorithm == "optuna":
            import optuna
            from ray.tune.search.optuna import OptunaSearch

            optuna.logging.set_verbosity(optuna.logging.WARNING)
            return OptunaSearch(sampler=optuna.samplers.TPESampler(seed=search.seed))
        from ray.tune.search.hyperopt import HyperOptSearch

        return HyperOptSearch(random_state_seed=search.seed)
    except ImportError as e:  # a dependency of spot-pbrl (pyproject.toml), missing from this environment
        raise SpotError(
            f"search.algorithm {search.algorithm}: {e.name or search.algorithm} is not installed "
            f"(pip install {search.algorithm})"
        ) from None


def scheduler_options(sched: Scheduler) -> dict[str, int]:
    """Every option the scheduler runs with: the file's, else spot's :data:`SCHEDULER_DEFAULTS`."""
    return {**SCHEDULER_DEFAULTS[sched.name], **sched.options}


def scheduler(sched: Scheduler) -> Any:
    from ray.tune import schedulers

    opts = scheduler_options(sched)
    if sched.name == "asha":
        return schedulers.ASHAScheduler(time_attr="training_iteration", **opts)
    return schedulers.MedianStoppingRule(time_attr="training_iteration", **opts)


# --------------------------------------------------------------------------- the sweep file's checks
def check(
    data: dict[str, Any], fields: dict[str, Any], where: str, reserved: tuple[str, ...], smoke: bool = False
) -> dict[str, Any]:
    """The sweep's ``metric``, ``mode``, ``search`` and ``scheduler`` fields, checked against the
    rest of the file (``fields``: its validated fields); with ``smoke``, the ``smoke:`` block's
    ``search``/``scheduler`` applied (:func:`apply_smoke`; checked either way)."""
    metric, mode = check_objective(data, where)
    found = check_search(data["search"], where, reserved) if "search" in data else None
    sched = check_scheduler(data["scheduler"], where) if "scheduler" in data else None
    smoked = apply_smoke(data.get("smoke", {}), found, sched, where)
    if smoke:
        found, sched = smoked
    if found is not None:
        for section in ("grid", "zip"):
            if fields[section]:
                raise _err(where, section, "goes with 'search:' only as the searcher's space ('search.space')")
        for key in found.space:
            if key in fields["base"]:
                raise _err(where, f"base.{key}", "is also searched ('search.space'); give it in one place")
        if fields["seed_mode"] == "trials" and len(fields["seeds"]) > 1:
            raise _err(
                where,
                "seed_mode",
                "a searcher proposes one config per trial: with several seeds use seed_mode: sequential or vmap "
                "(every seed of a proposed config in its trial)",
            )
    return {"metric": metric, "mode": mode, "search": found, "scheduler": sched}


def apply_smoke(
    block: Any, found: Search | None, sched: Scheduler | None, where: str
) -> tuple[Search | None, Scheduler | None]:
    """The smoke block's ``search: {num_samples: N}`` (at most the file's) and ``scheduler:`` (any of
    the file's scheduler's options but ``name``, e.g. a lower ``max_t`` or ``grace_period``) applied
    to the file's search and scheduler. Errors name ``smoke.search.<key>`` / ``smoke.scheduler.<key>``."""
    if not isinstance(block, dict):  # refused by spot.sweep.spec before this
        return found, sched
    if "search" in block:
        if found is None:
            raise _err(where, "smoke.search", "the file has no 'search:' block for it to shrink")
        part = _known(block["search"], SMOKE_SEARCH_KEYS, where, "smoke.search")
        if "num_samples" in part:
            n = part["num_samples"]
            if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= found.num_samples:
                raise _err(
                    where,
                    "smoke.search.num_samples",
                    f"expected an integer from 1 to search.num_samples ({found.num_samples}), "
                    f"got {config_lib.shown(n)}",
                )
            found = dataclasses.replace(found, num_samples=n)
    if "scheduler" in block:
        if sched is None:
            raise _err(where, "smoke.scheduler", "the file has no 'scheduler:' block for it to shorten")
        part = block["scheduler"]
        if isinstance(part, dict) and "name" in part:
            raise _err(where, "smoke.scheduler.name", f"a smoke launch keeps the file's scheduler ({sched.name})")
        part = _known(part, tuple(k for k in SCHEDULER_KEYS[sched.name] if k != "name"), where, "smoke.scheduler")
        sched = Scheduler(sched.name, _scheduler_values(sched.name, part, sched.options, where, "smoke.scheduler"))
    return found, sched


def check_trials(sweep: Any, where: str, check_trial: Any, trial_cls: Any) -> None:
    """Resolve the configs at the ends of the searched space (``check_trial``:
    :func:`spot.sweep.spec._check_trial`; ``trial_cls``: :class:`spot.sweep.spec.Trial`, passed in
    so that this module does not import the one that imports it), and refuse a reward-model metric
    for a trial whose method trains no reward model."""
    trials = list(sweep.trials())
    if sweep.search is not None:
        trials = [
            trial_cls(e, {**sweep.base, **e}, sweep.seeds, sweep.seed_mode == "vmap") for e in endpoints(sweep.search)
        ]
    for trial in trials:
        cfg = check_trial(trial, where)
        if sweep.metric in OFFLINE_SAFE and cfg.reward.kind in ("none", "ipl"):
            raise _err(
                where,
                "metric",
                f"{sweep.metric} is the reward model's, but trial {trial.label} (method {cfg.method}) trains "
                "none; use eval/score",
            )
