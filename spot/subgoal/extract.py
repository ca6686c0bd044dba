"""Attention-based subgoal extraction and CVAE training triplets (SPOT paper, §4.1.1-4.1.3).

For every labelled query the Preference Transformer gives, per step ``t`` of each segment, a
reward ``r̂_t`` and its preference-attention matrix ``A`` (``A_tj = softmax_j(q_t·k_j)``).
:func:`step_scores` turns them into the two per-step numbers the filter reads
(``subgoal.weight``, ``subgoal.filter_on``):

* the importance weight ``w_t`` (eq. 4): ``column_mean``, ``w_j = mean_t A_tj`` (the weight PT's
  segment logit ``mean_t z_t = Σ_j w_j r̂_j`` puts on step j, eq. 3; sums to 1), or ``diagonal``,
  ``w_t = A_tt`` (the attention step t pays to itself; the authors' code, SGPbrl
  ``JaxPref/PrefTransformer.py``);
* the value the reward filter compares with its segment mean: ``r_hat`` (``r̂_t``, eq. 5) or ``z``,
  the attention-weighted ``z_t = Σ_j A_tj r̂_j`` (the authors' code filters on PT's
  ``weighted_sum`` output).

Subgoals are taken from *preferred* segments only:

* :func:`preferred_segments` picks the preferred segment of each query: ``y = 1`` -> segment 2,
  ``y = 0`` -> segment 1. A tie (``y = 0.5``) prefers neither segment, so ties are skipped by
  default (``ties="both"`` keeps both segments of a tie instead).
* :func:`subgoal_mask` is the dual-criteria filter of eq. 5-6,
  ``S_g(σ; K) = {s_t | w_t ≥ α_K(σ) ∧ r̂_t ≥ mean_t r̂(σ)}`` with
  ``α_K(σ) = Quantile_{1-K%}({w_i})`` taken per segment. The other percentile groups of Table 2
  use the same per-segment quantiles ``q(p)`` (numpy's linear interpolation), mirrored so that
  ``bottom`` is the exact counterpart of ``top`` (``k = K / 100``, levels clipped to ``[0, 1]``):

  ============  ======================================  =============================
  group         attention criterion                     Table 2 row
  ============  ======================================  =============================
  top           ``w ≥ q(1 - k)``                        Top 10% (SPOT), eq. 6
  top_next      ``q(1 - 2k) ≤ w < q(1 - k)``            Top 10-20%
  bottom_next   ``q(k) < w ≤ q(2k)``                    Bottom 10-20%
  bottom        ``w ≤ q(k)``                            Bottom 10%
  ============  ======================================  =============================

  The reward criterion ``r̂_t ≥ mean_t r̂`` applies to the ``top`` group; the other groups use
  attention alone, as in the authors' code that produced Table 2 (``subgoal.filter_groups=all``
  applies it to every group).
  With ``T = 100`` and ``K = 10`` each group holds exactly 10 steps when the weights are
  distinct. Equal weights all pass the same threshold (a uniform ``w`` selects every step for
  ``top`` and ``bottom``). ``subgoal.last_step`` adds the last step of every preferred segment to
  the subgoals whatever the filters say (the authors' code appends index ``T - 1``).

  ``subgoal.selection=authors`` is the authors' selection (SGPbrl a5b03df
  ``extract_and_accumulate_subgoals``) instead: with ``s = sort(w)`` (ascending) and ``n(p) =
  int(T·p)``, the thresholds are ranks, not interpolated quantiles, and at most ``m`` steps pass,
  the first ``m`` in time (ties fall in time order):

  ============  ==========================================  ======================
  group         attention criterion                         at most ``m`` steps
  ============  ==========================================  ======================
  top           ``w ≥ s[n(1 - k)]`` (and the reward filter)  ``T - n(1 - k)``
  top_next      ``s[n(1 - 2k)] ≤ w < s[n(1 - k)]``           ``n(k)``
  bottom_next   ``s[n(k)] < w ≤ s[n(2k)]``                   ``n(k)``
  bottom        ``w ≤ s[n(k)]`` (``n(k) + 1`` steps pass)    ``n(k)``
  ============  ==========================================  ======================

  (``T = 100``, ``K = 10``: ``s[90]``, ``s[80]``, ``s[10]``, ``s[20]``; ``m = 10``.) Their list of
  subgoal indices has a fixed size ``m`` and is padded with index 0 when fewer steps pass, so a
  segment whose group selects fewer than ``m`` steps starts its first interval at step 0, and one
  that selects ``m`` (the rule for ``top_next``/``bottom_next``/``bottom`` with distinct weights)
  draws nothing before its first subgoal: :func:`subgoal_selection` returns that first step.
* :func:`make_triplets` builds the CVAE data of §4.1.3 ("s_t, a_t between g_{t-1} and g_t"):

  - ``next_subgoal`` (default): every step ``t`` of a preferred segment is paired with the
    *next* subgoal at or after ``t`` in the same segment, ``g_t = s_τ`` with
    ``τ = min{τ ≥ t | mask_τ}``. A subgoal step is its own target (``τ = t``).
  - ``interval`` (the authors' code): with subgoal steps ``g_1 < ... < g_n`` and ``g_0 = 0`` (the
    segment start), each non-empty interval ``[g_(i-1), g_i)`` contributes ``draws`` steps drawn
    uniformly (with replacement), each paired with ``s_(g_i)``; so a subgoal step maps to the
    *next* subgoal, and every interval weighs the same whatever its length. The authors draw one
    step per interval at every reward-model step (the CVAE trains online: ``cvae.schedule=online``,
    :mod:`spot.subgoal.online`); the offline CVAE trains on a fixed set, hence ``draws``. Their
    subgoal index list is padded with index 0 by ``jnp.where(..., size=K%·T)`` whenever fewer steps
    pass the filters (nearly always with the reward filter), which is why their first interval
    starts at step 0; the padding also yields empty intervals that their code turns into spurious
    triplets, which are not reproduced.

  In both modes steps after the last subgoal of a segment have no target and are dropped, and so
  are steps before the segment's first step (0, or the first subgoal under
  ``subgoal.selection=authors`` when the group selected all its ``m`` steps).

Everything here is host-side numpy: it runs once per reward model and its outputs have
data-dependent sizes.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from spot import SpotError
from spot.config import SubgoalConfig

GROUPS = ("top", "top_next", "bottom_next", "bottom")
FILTER_GROUPS = ("top", "all")
TIES = ("skip", "both")
WEIGHTS = ("column_mean", "diagonal")
FILTER_ON = ("r_hat", "z")
TRIPLETS = ("next_subgoal", "interval")
SELECTIONS = ("quantile", "authors")


class Segments(NamedTuple):
    """Per-step PT outputs for one side of ``Q`` labelled queries.

    Attributes:
      obs: ``[Q, T, obs_dim]`` states.
      act: ``[Q, T, act_dim]`` actions.
      reward: ``[Q, T]`` the per-step value the reward filter reads (``r̂_t``, or ``z_t`` with
        ``subgoal.filter_on=z``; :func:`step_scores`).
      weight: ``[Q, T]`` importance weight ``w_t`` (:func:`step_scores`).
    """

    obs: np.ndarray
    act: np.ndarray
    reward: np.ndarray
    weight: np.ndarray


class Triplets(NamedTuple):
    """CVAE training data ``(s_t, a_t, g_t)``: ``s [M, obs_dim]``, ``a [M, act_dim]``, ``g [M, obs_dim]``
    (``g [M, obs_dim + act_dim]``, the subgoal's state then its action, for ``shaping.state_action``)."""

    s: np.ndarray
    a: np.ndarray
    g: np.ndarray


def step_scores(
    r_hat: np.ndarray, attn: np.ndarray, weight: str = "column_mean", filter_on: str = "r_hat"
) -> tuple[np.ndarray, np.ndarray]:
    """Per-step importance weight and reward-filter value from PT's preference attention.

    Args:
      r_hat: ``[Q, T]`` PT per-step rewards.
      attn: ``[Q, T, T]`` preference attention, ``attn[q, t, j] = A_tj`` (rows sum to 1 over keys j).
      weight: ``column_mean`` (``w_j = mean_t A_tj``) or ``diagonal`` (``w_t = A_tt``).
      filter_on: ``r_hat`` (``r̂_t``) or ``z`` (``z_t = Σ_j A_tj r̂_j``).

    Returns:
      ``(w [Q, T], r [Q, T])`` float64.
    """
    if weight not in WEIGHTS:
        raise SpotError(f"subgoal weight {weight!r}; expected one of {WEIGHTS}")
    if filter_on not in FILTER_ON:
        raise SpotError(f"subgoal filter_on {filter_on!r}; expected one of {FILTER_ON}")
    r_hat = np.asarray(r_hat, dtype=np.float64)
    attn = np.asarray(attn, dtype=np.float64)
    if r_hat.ndim != 2 or attn.shape != r_hat.shape + r_hat.shape[-1:]:
        raise SpotError(f"rewards {r_hat.shape} and attention {attn.shape} must be [Q, T] and [Q, T, T]")
    w = attn.mean(axis=1) if weight == "column_mean" else np.diagonal(attn, axis1=1, axis2=2).copy()
    r = r_hat if filter_on == "r_hat" else np.einsum("qtj,qj->qt", attn, r_hat)
    return w, r


def segments(obs: np.ndarray, act: np.ndarray, r_hat: np.ndarray, attn: np.ndarray, cfg: SubgoalConfig) -> Segments:
    """One side of the queries as :class:`Segments`, scored by ``cfg.weight`` and ``cfg.filter_on``."""
    w, r = step_scores(r_hat, attn, cfg.weight, cfg.filter_on)
    return Segments(np.asarray(obs), np.asarray(act), r, w)


def preferred_segments(y: np.ndarray, ties: str = "skip") -> tuple[np.ndarray, np.ndarray]:
    """Which segment of each query is preferred.

    Args:
      y: ``[Q]`` labels in {0, 0.5, 1}; 1 means segment 2 is preferred, 0 segment 1, 0.5 a tie.
      ties: ``"skip"`` drops tied queries (neither segment is preferred; default), ``"both"``
        keeps both segments of a tie.

    Returns:
      ``(query [P], side [P])``: the query index and the side of each preferred segment
      (0 = segment 1, 1 = segment 2), ordered by query, segment 1 before segment 2.
    """
    if ties not in TIES:
        raise SpotError(f"ties={ties!r}; expected one of {TIES}")
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 1:
        raise SpotError(f"labels have shape {y.shape}; expected [Q]")
    is_tie = np.isclose(y, 0.5)
    bad = ~(np.isclose(y, 0.0) | np.isclose(y, 1.0) | is_tie)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SpotError(f"label {i} is {y[i]}; expected 0, 0.5 or 1")
    query = np.arange(y.size)
    side = np.isclose(y, 1.0).astype(np.int64)
    keep = ~is_tie
    if ties == "skip":
        return query[keep], side[keep]
    both_q = np.concatenate([query[keep], query[is_tie], query[is_tie]])
    both_s = np.concatenate([side[keep], np.zeros(is_tie.sum(), np.int64), np.ones(is_tie.sum(), np.int64)])
    order = np.lexsort((both_s, both_q))
    return both_q[order], both_s[order]


def take_preferred(seg_1: Segments, seg_2: Segments, y: np.ndarray, ties: str = "skip") -> Segments:
    """Stack the preferred segments of all queries: a :class:`Segments` with ``P`` rows."""
    query, side = preferred_segments(y, ties)
    pick = side.astype(bool)
    return Segments(
        *(np.where(_expand(pick, f1.ndim), f2[query], f1[query]) for f1, f2 in zip(seg_1, seg_2, strict=True))
    )


def _expand(pick: np.ndarray, ndim: int) -> np.ndarray:
    return pick.reshape(pick.shape + (1,) * (ndim - 1))


def subgoal_mask(
    w: np.ndarray,
    r: np.ndarray,
    top_k: float,
    group: str = "top",
    reward_filter: bool = True,
    filter_groups: str = "top",
    last_step: bool = False,
    selection: str = "quantile",
) -> np.ndarray:
    """Dual-criteria subgoal filter, eq. 5-6 (see the module docstring for the groups).

    Args:
      w: ``[Q, T]`` importance weights.
      r: ``[Q, T]`` PT per-step rewards.
      top_k: ``K`` in percent, e.g. 10.
      group: ``top`` | ``top_next`` | ``bottom_next`` | ``bottom``.
      reward_filter: also require ``r̂_t ≥ mean_t r̂`` of the segment (eq. 5).
      filter_groups: ``top``: the reward filter applies to the ``top`` group only, the other
        groups use attention alone (the authors' code, which produced Table 2's numbers);
        ``all``: to every group (eq. 5 read literally for each group).
      last_step: the last step of every segment is a subgoal whatever the filters say.
      selection: ``quantile`` (linear per-segment quantiles, every step that passes) or
        ``authors`` (rank thresholds, the first ``m`` steps in time; module docstring).

    Returns:
      ``[Q, T]`` bool, True at subgoal steps.
    """
    return subgoal_selection(w, r, top_k, group, reward_filter, filter_groups, last_step, selection)[0]


def subgoal_selection(
    w: np.ndarray,
    r: np.ndarray,
    top_k: float,
    group: str = "top",
    reward_filter: bool = True,
    filter_groups: str = "top",
    last_step: bool = False,
    selection: str = "quantile",
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`subgoal_mask` and each segment's first step ``start [Q]`` int: the step where its
    first interval (``interval`` triplets) or its first triplet (``next_subgoal``) may start. 0 for
    ``selection=quantile``; for ``authors`` 0 where the group selected fewer than its ``m`` steps
    (the authors' padding with index 0), else the first subgoal (``T`` when there is none)."""
    if group not in GROUPS:
        raise SpotError(f"subgoal group {group!r}; expected one of {GROUPS}")
    if filter_groups not in FILTER_GROUPS:
        raise SpotError(f"subgoal filter_groups {filter_groups!r}; expected one of {FILTER_GROUPS}")
    if selection not in SELECTIONS:
        raise SpotError(f"subgoal selection {selection!r}; expected one of {SELECTIONS}")
    w = np.asarray(w, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if w.ndim != 2 or w.shape != r.shape:
        raise SpotError(f"weights {w.shape} and rewards {r.shape} must both be [Q, T]")
    reward_ok = r >= r.mean(axis=1, keepdims=True)
    use_reward = reward_filter and (group == "top" or filter_groups == "all")
    if selection == "quantile":
        mask = _quantile_group(w, top_k, group)
        if use_reward:
            mask &= reward_ok
        start = np.zeros(w.shape[0], np.int64)
    else:
        passing, size = _rank_group(w, top_k, group)
        if use_reward:
            passing &= reward_ok
        mask = passing & (np.cumsum(passing, axis=1) <= size)  # the first `size` in time
        padded = passing.sum(axis=1) < size
    if last_step:
        mask[:, -1] = True
    if selection == "authors":
        first = np.where(mask.any(axis=1), mask.argmax(axis=1), w.shape[1])
        start = np.where(padded, 0, first).astype(np.int64)
    return mask, start


def _quantile_group(w: np.ndarray, top_k: float, group: str) -> np.ndarray:
    """The attention criterion of ``group`` with per-segment linear quantiles (module docstring)."""
    k = top_k / 100.0

    def q(level: float) -> np.ndarray:  # per-segment quantile, shape [Q, 1]
        return np.quantile(w, np.clip(level, 0.0, 1.0), axis=1, keepdims=True)

    if group == "top":
        return w >= q(1 - k)
    if group == "top_next":
        return (w >= q(1 - 2 * k)) & (w < q(1 - k))
    if group == "bottom_next":
        return (w > q(k)) & (w <= q(2 * k))
    return w <= q(k)


def rank_index(length: int, percent: float) -> int:
    """``int(T · percent / 100)``, the authors' rank of a threshold in the sorted weights (``percent
    = 90`` is their ``int(T · 90 / 100)``), clipped to ``[0, T - 1]``."""
    return min(max(int(length * percent / 100.0), 0), length - 1)


def rank_thresholds(top_k: float, group: str) -> tuple[float | None, float | None, str]:
    """The percents of the authors' lower and upper rank thresholds of ``group`` (None: none) and
    whether each bound is strict: ``top`` ``w ≥ s[100 - K]``; ``top_next`` ``s[100 - 2K] ≤ w <
    s[100 - K]``; ``bottom_next`` ``s[K] < w ≤ s[2K]``; ``bottom`` ``w ≤ s[K]`` (module docstring).
    The third item names the strict side: ``"upper"`` (``w <``), ``"lower"`` (``w >``) or ``""``."""
    k = top_k
    return {
        "top": (100.0 - k, None, ""),
        "top_next": (100.0 - 2 * k, 100.0 - k, "upper"),
        "bottom_next": (k, 2 * k, "lower"),
        "bottom": (None, k, ""),
    }[group]


def rank_size(length: int, top_k: float, group: str) -> int:
    """How many steps the authors' fixed-size index list holds: ``T - int(T (100 - K) / 100)`` for
    ``top``, ``int(T K / 100)`` for the other groups."""
    if group == "top":
        return length - int(length * (100.0 - top_k) / 100.0)
    return int(length * top_k / 100.0)


def _rank_group(w: np.ndarray, top_k: float, group: str) -> tuple[np.ndarray, int]:
    """The authors' attention criterion of ``group`` (thresholds at ranks of each segment's sorted
    weights) and the most steps it keeps (module docstring)."""
    t = w.shape[1]
    s = np.sort(w, axis=1)
    lo, hi, strict = rank_thresholds(top_k, group)
    ok = np.ones(w.shape, bool)
    if lo is not None:
        bound = s[:, rank_index(t, lo)][:, None]
        ok &= w > bound if strict == "lower" else w >= bound
    if hi is not None:
        bound = s[:, rank_index(t, hi)][:, None]
        ok &= w < bound if strict == "upper" else w <= bound
    return ok, rank_size(t, top_k, group)


def make_triplets(
    obs: np.ndarray,
    act: np.ndarray,
    mask: np.ndarray,
    mode: str = "next_subgoal",
    draws: int = 1,
    rng: np.random.Generator | None = None,
    goal_actions: bool = False,
    start: np.ndarray | None = None,
) -> tuple[Triplets, dict[str, float]]:
    """CVAE triplets ``(s_t, a_t, g_t)`` from the subgoal steps of each segment (§4.1.3).

    Args:
      obs: ``[P, T, obs_dim]`` states of the preferred segments.
      act: ``[P, T, act_dim]`` actions.
      mask: ``[P, T]`` subgoal steps (from :func:`subgoal_mask`).
      mode: ``next_subgoal``: every step paired with the first subgoal at or after it;
        ``interval``: ``draws`` uniform draws from each interval ``[g_(i-1), g_i)`` (``g_0 = 0``)
        paired with ``g_i`` (module docstring).
      draws: draws per interval (``interval`` only).
      rng: random generator of the draws (``interval`` only; default seed 0).
      goal_actions: ``g`` is the subgoal step's state and action (``[M, obs_dim + act_dim]``).
      start: ``[P]`` the first step of each segment that may be a triplet's (the first interval
        starts there; :func:`subgoal_selection`); default 0.

    Returns:
      ``(Triplets, info)``; ``info`` holds ``subgoal/num_segments``, ``subgoal/num_subgoals``,
      ``subgoal/num_triplets`` and ``subgoal/segments_without_subgoal``.
    """
    triplets, _, info = make_triplets_with_segments(obs, act, mask, mode, draws, rng, goal_actions, start)
    return triplets, info


def make_triplets_with_segments(
    obs: np.ndarray,
    act: np.ndarray,
    mask: np.ndarray,
    mode: str = "next_subgoal",
    draws: int = 1,
    rng: np.random.Generator | None = None,
    goal_actions: bool = False,
    start: np.ndarray | None = None,
) -> tuple[Triplets, np.ndarray, dict[str, float]]:
    """:func:`make_triplets` plus the segment (row of ``obs``) of every triplet, ``[M]`` int, so
    that a train/held-out split can keep each segment's triplets on one side."""
    if mode not in TRIPLETS:
        raise SpotError(f"subgoal triplets {mode!r}; expected one of {TRIPLETS}")
    if draws < 1:
        raise SpotError(f"subgoal interval_draws={draws}; expected >= 1")
    mask = np.asarray(mask, dtype=bool)
    p, t = mask.shape
    if obs.shape[:2] != (p, t) or act.shape[:2] != (p, t):
        raise SpotError(f"obs {obs.shape}, act {act.shape} and mask {mask.shape} must share [P, T]")
    start = np.zeros(p, np.int64) if start is None else np.asarray(start, np.int64)
    if mode == "next_subgoal":
        # next_idx[i, t] = first subgoal index >= t in row i, or T if there is none.
        idx = np.where(mask, np.arange(t)[None, :], t)
        next_idx = np.minimum.accumulate(idx[:, ::-1], axis=1)[:, ::-1]
        valid = (next_idx < t) & (np.arange(t)[None, :] >= start[:, None])
        rows = np.broadcast_to(np.arange(p)[:, None], (p, t))
        row, step, goal = rows[valid], np.nonzero(valid)[1], next_idx[valid]
    else:
        rng = np.random.default_rng(0) if rng is None else rng
        rows_l, steps_l, goals_l = [], [], []
        for i in range(p):
            lo = int(start[i])
            for g in np.flatnonzero(mask[i]):
                if g > lo:  # the interval [lo, g) is not empty
                    rows_l.append(np.full(draws, i))
                    steps_l.append(rng.integers(lo, g, size=draws))
                    goals_l.append(np.full(draws, g))
                lo = max(lo, int(g))
        empty = np.zeros(0, np.int64)
        row, step, goal = (np.concatenate(x) if x else empty for x in (rows_l, steps_l, goals_l))
    g = np.concatenate([obs[row, goal], act[row, goal]], axis=-1) if goal_actions else obs[row, goal]
    triplets = Triplets(s=obs[row, step], a=act[row, step], g=g)
    info = {
        "subgoal/num_segments": float(p),
        "subgoal/num_subgoals": float(mask.sum()),
        "subgoal/num_triplets": float(row.size),
        "subgoal/segments_without_subgoal": float((~mask.any(axis=1)).sum()),
    }
    return triplets, np.asarray(row, np.int64), info


def extract(
    seg_1: Segments,
    seg_2: Segments,
    y: np.ndarray,
    cfg: SubgoalConfig,
    ties: str = "skip",
    rng: np.random.Generator | None = None,
    goal_actions: bool = False,
) -> tuple[Triplets, np.ndarray, dict[str, float]]:
    """:func:`extract_with_segments` without the segment ids."""
    triplets, _, states, info = extract_with_segments(seg_1, seg_2, y, cfg, ties, rng, goal_actions)
    return triplets, states, info


def extract_with_segments(
    seg_1: Segments,
    seg_2: Segments,
    y: np.ndarray,
    cfg: SubgoalConfig,
    ties: str = "skip",
    rng: np.random.Generator | None = None,
    goal_actions: bool = False,
) -> tuple[Triplets, np.ndarray, np.ndarray, dict[str, float]]:
    """Preferred segments -> subgoal mask -> CVAE triplets, with counts for logging.

    ``rng`` draws the ``interval`` triplets (``subgoal.triplets``); unused otherwise.
    ``goal_actions``: the triplets' subgoals are states and actions (``shaping.state_action``).

    Returns:
      ``(triplets, segments [M], subgoals [N_g, obs_dim], info)``; ``segments`` is the preferred
      segment each triplet comes from (:func:`make_triplets_with_segments`), ``subgoals`` the
      extracted subgoal states (the "real" set of the precision/recall diagnostic).

    Raises:
      SpotError: if no triplet is left (every label a tie, or no step passes the filter).
    """
    pref = take_preferred(seg_1, seg_2, y, ties)
    mask, start = subgoal_selection(
        pref.weight,
        pref.reward,
        cfg.top_k,
        cfg.group,
        cfg.reward_filter,
        cfg.filter_groups,
        cfg.last_step,
        cfg.selection,
    )
    triplets, segments, info = make_triplets_with_segments(
        pref.obs, pref.act, mask, cfg.triplets, cfg.interval_draws, rng, goal_actions, start
    )
    if triplets.s.shape[0] == 0:
        raise SpotError(
            f"no subgoal triplets from {len(y)} queries ({pref.obs.shape[0]} preferred segments, "
            f"subgoal.top_k={cfg.top_k}, subgoal.group={cfg.group!r}); expected at least one "
            "non-tied label and a top_k large enough to select a step"
        )
    return triplets, segments, pref.obs[mask], info


def random_subgoals(
    triplets: Triplets, observations: np.ndarray, rng: np.random.Generator, actions: np.ndarray | None = None
) -> Triplets:
    """The control ``subgoal.source=random``: each triplet's subgoal replaced by a dataset state
    drawn uniformly at random (with replacement); ``s`` and ``a`` are kept. With ``actions`` the
    subgoal is that row's state and action (subgoals of ``shaping.state_action``)."""
    pick = rng.integers(0, observations.shape[0], size=triplets.g.shape[0])
    g = observations[pick] if actions is None else np.concatenate([observations[pick], actions[pick]], axis=-1)
    return Triplets(triplets.s, triplets.a, np.asarray(g, dtype=triplets.g.dtype))
