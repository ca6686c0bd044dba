"""In-memory offline datasets in the D4RL layout, and the ``qlearning_dataset`` view.

Two levels, as in D4RL:

* :class:`RawDataset` holds the arrays exactly as a D4RL hdf5 file stores them: one row per
  environment step, ``observations[i]``, ``actions[i]``, ``rewards[i]``, ``terminals[i]``,
  ``timeouts[i]`` and (optionally) ``next_observations[i]``. An episode ends at a row whose
  terminal or timeout flag is set.
* :class:`Dataset` is the ``d4rl.qlearning_dataset`` view of it (terminate_on_end=False): the raw
  rows ``0..N-2``, minus every row whose ``timeouts`` flag is set. The PT human label files index
  into exactly this view, so a segment ``[start, start + L)`` of the view lines up with them.

Extra per-step arrays travel in ``infos`` (D4RL's ``infos/`` group, e.g. ``infos/qpos``): a dict
of arrays with one row per raw row, indexed like the other arrays in the ``qlearning`` view. The
local robosuite recipe stores robosuite's staged dense reward there as ``infos/dense_reward``
(:data:`DENSE_REWARD_KEY`), which the scripted teacher can score segments with.

One deliberate difference: d4rl's ``qlearning_dataset`` always takes ``next_observations[i] =
observations[i + 1]``, which at a terminal row is the first state of the *next* episode. When the
file stores ``next_observations`` we use them (the true next state); without them we fall back to
``observations[i + 1]`` like d4rl. Indices, and therefore labels, are unaffected.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from spot import SpotError
from spot.batches import Transitions

RAW_KEYS = ("observations", "actions", "rewards", "terminals", "timeouts")
DENSE_REWARD_KEY = "dense_reward"  # infos key of a per-step dense reward (robosuite recipe)


def _check_finite(name: str, arr: np.ndarray, where: str) -> None:
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise SpotError(
            f"{where}: '{name}' contains NaN or inf (first at index {tuple(int(b) for b in bad)}); "
            "expected finite values"
        )


@dataclass(frozen=True, eq=False)
class RawDataset:
    """D4RL hdf5 layout, one row per environment step. Shapes: ``[N, obs_dim]``, ``[N, act_dim]``, ``[N]``;
    ``infos`` maps names to extra per-step arrays ``[N, ...]`` (the file's ``infos/`` group)."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminals: np.ndarray
    timeouts: np.ndarray
    next_observations: np.ndarray | None = None
    name: str = "unnamed"
    metadata: dict[str, Any] = field(default_factory=dict)
    infos: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_raw(self, where=self.name)

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    def qlearning(self) -> Dataset:
        """The ``d4rl.qlearning_dataset`` view (see module docstring)."""
        n = len(self)
        keep = np.flatnonzero(~self.timeouts[: n - 1].astype(bool))  # rows 0..N-2, timeouts dropped
        if keep.size == 0:
            raise SpotError(
                f"dataset '{self.name}': every one of its {n - 1} rows before the last is a timeout, so "
                "it has no transitions (the qlearning view drops timeout rows); expected steps with timeouts = 0"
            )
        if self.next_observations is not None:
            next_obs = self.next_observations[keep]
        else:
            next_obs = self.observations[keep + 1]
        # An episode ends after a terminal or a timeout; number the raw rows by episode.
        ends = (self.terminals.astype(bool) | self.timeouts.astype(bool)).astype(np.int64)
        episode_of_row = np.concatenate([[0], np.cumsum(ends)[:-1]])
        return Dataset(
            observations=self.observations[keep],
            actions=self.actions[keep],
            rewards=self.rewards[keep],
            next_observations=next_obs,
            terminals=self.terminals[keep].astype(bool),
            episode_ids=episode_of_row[keep],
            raw_index=keep,
            name=self.name,
            metadata=dict(self.metadata),
            infos={k: v[keep] for k, v in self.infos.items()},
        )


def validate_raw(raw: RawDataset, where: str) -> None:
    """Check shapes, dtypes and finiteness; raise :class:`SpotError` naming the key."""
    n = None
    for key in RAW_KEYS + ("next_observations",):
        arr = getattr(raw, key)
        if arr is None:
            continue
        if not isinstance(arr, np.ndarray):
            raise SpotError(f"{where}: '{key}' must be a numpy array, got {type(arr).__name__}")
        if n is None:
            n = arr.shape[0]
        if arr.shape[0] != n:
            raise SpotError(
                f"{where}: '{key}' has {arr.shape[0]} rows but 'observations' has {n}; "
                "all keys must have one row per step"
            )
    for key, rank in (("observations", 2), ("actions", 2), ("rewards", 1), ("terminals", 1), ("timeouts", 1)):
        if getattr(raw, key).ndim != rank:
            raise SpotError(f"{where}: '{key}' has shape {getattr(raw, key).shape}; expected rank {rank}")
    if raw.next_observations is not None and raw.next_observations.shape != raw.observations.shape:
        raise SpotError(
            f"{where}: 'next_observations' has shape {raw.next_observations.shape}; expected "
            f"{raw.observations.shape} like 'observations'"
        )
    if n is not None and n < 2:
        raise SpotError(f"{where}: dataset has {n} rows; expected at least 2")
    for key, arr in raw.infos.items():
        if not isinstance(arr, np.ndarray) or arr.ndim < 1 or arr.shape[0] != n:
            shape = arr.shape if isinstance(arr, np.ndarray) else type(arr).__name__
            raise SpotError(f"{where}: 'infos/{key}' has shape {shape}; expected {n} rows like 'observations'")
    for key in ("observations", "actions", "rewards", "next_observations"):
        arr = getattr(raw, key)
        if arr is not None:
            _check_finite(key, arr, where)


@dataclass(frozen=True, eq=False)
class Dataset:
    """The ``qlearning_dataset`` view: one row per transition.

    Attributes:
      observations: ``[N, obs_dim]`` float32.
      actions: ``[N, act_dim]`` float32.
      rewards: ``[N]`` float32, the dataset's true reward.
      next_observations: ``[N, obs_dim]``.
      terminals: ``[N]`` bool, true environment termination (not timeouts).
      episode_ids: ``[N]`` int, which episode of the raw data each transition belongs to.
      raw_index: ``[N]`` int, the raw row of each transition.
      infos: extra per-step arrays ``[N, ...]`` (e.g. ``dense_reward``), rows as above.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminals: np.ndarray
    episode_ids: np.ndarray
    raw_index: np.ndarray
    name: str = "unnamed"
    metadata: dict[str, Any] = field(default_factory=dict)
    infos: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    @property
    def obs_dim(self) -> int:
        return int(self.observations.shape[1])

    @property
    def act_dim(self) -> int:
        return int(self.actions.shape[1])

    def replace(self, **changes: Any) -> Dataset:
        return dataclasses.replace(self, **changes)

    def fingerprint(self) -> str:
        """SHA-256 (hex) of every array of the view: observations, actions, rewards, next
        observations, terminals, episode ids (the episode ends, terminals and timeouts alike),
        raw row indices and each ``infos`` array, with their names, dtypes and shapes. What
        identifies the data in stage-cache keys; the name and metadata are not part of it."""
        h = hashlib.sha256()
        arrays = [
            (f.name, getattr(self, f.name))
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        ]
        arrays += [(f"infos/{k}", np.asarray(v)) for k, v in sorted(self.infos.items())]
        for name, arr in arrays:
            h.update(f"|{name}|{arr.dtype.str}|{arr.shape}|".encode())
            h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()

    def transitions(self, rewards: np.ndarray | None = None) -> Transitions:
        """The transition view the policy trains on (:class:`spot.batches.Transitions`, numpy
        float32): ``obs``, ``act``, ``rew`` (``rewards`` ``[N]`` if given, e.g. relabelled; else the
        dataset's reward), ``next_obs`` and ``mask = 1 - terminal``."""
        rew = self.rewards if rewards is None else np.asarray(rewards)
        if rew.shape != (len(self),):
            raise SpotError(f"rewards have shape {rew.shape}; expected ({len(self)},) like dataset '{self.name}'")
        return Transitions(
            obs=np.asarray(self.observations, np.float32),
            act=np.asarray(self.actions, np.float32),
            rew=np.asarray(rew, np.float32),
            next_obs=np.asarray(self.next_observations, np.float32),
            mask=1.0 - self.terminals.astype(np.float32),
        )

    # ----------------------------------------------------------------- episodes
    def episode_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(starts, ends)`` of each episode in this view; ``ends`` is exclusive."""
        change = np.flatnonzero(np.diff(self.episode_ids) != 0) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [len(self)]])
        return starts, ends

    def episode_returns(self) -> np.ndarray:
        """Sum of true reward per episode of this view, shape ``[num_episodes]``."""
        starts, _ = self.episode_bounds()
        return np.add.reduceat(self.rewards.astype(np.float64), starts)

    def episode_lengths(self) -> np.ndarray:
        starts, ends = self.episode_bounds()
        return ends - starts

    # ----------------------------------------------------------------- segments
    def segment_index(
        self, starts: np.ndarray, length: int, *, allow_cross_episode: bool = True, what: str = "segment"
    ) -> np.ndarray:
        """Row indices ``[len(starts), length]`` of segments ``[start, start + length)``.

        Raises :class:`SpotError` if a segment runs past the end of the dataset, or crosses an
        episode end when ``allow_cross_episode`` is False (the PT label files were drawn without
        that check, so reading them allows it by default).
        """
        starts = np.asarray(starts, dtype=np.int64)
        if starts.ndim != 1:
            raise SpotError(f"{what} starts must be a 1-D array, got shape {starts.shape}")
        last = len(self) - length  # the last start whose segment fits; compared without adding to starts,
        # which would overflow int64 for a start near 2**63 and wrap to a "valid" negative sum
        if starts.size and (starts.min() < 0 or starts.max() > last):
            bad = int(np.argmax((starts < 0) | (starts > last)))
            raise SpotError(
                f"{what} {bad} starts at index {int(starts[bad])} with length {length}, past the end "
                f"of dataset '{self.name}' ({len(self)} transitions); expected 0 <= start <= "
                f"{len(self) - length}"
            )
        idx = starts[:, None] + np.arange(length)[None, :]
        if not allow_cross_episode and starts.size:
            ep = self.episode_ids[idx]
            crossing = np.flatnonzero((ep != ep[:, :1]).any(axis=1))
            if crossing.size:
                b = int(crossing[0])
                raise SpotError(
                    f"{what} {b} (start {int(starts[b])}, length {length}) crosses an episode end in "
                    f"dataset '{self.name}'; expected segments inside one episode"
                )
        return idx

    def summary(self) -> dict[str, Any]:
        rets = self.episode_returns()
        lens = self.episode_lengths()
        return {
            "name": self.name,
            "transitions": len(self),
            "episodes": int(rets.size),
            "obs_dim": self.obs_dim,
            "act_dim": self.act_dim,
            "terminals": int(self.terminals.sum()),
            "return_mean": float(rets.mean()),
            "return_std": float(rets.std()),
            "return_min": float(rets.min()),
            "return_max": float(rets.max()),
            "episode_length_mean": float(lens.mean()),
            "reward_mean": float(self.rewards.mean()),
        }


def raw_from_episodes(
    episodes: list[dict[str, np.ndarray]], name: str, metadata: dict[str, Any] | None = None
) -> RawDataset:
    """Stack episodes into the raw D4RL layout.

    Each episode is a dict with ``observations [T, o]``, ``actions [T, a]``, ``rewards [T]``,
    ``next_observations [T, o]``, ``terminals [T]`` and ``timeouts [T]`` (a truncated episode has
    ``timeouts[-1] = True``; a terminated one ``terminals[-1] = True``), and optionally ``infos``,
    a dict of extra per-step arrays ``[T, ...]`` with the same keys in every episode. This is the
    writer side used by the local recipes, so that their files read back through the same path as
    D4RL's.
    """
    if not episodes:
        raise SpotError(f"dataset '{name}': no episodes to write")
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in RAW_KEYS + ("next_observations",)}
    info_keys = sorted(episodes[0].get("infos", {}))
    for i, ep in enumerate(episodes):
        if sorted(ep.get("infos", {})) != info_keys:
            raise SpotError(
                f"dataset '{name}': episode {i} has infos {sorted(ep.get('infos', {}))}; expected "
                f"{info_keys} like episode 0"
            )
    infos = {k: np.concatenate([ep["infos"][k] for ep in episodes]) for k in info_keys}
    return RawDataset(
        observations=cat["observations"].astype(np.float32),
        actions=cat["actions"].astype(np.float32),
        rewards=cat["rewards"].astype(np.float32),
        terminals=cat["terminals"].astype(bool),
        timeouts=cat["timeouts"].astype(bool),
        next_observations=cat["next_observations"].astype(np.float32),
        name=name,
        metadata=dict(metadata or {}),
        infos=infos,
    )
