"""Rows padded to a bucket, so that datasets of different sizes share compiled programs.

A jitted program that takes a dataset's arrays (``[N, ...]``) is compiled for that ``N``: the
Table 1 smoke launch's two datasets of each environment (``hopper-medium-replay`` and
``hopper-medium-expert``, ``lift-ph`` and ``lift-mh``, ...) compiled every such program twice, in
every trial process. Padding the rows to :func:`bucket` (the next power of two, at least
:data:`MIN_ROWS`) gives every dataset of an environment's tiny size the same shapes, and the
programs that only *index* the rows (minibatch draws, relabelling batches, segment starts) the
same compiled program: in a process (jit's cache) and across the processes of a machine (the
persistent compilation cache, :mod:`spot.runtime`).

Padding leaves every number unchanged:

* The padded rows are zeros that nothing reads: draws go to ``[0, count)``, with ``count`` the
  real number of rows passed as a traced int32 (:class:`Rows`). ``jax.random.randint`` computes
  the same integers for a traced bound as for a static one of the same value (it is itself a
  jitted function of ``minval``/``maxval``, in integer arithmetic), so a run draws the same
  minibatches padded or not; relabelling reads only rows of real episodes.
* tests/test_padding_compiles.py checks both: the same draws and states for padded and unpadded
  data, and a seed-0 tiny run's scores and losses equal to the last digit.

What cannot be padded: observation and action sizes. They are the networks' input and output
sizes, so padding them would change the networks (their parameters, initialisation and outputs);
programs of different environments stay separate.

Cost: memory only (at most twice the rows, and :data:`MIN_ROWS` rows of a tiny dataset: 5 MB for
Meta-World's 39-dimensional observations); no program's work grows with the padding, since the
programs index rows rather than compute over all of them.

Padded: the IQL and IPL chunks' transitions (:mod:`spot.run.policy_stages`), HPL's unlabelled
segments and regulariser rows (:func:`spot.reward.hpl.train_hpl`), the arrays the relabelling
programs index (:mod:`spot.reward.relabel`), and the CVAE's triplets (:func:`spot.subgoal.cvae.bucket`,
a minimum of 64). A vmapped trial's IQL (:func:`spot.policy.iql.make_vmapped_train_chunk`) takes
padded rows with ``padded=True``. Still compiled per dataset: the reward model's chunk when the
number of training pairs differs (its minibatches are a permutation of the pairs, whose draws
depend on their number), the CVAE's train/held-out permutation of the subgoals (the same) and
the shaping's eager array operations (small programs, left as they are).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

MIN_ROWS = 1 << 14  # every tiny dataset (at most ~4,000 rows) pads to this: one program per env


class Rows(NamedTuple):
    """``data``: a pytree of arrays ``[bucket, ...]`` whose first ``count`` rows are real (the
    rest zeros, never read); ``count``: int32 ``[]``. A pytree, so it passes through jit with
    ``count`` traced (one program for every ``count`` of a bucket)."""

    data: Any
    count: Any


def bucket(n: int, min_rows: int = MIN_ROWS) -> int:
    """Rows of the padded arrays of an ``n``-row dataset: the next power of two ``>= n``, at least
    ``min_rows`` (``bucket(1498) == bucket(4000) == 16384``; ``bucket(402_000) == 524_288``)."""
    if n < 0:
        raise ValueError(f"n={n}: expected >= 0")
    return max(min_rows, 1 << max(n - 1, 0).bit_length())


def _leading(tree: Any) -> int:
    import jax

    leaves = jax.tree.leaves(tree)
    if not leaves:
        raise ValueError("no arrays to pad")
    n = int(np.shape(leaves[0])[0])
    if any(int(np.shape(x)[0]) != n for x in leaves):
        raise ValueError(f"arrays with different numbers of rows: {[np.shape(x) for x in leaves]}")
    return n


def pad_rows(tree: Any, rows: int | None = None) -> Any:
    """Host arrays ``[N, ...]`` (a pytree) zero-padded to ``rows`` rows (default :func:`bucket` of
    ``N``); unchanged when ``N`` is already ``rows``."""
    import jax

    n = _leading(tree)
    rows = bucket(n) if rows is None else rows
    if rows < n:
        raise ValueError(f"cannot pad {n} rows to {rows}")
    if rows == n:
        return tree

    def pad(x: Any) -> np.ndarray:
        x = np.asarray(x)
        return np.concatenate([x, np.zeros((rows - n, *x.shape[1:]), x.dtype)])

    return jax.tree.map(pad, tree)


def padded(tree: Any) -> Rows:
    """``Rows(pad_rows(tree), int32 N)``: a dataset's arrays as one program's argument for every
    ``N`` of a bucket (module docstring)."""
    return Rows(pad_rows(tree), np.int32(_leading(tree)))


def count(data: Any) -> Any:
    """Real rows of ``data``: ``data.count`` of :class:`Rows`, else the leading size of a plain
    pytree of arrays (a Python int, static under jit)."""
    return data.count if isinstance(data, Rows) else _leading(data)


def rows_of(data: Any) -> Any:
    """The arrays of ``data``: ``data.data`` of :class:`Rows`, else ``data`` itself."""
    return data.data if isinstance(data, Rows) else data


def part(data: Any, fn: Any) -> Any:
    """``fn`` of the arrays of ``data``, as :class:`Rows` with the same ``count`` when ``data`` is
    (``part(rows, lambda u: u.x)``: one field of padded rows), else ``fn(data)``."""
    return Rows(fn(data.data), data.count) if isinstance(data, Rows) else fn(data)


def take(data: Any, idx: Any) -> Any:
    """Rows ``idx`` of every array of ``data`` (:class:`Rows` or a plain pytree)."""
    import jax

    return jax.tree.map(lambda x: x[idx], rows_of(data))
