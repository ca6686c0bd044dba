"""The one training loop of spot's learners (reward models, HPL, the CVAE, IQL and IPL).

A learner supplies a pure ``update(state, *args) -> (state, metrics)`` that takes one gradient
step (drawing its minibatch inside jit from ``fold_in(key, state.step)``); this module runs it:

* :func:`make_chunk`: ``chunk(state, n, *args)`` runs ``n <= length`` updates as one jitted
  ``lax.scan`` (the state is donated). Every chunk of a run compiles once: the last, shorter
  chunk runs the same program with ``n`` below ``length``, so a run does exactly ``steps``
  updates (:func:`chunk_sizes`). Its metrics come back as

  - ``"stack"``: per-update arrays ``[length]`` and a bool ``"active"`` (updates past ``n`` are
    skipped by a ``lax.cond`` and report zeros): for learners that name the exact failing step;
  - ``"mean"``: means over the ``n`` updates (same masking);
  - ``"sum"``: means over the ``n`` updates accumulated in the loop carry, which runs exactly
    ``n`` iterations (a ``fori_loop`` with a traced bound: no per-update ``cond``; IQL's hot loop).

* :func:`pad_minibatches`: held-out data as equal ``[M, size, ...]`` minibatches (the last padded
  with row 0 at weight 0), so an evaluation is one compiled ``lax.map``.
* :func:`run`: the host loop: chunk, check losses for NaN/inf (:class:`spot.NonFiniteError` with
  the step and the loss name), evaluate, keep the parameters of the best held-out loss, call back.

Compiled programs are kept by jit's own cache: learners memoise the jitted chunk per
configuration (``functools.lru_cache``), so a second run with the same config and shapes in one
process traces and compiles nothing (``chunk._cache_size()`` stays 1).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from spot import NonFiniteError, SpotError

REDUCTIONS = ("stack", "mean", "sum")


def chunk_sizes(steps: int, chunk: int) -> list[int]:
    """Updates per chunk for a run of exactly ``steps`` updates: ``chunk`` each, the last one the
    remainder (``chunk_sizes(1500, 1000) == [1000, 500]``)."""
    if steps < 1 or chunk < 1:
        raise SpotError(f"steps={steps} and chunk={chunk} must both be >= 1")
    full, rest = divmod(steps, chunk)
    return [chunk] * full + ([rest] if rest else [])


def chunk_length(steps: int, chunk: int) -> int:
    """Compiled scan length of a run: ``chunk``, or ``steps`` when the run is shorter."""
    return min(steps, chunk)


def _zeros_like_metrics(update: Callable, state: Any, *args: Any) -> dict[str, jax.Array]:
    shapes = jax.eval_shape(update, state, *args)[1]
    return jax.tree.map(lambda m: jnp.zeros(m.shape, m.dtype), shapes)


def _mean(total: jax.Array, n: jax.Array, length: int) -> jax.Array:
    """``total / n``; a full chunk divides by the constant ``length`` (XLA turns that into a
    multiply by its reciprocal, as ``jnp.mean`` over the chunk does: the same last bits)."""
    return jnp.where(n == length, total / length, total / n.astype(total.dtype))


def chunk_fn(update: Callable, length: int, reduce: str = "stack") -> Callable:
    """The un-jitted ``chunk(state, n, *args) -> (state, metrics)`` of :func:`make_chunk` (vmap it
    for several seeds: ``n`` is shared, so the masking stays a real branch, not a select)."""
    if reduce not in REDUCTIONS:
        raise ValueError(f"reduce={reduce!r}; expected one of {REDUCTIONS}")

    def chunk(state: Any, n: jax.Array, *args: Any) -> tuple[Any, dict[str, jax.Array]]:
        idle = _zeros_like_metrics(update, state, *args)
        if reduce == "sum":
            # Metrics summed in the carry: one fused add per update instead of a stacked output per
            # metric (~2 % of an IQL update at the reference sizes).
            def body(_: jax.Array, carry: tuple) -> tuple:
                state, sums = carry
                state, metrics = update(state, *args)
                return state, jax.tree.map(jnp.add, sums, metrics)

            state, sums = jax.lax.fori_loop(0, n, body, (state, idle))
            return state, jax.tree.map(lambda m: _mean(m, n, length), sums)

        def step(state: Any, i: jax.Array) -> tuple[Any, dict[str, jax.Array]]:
            active = i < n
            state, metrics = jax.lax.cond(active, lambda s: update(s, *args), lambda s: (s, idle), state)
            return state, {**metrics, "active": active}

        state, metrics = jax.lax.scan(step, state, jnp.arange(length))
        if reduce == "mean":  # skipped updates report zeros, so the sum runs over the active ones
            del metrics["active"]
            metrics = jax.tree.map(lambda m: _mean(jnp.sum(m, axis=0), n, length), metrics)
        return state, metrics

    return chunk


class Chunk:
    """A jitted chunk, called as ``chunk(state, n, *args)``. ``n`` (any int) is passed to jit as an
    int32 array, so every chunk of a run, the shorter last one included, hits one compiled program."""

    def __init__(self, jitted: Callable) -> None:
        self.jitted = jitted

    def __call__(self, state: Any, n: int | jax.Array, *args: Any) -> tuple[Any, dict[str, jax.Array]]:
        return self.jitted(state, jnp.asarray(n, jnp.int32), *args)

    def lower(self, state: Any, n: int | jax.Array, *args: Any) -> Any:
        """``jax.jit(...).lower`` with the same argument types as a call."""
        return self.jitted.lower(state, jnp.asarray(n, jnp.int32), *args)

    def _cache_size(self) -> int:
        """Programs jit compiled for this chunk (1 for a run, whatever its number of chunks)."""
        return self.jitted._cache_size()


def make_chunk(update: Callable, length: int, reduce: str = "stack", vmap_axes: tuple | None = None) -> Chunk:
    """Jitted ``chunk(state, n, *args) -> (state, metrics)``: ``n <= length`` updates of
    ``update(state, *args)`` in one scan; the state is donated (module docstring for ``reduce``).

    ``vmap_axes``: ``in_axes`` of ``(state, *args)`` to vmap the chunk over seeds (``n`` is shared).
    """
    fn = chunk_fn(update, length, reduce)
    if vmap_axes is not None:
        fn = jax.vmap(fn, in_axes=(vmap_axes[0], None, *vmap_axes[1:]))
    return Chunk(jax.jit(fn, donate_argnums=0))


def compile_seconds(fn: Callable, *args: Any) -> float:
    """Compile jitted ``fn`` for ``args`` ahead of its first call and return the seconds it took
    (the executable lands in jit's cache; next to nothing when it was already compiled)."""
    t0 = time.perf_counter()
    fn.lower(*args).compile()
    return time.perf_counter() - t0


def pad_minibatches(tree: Any, size: int) -> tuple[Any, np.ndarray]:
    """Host arrays ``[Q, ...]`` as ``[M, size, ...]`` minibatches, ``M = ceil(Q / size)``, the last
    padded by repeating row 0; ``weight [M, size]`` is 1 for real rows and 0 for padding."""
    q = int(np.shape(jax.tree.leaves(tree)[0])[0])
    m = math.ceil(q / size)
    idx = np.concatenate([np.arange(q), np.zeros(m * size - q, np.int64)])
    weight = (np.arange(m * size) < q).astype(np.float32).reshape(m, size)
    return jax.tree.map(lambda a: np.asarray(a)[idx].reshape(m, size, *np.shape(a)[1:]), tree), weight


def check_finite(metrics: Mapping[str, Any], step: int, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Fetch metrics to the host and raise :class:`spot.NonFiniteError` (``step``, the metric's name)
    if one of ``names`` (default: every metric ending in ``loss``) holds a NaN/inf."""
    host = jax.device_get(dict(metrics))
    for name, value in host.items():
        if (name in names) if names is not None else name.endswith("loss"):
            value = np.asarray(value)
            bad = value[~np.isfinite(value)]
            if bad.size:
                raise NonFiniteError(step, name, float(bad.ravel()[0]))
    return host


# The config keys that scale each learner's losses, most likely culprit first: a loss that overflows
# to NaN/inf names them with their values (:func:`name_keys`). Keyed by the loss name's prefix.
NONFINITE_KEYS: dict[str, tuple[str, ...]] = {
    "iql/": ("iql.lr", "iql.temperature", "iql.discount", "relabel.scale", "shaping.weight"),
    "ipl/": ("iql.lr", "iql.temperature", "iql.discount", "ipl.chi2_coeff"),
    "cvae/": ("cvae.lr", "cvae.beta"),
    "hpl/": ("hpl.lr", "hpl.kl_coef", "hpl.reg_coef"),
    "reward/pt": ("pt.lr", "pt.peak_factor", "pt.b2"),  # reward/ losses of reward.kind=pt
    "reward/mr": ("mr.lr",),
}


def suspect_keys(loss_name: str, cfg: Any) -> list[tuple[str, Any, Any]]:
    """``[(dotted key, value, default)]`` of the config keys that scale ``loss_name``
    (:data:`NONFINITE_KEYS`), read from ``cfg`` (a :class:`spot.config.ExperimentConfig`; this layer
    only reads attributes), the values furthest from their defaults first (by orders of magnitude;
    a key whose default is 0 and value is not counts as furthest)."""
    prefix = loss_name.split("/", 1)[0] + "/"
    if prefix == "reward/":
        prefix += str(getattr(getattr(cfg, "reward", None), "kind", ""))
    out = []
    for key in NONFINITE_KEYS.get(prefix, ()):
        stage, sub = key.split(".")
        section = getattr(cfg, stage, None)
        value = getattr(section, sub, None)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            defaults = (
                {f.name: f.default for f in dataclasses.fields(section)} if dataclasses.is_dataclass(section) else {}
            )
            out.append((key, value, defaults.get(sub, value)))
    return sorted(out, key=lambda kvd: -_distance(kvd[1], kvd[2]))


def _distance(value: float, default: Any) -> float:
    """Orders of magnitude between a value and its default."""
    if not isinstance(default, (int, float)) or value == default:
        return 0.0
    if value == 0 or default == 0:
        return math.inf
    return abs(math.log10(abs(value) / abs(default)))


def name_keys(error: NonFiniteError, cfg: Any) -> NonFiniteError:
    """Add to ``error``'s message the config keys that scale its loss and their values, the values
    furthest from their defaults first (once), so that a run failed by an overflow says which
    settings to look at; returns ``error``."""
    if getattr(error, "suspects", None) is None:
        error.suspects = suspect_keys(error.loss_name, cfg)
        if error.suspects:
            keys = ", ".join(f"{k}={v!r}" + (f" (default {d!r})" if v != d else "") for k, v, d in error.suspects)
            error.args = (f"{error.args[0] if error.args else error}; the config keys that scale this loss: {keys}",)
    return error


def _chunk_row(metrics: dict[str, np.ndarray], done: int, n: int, losses: Mapping[str, str] | None) -> dict[str, Any]:
    """Check the chunk's losses (``losses``: metric -> reported name; None: every metric ending in
    ``loss``, under its own name) and reduce the chunk to one row of means. Stacked metrics name
    the failing update (``done + i``), chunk means the chunk's end (``done + n``)."""
    active = metrics.pop("active", None)
    if losses is None:
        losses = {name: name for name in metrics if name.endswith("loss")}
    for name, reported in losses.items():
        value = np.asarray(metrics[name])
        value = value.ravel() if active is None else value[active]
        bad = np.flatnonzero(~np.isfinite(value))
        if bad.size:
            step = done + n if active is None else done + int(bad[0])
            raise NonFiniteError(step, reported, float(value[bad[0]]))
    if active is None:
        return {k: float(v) if np.ndim(v) == 0 else np.asarray(v) for k, v in metrics.items()}
    return {k: float(np.asarray(v)[active].mean()) for k, v in metrics.items()}


@dataclass
class Run:
    """What :func:`run` returns: the final state, one row per chunk (``step`` = updates done, the
    chunk's mean metrics and the evaluation's), the best row and a host copy of its parameters
    (with ``best_by``), and the loop's wall seconds (compilation excluded when done beforehand)."""

    state: Any
    rows: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] | None = None
    best_params: Any = None
    loop_s: float = 0.0


def run(
    chunk: Callable,
    state: Any,
    args: tuple | Callable[[int], tuple],
    *,
    steps: int,
    length: int,
    losses: Mapping[str, str] | None = None,
    evaluate: Callable[[Any], Mapping[str, float]] | None = None,
    eval_loss: tuple[str, str] | None = None,
    best_by: str | None = None,
    params_of: Callable[[Any], Any] = lambda s: s.params,
    on_chunk: Callable[[dict[str, Any], Any], None] | None = None,
    progress: bool = False,
    desc: str = "train",
) -> Run:
    """Train for exactly ``steps`` updates in chunks of ``length`` (:func:`chunk_sizes`).

    Args:
      chunk: from :func:`make_chunk`; ``args``: its arguments after ``(state, n)``, or a function
        of the chunk index returning them (e.g. a key per chunk).
      losses: chunk metrics to check for NaN/inf -> the name :class:`spot.NonFiniteError` reports
        (default: every metric whose name ends in ``loss``).
      evaluate: ``evaluate(state) -> {name: value}`` after every chunk (held-out metrics).
      eval_loss: ``(key, reported name)`` of the evaluation's loss, checked for NaN/inf.
      best_by: evaluation key to minimise; the parameters (``params_of(state)``) of the best chunk
        are copied to the host (``Run.best_params``).
      on_chunk: ``on_chunk(row, state)`` after every chunk (do not keep ``state``: it is donated).
    """
    out = Run(state)
    best_value, done = math.inf, 0
    bar = tqdm(total=steps, desc=desc, disable=not progress, leave=False)
    t0 = time.perf_counter()
    for c, n in enumerate(chunk_sizes(steps, length)):
        chunk_args = args(c) if callable(args) else args
        out.state, metrics = chunk(out.state, n, *chunk_args)
        row = _chunk_row(jax.device_get(metrics), done, n, losses)
        done += n
        row = {"step": done, **row}
        if evaluate is not None:
            row.update({k: float(v) for k, v in evaluate(out.state).items()})
            if eval_loss is not None and not math.isfinite(row[eval_loss[0]]):
                raise NonFiniteError(done, eval_loss[1], row[eval_loss[0]])
        if best_by is not None and row[best_by] < best_value:
            best_value, out.best = row[best_by], row
            out.best_params = jax.tree.map(lambda a: np.array(a, copy=True), params_of(out.state))
        out.rows.append(row)
        if on_chunk is not None:
            on_chunk(row, out.state)
        bar.update(n)
    bar.close()
    out.loop_s = time.perf_counter() - t0
    return out


def column(rows: Sequence[Mapping[str, Any]], key: str) -> list[Any]:
    """One metric over the chunks: ``[row[key] for row in rows]``."""
    return [row[key] for row in rows]
