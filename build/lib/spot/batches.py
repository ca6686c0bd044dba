"""Typed array containers shared by the data layer and the learning core.

The learning modules (``spot.reward``, ``spot.subgoal``, ``spot.policy``) take these plain arrays
and never import ``spot.data``; ``spot.data`` builds them from a dataset. Keeping the types here,
below both, lets the layers point down (docs/design.md, "Layers").
"""

from __future__ import annotations

from typing import Any, NamedTuple


class Transitions(NamedTuple):
    """An offline dataset, one row per transition (float32; on device once built for training).

    Attributes:
      obs: ``[N, obs_dim]``.
      act: ``[N, act_dim]``.
      rew: ``[N]``.
      next_obs: ``[N, obs_dim]``.
      mask: ``[N]``, ``1 - terminal`` (0 stops bootstrapping).
    """

    obs: Any
    act: Any
    rew: Any
    next_obs: Any
    mask: Any
