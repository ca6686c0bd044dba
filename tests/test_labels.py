"""Preference queries: scripted teacher (hand-computed), PT human label files (the real ones),
restricted unpickling, segment batches and the eval split."""

import collections
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from spot import SpotError
from spot.data import labels
from spot.data.dataset import RawDataset
from spot.data.labels import Preferences

# The real PT human-label files (MIT), copied unchanged into tests/data (see PROVENANCE.md there).
PT_LABELS = Path(os.environ.get("SPOT_PT_LABELS", Path(__file__).parent / "data" / "pt-human-labels"))


def _dataset(rewards, ends=(), obs_dim=2, name="hand"):
    """The qlearning view of raw rows with these rewards; ``ends`` are terminal rows. One extra
    raw row is appended (the view drops the last row), so the view has exactly ``rewards``."""
    n = len(rewards) + 1
    terminals = np.zeros(n, bool)
    terminals[list(ends)] = True
    obs = np.repeat(np.arange(n, dtype=np.float32)[:, None], obs_dim, axis=1)
    return RawDataset(
        observations=obs,
        actions=-obs[:, :1],
        rewards=np.append(rewards, 0).astype(np.float32),
        terminals=terminals,
        timeouts=np.zeros(n, bool),
        name=name,
    ).qlearning()


def _zeros(n_raw, obs_dim=11, name="synthetic"):
    return RawDataset(
        observations=np.zeros((n_raw, obs_dim), np.float32),
        actions=np.zeros((n_raw, 3), np.float32),
        rewards=np.zeros(n_raw, np.float32),
        terminals=np.zeros(n_raw, bool),
        timeouts=np.zeros(n_raw, bool),
        name=name,
    ).qlearning()


def _scores(ds, starts, length, gamma=1.0):
    return np.array([sum(gamma**k * float(ds.rewards[s + k]) for k in range(length)) for s in starts])


# --------------------------------------------------------------------------- scripted teacher
def test_segment_scores_by_hand():
    r = np.array([[1.0, 2.0, 3.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(labels.segment_scores(r, "sum", 0.5), [6.0, 3.0])
    np.testing.assert_allclose(labels.segment_scores(r, "discounted", 0.5), [1 + 1 + 0.75, 3.0])


def test_sum_teacher_labels_are_one_when_segment_2_has_more_reward():
    ds = _dataset([0, 1, 2, 3, 10, 0, 0, 5], ends=[3])
    prefs = labels.scripted_teacher(ds, 300, 2, seed=3)
    assert prefs.source == "script" and prefs.segment_length == 2 and len(prefs) == 300
    s1, s2 = _scores(ds, prefs.starts_1, 2), _scores(ds, prefs.starts_2, 2)
    np.testing.assert_array_equal(prefs.labels, (s1 < s2).astype(np.float32))
    assert prefs.labels.dtype == np.float32 and prefs.starts_1.dtype == np.int64
    # no ties by default: equal scores give 0 (segment 1), as PT's label_type 0
    assert (s1 == s2).any() and (prefs.labels[s1 == s2] == 0).all()


def test_discounted_teacher_differs_from_sum_where_timing_matters():
    # segment A = [0, 1]: sum 1, discounted 0.99; segment B = [0.995, 0]: sum 0.995, discounted 0.995
    ds = _dataset([0, 1, 0.995, 0], ends=[1])
    by_sum = labels.scripted_teacher(ds, 50, 2, seed=0)
    by_disc = labels.scripted_teacher(ds, 50, 2, teacher="discounted", discount=0.99, seed=0)
    np.testing.assert_array_equal(by_sum.starts_1, by_disc.starts_1)
    a_vs_b = (by_sum.starts_1 == 0) & (by_sum.starts_2 == 2)
    assert a_vs_b.any()
    assert (by_sum.labels[a_vs_b] == 0).all() and (by_disc.labels[a_vs_b] == 1).all()
    s1 = _scores(ds, by_disc.starts_1, 2, 0.99)
    s2 = _scores(ds, by_disc.starts_2, 2, 0.99)
    np.testing.assert_array_equal(by_disc.labels, s1 < s2)


def test_ties_at_threshold_are_half():
    ds = _dataset([0, 1, 2, 3, 4, 5])
    prefs = labels.scripted_teacher(ds, 400, 1, tie_threshold=1.0, seed=1)
    diff = np.abs(ds.rewards[prefs.starts_1] - ds.rewards[prefs.starts_2])
    np.testing.assert_array_equal(prefs.labels == 0.5, diff <= 1.0)  # |S1 - S2| = 1 is a tie
    assert (diff == 1.0).any()
    strict = ~(diff <= 1.0)
    np.testing.assert_array_equal(
        prefs.labels[strict], ds.rewards[prefs.starts_1][strict] < ds.rewards[prefs.starts_2][strict]
    )
    exact = labels.scripted_teacher(ds, 400, 1, tie_threshold=0.0, seed=1)
    np.testing.assert_array_equal(exact.labels == 0.5, diff == 0)


def test_mistake_rate_flips_non_tie_labels():
    ds = _dataset(np.arange(50) % 7)
    clean = labels.scripted_teacher(ds, 2000, 3, tie_threshold=0.0, seed=5)
    flipped = labels.scripted_teacher(ds, 2000, 3, tie_threshold=0.0, mistake_rate=1.0, seed=5)
    ties = clean.labels == 0.5
    assert ties.any() and (~ties).any()
    np.testing.assert_array_equal(flipped.labels[ties], 0.5)
    np.testing.assert_array_equal(flipped.labels[~ties], 1 - clean.labels[~ties])
    noisy = labels.scripted_teacher(ds, 2000, 3, tie_threshold=0.0, mistake_rate=0.2, seed=5)
    rate = np.mean(noisy.labels[~ties] != clean.labels[~ties])
    assert 0.17 < rate < 0.23
    again = labels.scripted_teacher(ds, 2000, 3, tie_threshold=0.0, mistake_rate=0.2, seed=5)
    np.testing.assert_array_equal(again.labels, noisy.labels)
    other = labels.scripted_teacher(ds, 2000, 3, tie_threshold=0.0, mistake_rate=0.2, seed=6)
    assert not np.array_equal(other.starts_1, noisy.starts_1)


def test_segments_stay_inside_episodes_and_cover_every_valid_start():
    # episodes (view rows): 0-4 (5 long), 5 (1 long, too short), 6-9 (4 long)
    ds = _dataset(np.zeros(10), ends=[4, 5])
    prefs = labels.scripted_teacher(ds, 500, 3, seed=0)
    starts = np.concatenate([prefs.starts_1, prefs.starts_2])
    assert set(starts.tolist()) == {0, 1, 2, 6, 7}
    labels.check_against(prefs, ds, allow_cross_episode=False)
    crossing = labels.scripted_teacher(ds, 500, 3, allow_cross_episode=True, seed=0)
    assert set(np.concatenate([crossing.starts_1, crossing.starts_2]).tolist()) == set(range(8))
    with pytest.raises(SpotError, match=r"dataset 'hand': no episode has at least 6 transitions \(longest 5 of 3"):
        labels.scripted_teacher(ds, 5, 6)
    with pytest.raises(SpotError, match="unknown teacher 'max'"):
        labels.scripted_teacher(ds, 5, 2, teacher="max")


def test_dense_score_compares_the_dense_reward_and_names_a_missing_one():
    # Sparse reward: 1 at the last step only (robosuite's success), so nearly every pair ties;
    # the dense reward rises along the episode and decides them.
    sparse = np.zeros(30)
    sparse[-1] = 1.0
    dense = np.linspace(0.0, 0.6, 30)
    ds = _dataset(sparse)
    ds = ds.replace(infos={"dense_reward": dense.astype(np.float32)})
    by_reward = labels.scripted_teacher(ds, 400, 5, tie_threshold=0.0, seed=2)
    by_dense = labels.scripted_teacher(ds, 400, 5, tie_threshold=0.0, seed=2, score="dense")
    np.testing.assert_array_equal(by_reward.starts_1, by_dense.starts_1)  # same queries
    assert np.mean(by_reward.labels == 0.5) > 0.7
    same = by_dense.starts_1 == by_dense.starts_2
    np.testing.assert_array_equal(by_dense.labels == 0.5, same)  # only identical segments tie
    np.testing.assert_array_equal(by_dense.labels[~same], (by_dense.starts_1 < by_dense.starts_2)[~same])
    np.testing.assert_array_equal(labels.score_rewards(ds, "reward"), ds.rewards)
    with pytest.raises(SpotError, match=r"dataset 'hand' has no dense reward 'infos/dense_reward' \(infos: none\)"):
        labels.scripted_teacher(_dataset(sparse), 10, 5, score="dense")
    with pytest.raises(SpotError, match=r"'infos/dense_reward' has shape \(30,\) \(finite: False\)"):
        labels.scripted_teacher(ds.replace(infos={"dense_reward": np.full(30, np.nan)}), 10, 5, score="dense")
    with pytest.raises(SpotError, match="unknown teacher score 'shaped'; expected one of reward, dense"):
        labels.scripted_teacher(ds, 10, 5, score="shaped")


# --------------------------------------------------------------------------- Preferences
def test_preferences_validate_subset_and_npz_round_trip(tmp_path):
    prefs = Preferences(np.array([0, 5, 9]), np.array([1, 2, 3]), np.array([0, 0.5, 1]), 4, "script")
    sub = prefs.subset(np.array([2, 0]))
    np.testing.assert_array_equal(sub.starts_1, [9, 0])
    np.testing.assert_array_equal(sub.labels, [1, 0])
    path = tmp_path / "q" / "prefs.npz"
    prefs.save_npz(path)
    assert os.listdir(path.parent) == ["prefs.npz"]
    back = Preferences.load_npz(path)
    for key in ("starts_1", "starts_2", "labels"):
        np.testing.assert_array_equal(getattr(back, key), getattr(prefs, key))
        assert getattr(back, key).dtype == getattr(prefs, key).dtype
    assert (back.segment_length, back.source) == (4, "script")
    with pytest.raises(SpotError, match=r"labels \[0\.3\]; expected values in \{0, 0\.5, 1\}"):
        Preferences(np.array([0]), np.array([1]), np.array([0.3]), 4, "x")
    with pytest.raises(SpotError, match=r"'starts_2' has shape \(2,\); expected \(1,\)"):
        Preferences(np.array([0]), np.array([1, 2]), np.array([1.0]), 4, "x")
    np.savez(tmp_path / "partial.npz", starts_1=np.zeros(2, int))
    with pytest.raises(SpotError, match=r"partial\.npz': missing keys \['starts_2', 'labels'"):
        Preferences.load_npz(tmp_path / "partial.npz")
    with pytest.raises(SpotError, match="does not exist"):
        Preferences.load_npz(tmp_path / "none.npz")


# --------------------------------------------------------------------------- PT human labels
# (folder, labels, ties (-1), zeros, ones, segment length)
PT_FOLDERS = [
    ("hopper-medium-replay-v2", 500, 191, 121, 188, 100),
    ("hopper-medium-expert-v2", 100, 28, 32, 40, 100),
    ("walker2d-medium-replay-v2", 500, 117, 164, 219, 100),
    ("walker2d-medium-expert-v2", 100, 24, 30, 46, 100),
    ("Lift_ph", 100, None, None, None, 50),
    ("Can_ph", 100, None, None, None, 50),
    ("Lift_mh", 500, None, None, None, 100),
    ("Can_mh", 500, None, None, None, 100),
]


@pytest.mark.parametrize("folder, n, ties, zeros, ones, length", PT_FOLDERS)
def test_real_pt_label_files(folder, n, ties, zeros, ones, length):
    prefs = labels.read_pt_labels(PT_LABELS / folder)
    assert len(prefs) == n and prefs.segment_length == length
    assert prefs.source == str(PT_LABELS / folder)
    counts = (int(np.sum(prefs.labels == 0.5)), int(np.sum(prefs.labels == 0)), int(np.sum(prefs.labels == 1)))
    assert sum(counts) == n
    if ties is not None:
        assert counts == (ties, zeros, ones)
    end = int(max(prefs.starts_1.max(), prefs.starts_2.max())) + length
    labels.check_against(prefs, _zeros(end + 1, name=folder))  # raw rows; the view has `end`
    with pytest.raises(
        SpotError, match=rf"query \d+ starts at index {end - length} .*dataset '{folder}' \({end - 1} transitions\)"
    ):
        labels.check_against(prefs, _zeros(end, name=folder))


def test_medium_expert_uses_the_first_indices_and_num_queries_the_last_labels():
    folder = PT_LABELS / "hopper-medium-expert-v2"
    with open(folder / "indices_num100", "rb") as fh:  # a trusted file, read here only to compare
        all_starts = pickle.load(fh)
    prefs = labels.read_pt_labels(folder)
    assert all_starts.size == 500
    np.testing.assert_array_equal(prefs.starts_1, all_starts[:100])
    last = labels.read_pt_labels(folder, num_queries=10)
    np.testing.assert_array_equal(last.starts_1, all_starts[90:100])
    np.testing.assert_array_equal(last.labels, prefs.labels[90:])
    with pytest.raises(SpotError, match=r"num_queries 101; expected 1\.\.100"):
        labels.read_pt_labels(folder, num_queries=101)


def _label_folder(tmp_path, label_value):
    """A copy of the Lift_ph index files with ``label_value`` pickled as label_human."""
    folder = tmp_path / "Lift_ph"
    folder.mkdir()
    for name in ("indices_num100_q50", "indices_2_num100_q50"):
        shutil.copy(PT_LABELS / "Lift_ph" / name, folder / name)
    (folder / "label_human").write_bytes(pickle.dumps(label_value))
    return folder


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_pickles_with_other_globals_are_refused_and_never_run(tmp_path):
    marker = tmp_path / "pwned"
    folder = _label_folder(tmp_path, [_Evil(marker)])
    with pytest.raises(SpotError, match=r"Lift_ph/label_human': refused to unpickle global '(posix|os)\.system'"):
        labels.read_pt_labels(folder)
    assert not marker.exists()
    (folder / "label_human").write_bytes(pickle.dumps(collections.OrderedDict(a=1)))
    with pytest.raises(SpotError, match=r"refused to unpickle global 'collections\.OrderedDict'"):
        labels.read_pt_labels(folder)


@pytest.mark.parametrize(
    "value, fragment",
    [
        ([0, 1, 2] * 10, r"label_human' has values \[0, 1, 2\]; expected 0, 1, -1"),
        ([0] * 101, r"label_human' has 101 labels but '.*indices_num100_q50' only 100"),
        ([0.0, 1.0], r"label_human' holds other values; expected a 1-D sequence of integers"),
        ({"labels": [0]}, r"label_human' holds a dict; expected a list or numpy array"),
        (np.zeros((2, 2), np.int64), r"label_human' holds other values"),
    ],
)
def test_bad_label_files_name_the_file(tmp_path, value, fragment):
    with pytest.raises(SpotError, match=fragment):
        labels.read_pt_labels(_label_folder(tmp_path, value))


def test_missing_and_corrupt_label_files(tmp_path):
    folder = _label_folder(tmp_path, [0, 1, -1])
    assert len(labels.read_pt_labels(folder)) == 3
    (folder / "label_human").write_bytes(b"\x80\x04garbage")
    with pytest.raises(SpotError, match=r"label_human' is not a readable pickle"):
        labels.read_pt_labels(folder)
    (folder / "label_human").unlink()
    with pytest.raises(SpotError, match=r"0 files match 'label_human'; expected exactly one"):
        labels.read_pt_labels(folder)
    with pytest.raises(SpotError, match=r"label folder '.*nowhere' does not exist"):
        labels.read_pt_labels(tmp_path / "nowhere")


# --------------------------------------------------------------------------- use with a dataset
def test_segment_batch_gathers_segments_with_relative_timesteps():
    ds = _dataset(np.arange(10) * 0.5, ends=[4])
    prefs = Preferences(np.array([0, 3]), np.array([6, 2]), np.array([1.0, 0.5]), 3, "hand")
    batch = labels.segment_batch(ds, prefs)
    assert batch["obs_1"].shape == (2, 3, 2) and batch["act_2"].shape == (2, 3, 1)
    np.testing.assert_array_equal(batch["obs_1"][:, :, 0], [[0, 1, 2], [3, 4, 5]])  # crosses ep. end
    np.testing.assert_array_equal(batch["act_2"][:, :, 0], -np.array([[6, 7, 8], [2, 3, 4]]))
    np.testing.assert_array_equal(batch["rew_2"], [[3, 3.5, 4], [1, 1.5, 2]])
    np.testing.assert_array_equal(batch["timesteps_1"], [[1, 2, 3], [1, 2, 3]])
    assert batch["timesteps_2"].dtype == np.int32
    np.testing.assert_array_equal(batch["label"], [1.0, 0.5])
    with pytest.raises(SpotError, match=r"segment 1 of query 1 \(start 3, length 3\) crosses an episode end"):
        labels.check_against(prefs, ds, allow_cross_episode=False)
    late = Preferences(np.array([0, 8]), np.array([0, 0]), np.array([1.0, 0.0]), 3, "late")
    with pytest.raises(SpotError, match=r"labels 'late': segment 1 of query 1 starts at index 8 .*\(10 transitions\)"):
        labels.segment_batch(ds, late)


def test_split_eval_is_disjoint_and_seeded():
    prefs = labels.scripted_teacher(_dataset(np.arange(30.0)), 500, 5, seed=0)
    ids = np.arange(500)
    tagged = Preferences(ids, ids, prefs.labels, 5, "tagged")  # starts_1 = query id
    train, held = labels.split_eval(tagged, 0.1, seed=7)
    assert (len(train), len(held)) == (450, 50)
    assert not set(train.starts_1) & set(held.starts_1)
    assert sorted(set(train.starts_1) | set(held.starts_1)) == list(range(500))
    np.testing.assert_array_equal(train.labels, prefs.labels[train.starts_1])
    again, _ = labels.split_eval(tagged, 0.1, seed=7)
    other, _ = labels.split_eval(tagged, 0.1, seed=8)
    np.testing.assert_array_equal(again.starts_1, train.starts_1)
    assert not np.array_equal(other.starts_1, train.starts_1)
    all_train, none = labels.split_eval(tagged, 0.0, seed=0)
    assert (len(all_train), len(none)) == (500, 0)
    assert len(labels.split_eval(tagged.subset(np.arange(3)), 0.1, seed=0)[1]) == 1
    with pytest.raises(SpotError, match="expected 0 <= fraction < 1"):
        labels.split_eval(tagged, 1.0, seed=0)
