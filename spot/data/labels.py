"""Preference queries: pairs of segments of the ``qlearning`` view and a label y.

A query is two segment starts into a :class:`~spot.data.dataset.Dataset` and a label
``y in {0, 0.5, 1}`` with **1 = segment 2 preferred** (y of the Bradley-Terry loss in the PT
paper, Kim et al., 2023, arXiv:2303.00957, eq. 1), 0.5 = equally preferred.

Sources:

* :func:`scripted_teacher`: compares segment returns of the true reward, S_i = sum_t r_t or
  sum_k gamma^k r_k, y = 1[S_1 < S_2] (PT repo : JaxPref/reward_transform.py, label_type 0; IPL's
  discounted comparison, jhejna/inverse-preference-learning : scripts/create_comparison_dataset.py),
  with an optional tie threshold (Uni-RLHF's epsilon; 0 = PT's label_type 1) and mistake rate
  (B-Pref's epsilon_mistake). ``score="dense"`` scores with the dataset's per-step dense reward
  (``infos/dense_reward``, robosuite's staged reward in the local robosuite recipe) instead of its
  reward: robosuite's sparse success reward is 1 only at the success step, so almost every pair
  of segments of successful demonstrations would tie.
* :func:`read_pt_labels`: the PT repo's human label files (``human_label/<dataset>/``), decoded
  with a restricted unpickler (they are pickles).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy._core.multiarray import _reconstruct, scalar

from spot import SpotError
from spot.data.dataset import DENSE_REWARD_KEY, Dataset

TEACHERS = ("sum", "discounted")
SCORES = ("reward", "dense")  # what the scripted teacher sums: ds.rewards or ds.infos["dense_reward"]
PT_DEFAULT_SEGMENT_LENGTH = 100  # D4RL label files carry no _q{L} suffix (PT README: query_len 100)


@dataclass(frozen=True, eq=False)
class Preferences:
    """Preference queries. Shapes ``[Q]``.

    Attributes:
      starts_1: int64 start rows of segment 1 in the ``qlearning`` view.
      starts_2: int64 start rows of segment 2.
      labels: float32 y in {0, 0.5, 1}; 1 = segment 2 preferred, 0.5 = equal.
      segment_length: T, rows per segment.
      source: "script", "human" or the label file path.
    """

    starts_1: np.ndarray
    starts_2: np.ndarray
    labels: np.ndarray
    segment_length: int
    source: str

    def __post_init__(self) -> None:
        arrays = {k: np.asarray(getattr(self, k)) for k in ("starts_1", "starts_2", "labels")}
        q = arrays["labels"].shape
        for key, arr in arrays.items():
            if arr.ndim != 1 or arr.shape != q:
                raise SpotError(f"preferences '{self.source}': '{key}' has shape {arr.shape}; expected {q}")
        for key in ("starts_1", "starts_2"):
            if arrays[key].size and arrays[key].dtype.kind not in "iu":
                raise SpotError(
                    f"preferences '{self.source}': '{key}' has dtype {arrays[key].dtype}; expected integers"
                )
            if arrays[key].size and int(arrays[key].max()) > np.iinfo(np.int64).max:  # exact: Python ints
                raise SpotError(
                    f"preferences '{self.source}': '{key}' has start index {int(arrays[key].max())}; expected "
                    f"at most {np.iinfo(np.int64).max}"
                )
        if not np.isin(arrays["labels"], (0.0, 0.5, 1.0)).all():
            raise SpotError(
                f"preferences '{self.source}': labels {np.unique(arrays['labels'])}; expected values in {{0, 0.5, 1}}"
            )
        if self.segment_length < 1:
            raise SpotError(f"preferences '{self.source}': segment_length {self.segment_length}; expected >= 1")
        object.__setattr__(self, "starts_1", arrays["starts_1"].astype(np.int64))
        object.__setattr__(self, "starts_2", arrays["starts_2"].astype(np.int64))
        object.__setattr__(self, "labels", arrays["labels"].astype(np.float32))
        object.__setattr__(self, "segment_length", int(self.segment_length))

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def subset(self, idx: np.ndarray) -> Preferences:
        """The queries ``idx`` (indices or a boolean mask), same length and source."""
        return dataclasses.replace(
            self, starts_1=self.starts_1[idx], starts_2=self.starts_2[idx], labels=self.labels[idx]
        )

    def save_npz(self, path: str | Path) -> None:
        """Write to ``path`` (atomically: temporary file, then ``os.replace``)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        try:
            with open(tmp, "wb") as fh:
                np.savez(
                    fh,
                    starts_1=self.starts_1,
                    starts_2=self.starts_2,
                    labels=self.labels,
                    segment_length=np.int64(self.segment_length),
                    source=np.str_(self.source),
                )
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    @classmethod
    def load_npz(cls, path: str | Path) -> Preferences:
        """Read a file written by :meth:`save_npz`."""
        path = Path(path)
        if not path.is_file():
            raise SpotError(f"preference file '{path}' does not exist")
        try:
            z = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise SpotError(
                f"preference file '{path}' is not a readable npz file ({err or type(err).__name__})"
            ) from None
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise SpotError(f"preference file '{path}' holds a single array; expected an npz archive")
        with z:
            fields = {}
            for k in z.files:
                try:
                    fields[k] = z[k]
                except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:  # object arrays, damage
                    raise SpotError(
                        f"preference file '{path}': array '{k}' cannot be read without pickles ({err}); "
                        "expected numeric arrays as written by `spot labels make`"
                    ) from None
        keys = ("starts_1", "starts_2", "labels", "segment_length", "source")
        missing = [k for k in keys if k not in fields]
        if missing:
            raise SpotError(f"preference file '{path}': missing keys {missing}; found {sorted(fields)}")
        length, source = fields["segment_length"], fields["source"]
        if length.shape != () or length.dtype.kind not in "iu":
            raise SpotError(
                f"preference file '{path}': 'segment_length' is an array of shape {length.shape} and dtype "
                f"{length.dtype}; expected one integer"
            )
        if source.shape != () or source.dtype.kind not in "U":
            raise SpotError(
                f"preference file '{path}': 'source' has shape {source.shape} and dtype {source.dtype}; "
                "expected one string"
            )
        try:
            return cls(fields["starts_1"], fields["starts_2"], fields["labels"], int(length), str(source))
        except SpotError as err:
            raise SpotError(f"preference file '{path}': {err}") from None


# --------------------------------------------------------------------------- scripted teacher
def _sample_starts(
    ds: Dataset, num: int, length: int, allow_cross_episode: bool, rng: np.random.Generator
) -> np.ndarray:
    """``num`` segment starts drawn uniformly from every start whose segment fits.

    Every valid start is equally likely (PT's sampler instead picks a trajectory first, which
    favours starts in short trajectories).
    """
    if allow_cross_episode:
        if len(ds) < length:
            raise SpotError(
                f"dataset '{ds.name}' has {len(ds)} transitions; expected at least segment_length = {length}"
            )
        return rng.integers(0, len(ds) - length + 1, size=num)
    starts, ends = ds.episode_bounds()
    counts = np.maximum(ends - starts - length + 1, 0)  # valid starts per episode
    if counts.sum() == 0:
        raise SpotError(
            f"dataset '{ds.name}': no episode has at least {length} transitions (longest "
            f"{int((ends - starts).max())} of {starts.size} episodes); use a shorter segment_length "
            "or allow_cross_episode"
        )
    draw = rng.integers(0, counts.sum(), size=num)  # position among all valid starts
    cum = np.cumsum(counts)
    episode = np.searchsorted(cum, draw, side="right")
    return starts[episode] + draw - (cum[episode] - counts[episode])


def segment_scores(rewards: np.ndarray, teacher: str, discount: float) -> np.ndarray:
    """S = sum_t r_t (``sum``) or sum_k discount^k r_k (``discounted``) of ``rewards [Q, T]``."""
    weights = np.ones(rewards.shape[1]) if teacher == "sum" else discount ** np.arange(rewards.shape[1])
    return rewards.astype(np.float64) @ weights


def score_rewards(ds: Dataset, score: str) -> np.ndarray:
    """The per-step rewards ``[N]`` the scripted teacher sums: ``ds.rewards`` (``score="reward"``)
    or ``ds.infos["dense_reward"]`` (``score="dense"``); :class:`SpotError` if the latter is missing."""
    if score not in SCORES:
        raise SpotError(f"unknown teacher score '{score}'; expected one of {', '.join(SCORES)}")
    if score == "reward":
        return ds.rewards
    if DENSE_REWARD_KEY not in ds.infos:
        raise SpotError(
            f"labels.score=dense: dataset '{ds.name}' has no dense reward 'infos/{DENSE_REWARD_KEY}' "
            f"(infos: {sorted(ds.infos) or 'none'}); the local robosuite recipe records it (a build "
            "from before it did is rebuilt on load), other datasets need labels.score=reward"
        )
    dense = np.asarray(ds.infos[DENSE_REWARD_KEY])
    if dense.shape != ds.rewards.shape or not np.all(np.isfinite(dense)):
        raise SpotError(
            f"dataset '{ds.name}': 'infos/{DENSE_REWARD_KEY}' has shape {dense.shape} (finite: "
            f"{bool(np.all(np.isfinite(dense)))}); expected finite values of shape {ds.rewards.shape}"
        )
    return dense


def scripted_teacher(
    ds: Dataset,
    num_queries: int,
    segment_length: int,
    *,
    teacher: str = "sum",
    discount: float = 0.99,
    tie_threshold: float = -1.0,
    mistake_rate: float = 0.0,
    allow_cross_episode: bool = False,
    seed: int = 0,
    score: str = "reward",
) -> Preferences:
    """Label random segment pairs by comparing their true-reward scores.

    Args:
      ds: the dataset (its ``rewards`` are the true reward).
      num_queries: Q, pairs to draw.
      segment_length: T, rows per segment.
      teacher: ``sum`` (PT, undiscounted) or ``discounted`` (IPL, gamma = ``discount``).
      discount: gamma of the discounted teacher.
      tie_threshold: |S_1 - S_2| <= threshold gives y = 0.5; negative = no ties (a tie then gives
        y = 0, segment 1, as PT's label_type 0 does).
      mistake_rate: probability of flipping each non-tie label.
      allow_cross_episode: allow segments to cross episode ends; otherwise they lie inside one
        episode and episodes shorter than T are skipped.
      seed: seed of the ``numpy`` Generator (starts 1, starts 2, then mistakes).
      score: ``reward`` sums ``ds.rewards``; ``dense`` sums the dataset's dense reward
        ``ds.infos["dense_reward"]`` (:func:`score_rewards`).

    Returns:
      ``Preferences`` with ``source="script"``.
    """
    if num_queries < 1 or segment_length < 1:
        raise SpotError(f"num_queries {num_queries} and segment_length {segment_length}; expected both >= 1")
    if teacher not in TEACHERS:
        raise SpotError(f"unknown teacher '{teacher}'; expected one of {', '.join(TEACHERS)}")
    if not 0.0 <= discount <= 1.0 or not 0.0 <= mistake_rate <= 1.0:
        raise SpotError(f"discount {discount} and mistake_rate {mistake_rate}; expected both in [0, 1]")
    rewards = score_rewards(ds, score)
    rng = np.random.default_rng(seed)
    starts_1 = _sample_starts(ds, num_queries, segment_length, allow_cross_episode, rng)
    starts_2 = _sample_starts(ds, num_queries, segment_length, allow_cross_episode, rng)
    window = np.arange(segment_length)
    s1 = segment_scores(rewards[starts_1[:, None] + window], teacher, discount)
    s2 = segment_scores(rewards[starts_2[:, None] + window], teacher, discount)
    labels = (s1 < s2).astype(np.float32)
    flip = rng.random(num_queries) < mistake_rate
    labels = np.where(flip, 1.0 - labels, labels)
    if tie_threshold >= 0:
        labels[np.abs(s1 - s2) <= tie_threshold] = 0.5
    return Preferences(starts_1, starts_2, labels, segment_length, "script")


# --------------------------------------------------------------------------- PT human labels
# Globals a pickled numpy array, dtype or numpy scalar refers to (numpy 1.x wrote numpy.core).
_SAFE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy.core.multiarray", "scalar"): scalar,
    ("numpy._core.multiarray", "scalar"): scalar,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class _NumpyUnpickler(pickle.Unpickler):
    """Admits numpy arrays, dtypes, numpy scalars and plain containers; refuses every other global."""

    def __init__(self, fh, path: Path) -> None:
        super().__init__(fh)
        self.path = path

    def find_class(self, module: str, name: str) -> object:
        if (module, name) in _SAFE_GLOBALS:
            return _SAFE_GLOBALS[(module, name)]
        raise SpotError(
            f"label file '{self.path}': refused to unpickle global '{module}.{name}'; expected only "
            "numpy arrays, numpy scalars and lists"
        )


def _unpickle_ints(path: Path) -> np.ndarray:
    """A pickled list or numpy array of integers, as a 1-D int64 array."""
    if not path.is_file():
        raise SpotError(f"label file '{path}' does not exist")
    try:
        with open(path, "rb") as fh:
            value = _NumpyUnpickler(fh, path).load()
    except SpotError:
        raise
    except Exception as err:  # a corrupt pickle can raise almost anything
        raise SpotError(f"label file '{path}' is not a readable pickle ({err!r})") from None
    if isinstance(value, np.ndarray):
        integers = value.dtype.kind in "iu" and value.ndim == 1
    elif isinstance(value, list):
        integers = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value)
    else:
        raise SpotError(f"label file '{path}' holds a {type(value).__name__}; expected a list or numpy array")
    if not integers:
        raise SpotError(f"label file '{path}' holds other values; expected a 1-D sequence of integers")
    big = max((int(v) for v in value), default=0)  # exact (Python ints): a uint64 or huge int does not wrap
    if big > np.iinfo(np.int64).max:
        raise SpotError(f"label file '{path}' holds the integer {big}; expected at most {np.iinfo(np.int64).max}")
    return np.asarray(value, dtype=np.int64)


def _find(folder: Path, pattern: str) -> tuple[Path, re.Match]:
    """The one file in ``folder`` whose name matches ``pattern``, and the match."""
    names = sorted(p.name for p in folder.iterdir())
    found = [(name, m) for name in names if (m := re.fullmatch(pattern, name))]
    if len(found) != 1:
        raise SpotError(
            f"label folder '{folder}': {len(found)} files match '{pattern}'; expected exactly one (files: {names})"
        )
    return folder / found[0][0], found[0][1]


def pt_label_name(dataset_name: str) -> str | None:
    """The PT repo's ``human_label/`` folder name for a dataset name, or None where PT has none.

    D4RL's v2 names (``hopper-medium-replay-v2``, or D4RL's file stem ``hopper_medium_replay-v2``)
    -> ``hopper-medium-replay-v2``; robomimic ``lift-ph`` / ``can-mh`` -> ``Lift_ph`` / ``Can_mh``.
    A locomotion name without ``-v2`` names spot's locally built dataset, which PT's indices do not
    point into: None. Which datasets PT labelled is up to the folder's presence
    (:func:`pt_label_folder`).
    """
    from spot.data.registry import D4RL_FILE_STEMS, ROBOMIMIC_ENV_NAMES, ROBOMIMIC_KINDS

    name = str(dataset_name).strip()
    name = D4RL_FILE_STEMS.get(name, name)
    task, _, kind = name.partition("-")
    if task in ROBOMIMIC_ENV_NAMES and kind in ROBOMIMIC_KINDS:
        return f"{task.capitalize()}_{kind}"
    if name in D4RL_FILE_STEMS.values():
        return name
    return None


def pt_label_folder(dataset_name: str, root: str | Path) -> Path | None:
    """The PT human label folder of ``dataset_name`` under ``root`` (one that holds
    ``label_human``), or None (see :func:`pt_label_name`)."""
    name = pt_label_name(dataset_name)
    if name is None or not (Path(root) / name / "label_human").is_file():
        return None
    return Path(root) / name


def read_pt_labels(folder: str | Path, num_queries: int | None = None) -> Preferences:
    """Read a PT human label folder (``indices_num{N}[_q{L}]``, ``indices_2_num{N}[_q{L}]``,
    ``label_human``).

    Labels 0 / 1 / -1 (segment 1 / segment 2 / equal) become y = 0 / 1 / 0.5. Only the first
    ``len(label_human)`` index entries are labelled (medium-expert stores 500 indices and 100
    labels). As PT's ``query_range``, ``num_queries`` keeps the *last* ``num_queries`` labels.

    Args:
      folder: the dataset's label folder.
      num_queries: how many queries to keep; default all labelled ones.

    Returns:
      ``Preferences`` with T = L from the ``_q{L}`` suffix (100 without one), source = folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise SpotError(f"label folder '{folder}' does not exist")
    from spot.data.fetch import verify_fetched

    verify_fetched(folder)  # files from `spot data fetch`: recheck their size and sha256
    path_1, m_1 = _find(folder, r"indices_num\d+(?:_q(\d+))?")
    path_2, m_2 = _find(folder, r"indices_2_num\d+(?:_q(\d+))?")
    path_y, _ = _find(folder, "label_human")
    if m_1.group(1) != m_2.group(1):
        raise SpotError(
            f"label folder '{folder}': '{path_1.name}' and '{path_2.name}' disagree on the segment "
            "length suffix _q{L}"
        )
    starts_1, starts_2, raw_labels = (_unpickle_ints(p) for p in (path_1, path_2, path_y))
    if starts_1.size != starts_2.size:
        raise SpotError(f"label file '{path_2}' has {starts_2.size} entries but '{path_1}' has {starts_1.size}")
    if raw_labels.size > starts_1.size:
        raise SpotError(
            f"label file '{path_y}' has {raw_labels.size} labels but '{path_1}' only {starts_1.size} index entries"
        )
    if not np.isin(raw_labels, (0, 1, -1)).all():
        raise SpotError(f"label file '{path_y}' has values {sorted(set(raw_labels.tolist()))}; expected 0, 1, -1")
    for path, starts in ((path_1, starts_1), (path_2, starts_2)):
        if (starts < 0).any():
            raise SpotError(f"label file '{path}' has negative start indices")
    n = raw_labels.size
    num = n if num_queries is None else num_queries
    if not 1 <= num <= n:
        raise SpotError(f"label folder '{folder}': num_queries {num}; expected 1..{n} (labels in the file)")
    query_range = np.arange(n - num, n)
    labels = np.where(raw_labels == -1, 0.5, raw_labels).astype(np.float32)
    return Preferences(
        starts_1[query_range],
        starts_2[query_range],
        labels[query_range],
        int(m_1.group(1) or PT_DEFAULT_SEGMENT_LENGTH),
        str(folder),
    )


# --------------------------------------------------------------------------- use with a dataset
def check_against(prefs: Preferences, ds: Dataset, allow_cross_episode: bool = True) -> None:
    """Raise :class:`SpotError` unless every segment of ``prefs`` fits in ``ds``.

    The error names the query index, its start and the dataset length. PT's human segments may
    cross episode ends (its sampler did not check), hence ``allow_cross_episode=True``.
    """
    for which, starts in (("1", prefs.starts_1), ("2", prefs.starts_2)):
        try:
            ds.segment_index(
                starts, prefs.segment_length, allow_cross_episode=allow_cross_episode, what=f"segment {which} of query"
            )
        except SpotError as err:
            raise SpotError(f"labels '{prefs.source}': {err}") from None


def segment_batch(ds: Dataset, prefs: Preferences) -> dict[str, np.ndarray]:
    """The segments' arrays, what reward models train on.

    Returns:
      ``obs_1, obs_2 [Q, T, obs_dim]``, ``act_1, act_2 [Q, T, act_dim]``, ``rew_1, rew_2 [Q, T]``
      (true reward), ``timesteps_1, timesteps_2 [Q, T]`` int32 = 1..T (PT feeds relative
      timesteps) and ``label [Q]``.
    """
    check_against(prefs, ds)
    q, t = len(prefs), prefs.segment_length
    timesteps = np.broadcast_to(np.arange(1, t + 1, dtype=np.int32), (q, t)).copy()
    batch = {"label": prefs.labels.copy()}
    for which, starts in (("1", prefs.starts_1), ("2", prefs.starts_2)):
        idx = starts[:, None] + np.arange(t)  # [Q, T]
        batch[f"obs_{which}"] = ds.observations[idx]
        batch[f"act_{which}"] = ds.actions[idx]
        batch[f"rew_{which}"] = ds.rewards[idx]
        batch[f"timesteps_{which}"] = timesteps.copy()
    return batch


def split_eval(prefs: Preferences, fraction: float, seed: int) -> tuple[Preferences, Preferences]:
    """A random disjoint (train, eval) split, ``round(fraction * Q)`` eval queries (at least one
    when ``fraction > 0``).

    PT's own reward-model eval set is the last 10 % of the training queries, which overlaps the
    training set (PT repo : JaxPref/new_preference_reward_main.py); we hold the eval queries out
    so that eval accuracy measures generalisation.
    """
    if not 0.0 <= fraction < 1.0:
        raise SpotError(f"eval fraction {fraction}; expected 0 <= fraction < 1")
    n_eval = int(round(fraction * len(prefs)))
    if fraction > 0:
        n_eval = max(n_eval, 1)
    if n_eval >= len(prefs):
        raise SpotError(f"eval fraction {fraction} of {len(prefs)} queries leaves none for training")
    perm = np.random.default_rng(seed).permutation(len(prefs))
    return prefs.subset(np.sort(perm[n_eval:])), prefs.subset(np.sort(perm[:n_eval]))
