"""Dataset file readers and writers, on small files written here in the real layouts."""

import dataclasses
import json
import os

import gymnasium as gym
import h5py
import numpy as np
import pytest

from spot import SpotError
from spot.data import formats
from spot.data.dataset import RawDataset


def _raw(n=10, timeouts=(3,), terminals=(6,), name="hand"):
    obs = np.arange(n * 2, dtype=np.float32).reshape(n, 2)
    t = np.zeros(n, bool)
    t[list(terminals)] = True
    to = np.zeros(n, bool)
    to[list(timeouts)] = True
    return RawDataset(
        observations=obs,
        actions=np.ones((n, 1), np.float32),
        rewards=np.arange(n, dtype=np.float32),
        terminals=t,
        timeouts=to,
        next_observations=obs + 0.5,
        name=name,
        metadata={"env": "Hop"},
    )


def _write_d4rl(path, n=10, drop=(), **replace):
    """A file exactly in D4RL's layout: float32 arrays, bool flags, infos/ and metadata/ groups."""
    arrays = {
        "observations": np.arange(n * 3, dtype=np.float32).reshape(n, 3),
        "actions": np.zeros((n, 2), np.float32),
        "rewards": np.arange(n, dtype=np.float32),
        "terminals": np.zeros(n, bool),
        "timeouts": np.zeros(n, bool),
        **replace,
    }
    with h5py.File(path, "w") as f:
        for key, arr in arrays.items():
            if key not in drop:
                f.create_dataset(key, data=arr)
        f.create_dataset("infos/qpos", data=np.zeros((n, 3)))
        f.create_dataset("metadata/algorithm", data="SAC")
        f.create_dataset("metadata/iteration", data=np.int64(7))
        f.create_dataset("metadata/policy/fc0/weight", data=np.zeros((4, 3)))
    return path


# --------------------------------------------------------------------------- D4RL
def test_d4rl_round_trip_keeps_arrays_card_and_metadata(tmp_path):
    raw = _raw()
    path = tmp_path / "sub" / "hand.hdf5"
    card = {"recipe": "test", "returns": [1.5, 2.0]}
    formats.write_d4rl_hdf5(raw, path, card)
    back = formats.read_d4rl_hdf5(path)
    for key in ("observations", "actions", "rewards", "terminals", "timeouts", "next_observations"):
        np.testing.assert_array_equal(getattr(back, key), getattr(raw, key))
        assert getattr(back, key).dtype == getattr(raw, key).dtype
    assert back.name == "hand"
    assert back.metadata == {"env": "Hop", "spot_card": card}
    with h5py.File(path) as f:
        assert f["observations"].compression == "gzip"
        assert json.loads(f.attrs["spot_card"]) == card
    assert os.listdir(path.parent) == ["hand.hdf5"]


def test_d4rl_infos_round_trip_and_real_infos_group(tmp_path):
    dense = np.linspace(0, 1, 10, dtype=np.float32)
    path = tmp_path / "dense.hdf5"
    formats.write_d4rl_hdf5(dataclasses.replace(_raw(), infos={"dense_reward": dense}), path)
    back = formats.read_d4rl_hdf5(path)
    assert back.infos.keys() == {"dense_reward"}
    np.testing.assert_array_equal(back.infos["dense_reward"], dense)
    assert back.infos["dense_reward"].dtype == np.float32
    np.testing.assert_array_equal(back.qlearning().infos["dense_reward"], dense[[0, 1, 2, 4, 5, 6, 7, 8]])
    # D4RL's own infos/ (per-step qpos here) are read; arrays of another length are skipped; a
    # file written before infos existed reads with none.
    real = _write_d4rl(tmp_path / "real.hdf5")
    with h5py.File(real, "a") as f:
        f.create_dataset("infos/per_episode", data=np.zeros(3))
    assert formats.read_d4rl_hdf5(real).infos.keys() == {"qpos"}
    formats.write_d4rl_hdf5(_raw(), tmp_path / "old.hdf5")
    assert formats.read_d4rl_hdf5(tmp_path / "old.hdf5").infos == {}


def test_d4rl_real_layout_and_qlearning_view(tmp_path):
    terminals = np.zeros(10, bool)
    terminals[6] = True
    timeouts = np.zeros(10, bool)
    timeouts[3] = True
    path = _write_d4rl(tmp_path / "hopper-medium-v2.hdf5", terminals=terminals, timeouts=timeouts)
    raw = formats.read_d4rl_hdf5(path)
    assert raw.next_observations is None
    assert raw.metadata == {"algorithm": "SAC", "iteration": 7}  # policy weights skipped
    ds = raw.qlearning()
    # row 3 is a timeout and row 9 the last row: both dropped, as d4rl.qlearning_dataset does
    np.testing.assert_array_equal(ds.raw_index, [0, 1, 2, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(ds.rewards, [0, 1, 2, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(ds.next_observations[:, 0], 3 * (ds.raw_index + 1))
    np.testing.assert_array_equal(ds.terminals, [0, 0, 0, 0, 0, 1, 0, 0])
    np.testing.assert_array_equal(ds.episode_ids, [0, 0, 0, 1, 1, 1, 2, 2])


@pytest.mark.parametrize(
    "drop, replace, fragment",
    [
        (("timeouts",), {}, "missing key 'timeouts'"),
        ((), {"rewards": np.zeros((10, 1), np.float32)}, "'rewards' has shape (10, 1); expected rank 1"),
        ((), {"actions": np.zeros((9, 2), np.float32)}, "'actions' has 9 rows but 'observations' has 10"),
        ((), {"observations": np.full((10, 3), np.nan, np.float32)}, "'observations' contains NaN"),
        ((), {"rewards": np.array([0.0] * 9 + [np.inf], np.float32)}, "'rewards' contains NaN or inf"),
        ((), {"terminals": np.array(["x"] * 10, dtype="S1")}, "'terminals' has dtype |S1; expected numbers"),
    ],
)
def test_d4rl_bad_files_name_file_and_key(tmp_path, drop, replace, fragment):
    path = _write_d4rl(tmp_path / "bad.hdf5", drop=drop, **replace)
    with pytest.raises(SpotError) as err:
        formats.read_d4rl_hdf5(path)
    assert str(path) in str(err.value)
    assert fragment in str(err.value)


def test_d4rl_missing_not_hdf5_group_and_bad_card(tmp_path):
    with pytest.raises(SpotError, match=r"'.*nope\.hdf5' does not exist"):
        formats.read_d4rl_hdf5(tmp_path / "nope.hdf5")
    text = tmp_path / "text.hdf5"
    text.write_text("not hdf5")
    with pytest.raises(SpotError, match=r"text\.hdf5' is not a readable hdf5 file"):
        formats.read_d4rl_hdf5(text)
    grouped = _write_d4rl(tmp_path / "grouped.hdf5", drop=("rewards",))
    with h5py.File(grouped, "a") as f:
        f.create_group("rewards")
    with pytest.raises(SpotError, match=r"grouped\.hdf5': 'rewards' is a group; expected an array"):
        formats.read_d4rl_hdf5(grouped)
    card = _write_d4rl(tmp_path / "card.hdf5")
    with h5py.File(card, "a") as f:
        f.attrs["spot_card"] = "{not json"
    with pytest.raises(SpotError, match=r"card\.hdf5': attribute 'spot_card' is not JSON"):
        formats.read_d4rl_hdf5(card)


def test_atomic_write_leaves_old_file_and_no_partial_file(tmp_path, monkeypatch):
    path = tmp_path / "data.hdf5"
    formats.write_d4rl_hdf5(_raw(name="old"), path, {"v": 1})
    real_create = h5py.Group.create_dataset

    def failing_create(self, name, *args, **kwargs):
        if name == "rewards":
            raise OSError("disk full")
        return real_create(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing_create)
    with pytest.raises(OSError, match="disk full"):
        formats.write_d4rl_hdf5(_raw(n=20, timeouts=(), terminals=()), path, {"v": 2})
    with pytest.raises(OSError, match="disk full"):
        formats.write_d4rl_hdf5(_raw(), tmp_path / "new.hdf5")
    assert sorted(os.listdir(tmp_path)) == ["data.hdf5"]
    monkeypatch.undo()
    old = formats.read_d4rl_hdf5(path)
    assert len(old) == 10 and old.metadata["spot_card"] == {"v": 1}


# --------------------------------------------------------------------------- robomimic
_OBS_DIMS = dict(zip(formats.ROBOMIMIC_OBS_KEYS, (10, 7, 7, 7, 7, 3, 4, 2, 2), strict=True))  # Lift: 49


def _write_robomimic(path, lengths=None, skip_key=None, env_args=True):
    """robomimic low_dim layout; obs column j of key k holds 1000*demo + 100*step + key index."""
    lengths = lengths or {0: 3, 1: 4, 2: 2, 10: 5}
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        if env_args:
            data.attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1, "env_kwargs": {}})
        for n, steps in lengths.items():
            demo = data.create_group(f"demo_{n}")
            for i, (key, dim) in enumerate(_OBS_DIMS.items()):
                if key == skip_key:
                    continue
                value = 1000 * n + 100 * np.arange(steps + 1)[:, None] + i + np.zeros((1, dim))
                demo.create_dataset(f"obs/{key}", data=value[:-1])
                demo.create_dataset(f"next_obs/{key}", data=value[1:])
            demo.create_dataset("actions", data=np.full((steps, 7), n, np.float64))
            demo.create_dataset("rewards", data=np.arange(steps, dtype=np.float64))
            dones = np.zeros(steps, np.int64)
            dones[-1] = n % 2  # odd demos end with done = 1
            demo.create_dataset("dones", data=dones)
            demo.create_dataset("states", data=np.zeros((steps, 5)))
            demo.attrs["num_samples"] = steps
        f.create_dataset("mask/train", data=np.array([b"demo_0", b"demo_1"]))
    return path


def test_robomimic_layout_order_and_pt_view(tmp_path):
    raw = formats.read_robomimic_hdf5(_write_robomimic(tmp_path / "low_dim.hdf5"))
    assert raw.observations.shape == (14, 49) and raw.observations.dtype == np.float32
    key_of_column = np.repeat(np.arange(9), list(_OBS_DIMS.values()))
    np.testing.assert_array_equal(raw.observations[0] % 100, key_of_column)
    # the file's key order (PT's loader): demo_0, demo_1, demo_10, demo_2
    np.testing.assert_array_equal(raw.actions[:, 0], [0] * 3 + [1] * 4 + [10] * 5 + [2] * 2)
    np.testing.assert_array_equal(raw.next_observations[:, 0], raw.observations[:, 0] + 100)
    assert raw.metadata["env_name"] == "Lift" and raw.metadata["demos"] == 4
    ends = np.cumsum([3, 4, 5, 2]) - 1
    np.testing.assert_array_equal(np.flatnonzero(raw.timeouts), ends)
    np.testing.assert_array_equal(np.flatnonzero(raw.terminals), [ends[1]])  # demo_1 has done = 1
    ds = raw.qlearning()
    # the last step of every demo is dropped, as in PT's qlearning_robosuite_dataset
    assert len(ds) == 2 + 3 + 4 + 1
    np.testing.assert_array_equal(ds.episode_lengths(), [2, 3, 4, 1])
    assert not ds.terminals.any()


def test_robomimic_obs_keys_and_errors(tmp_path):
    path = _write_robomimic(tmp_path / "mh.hdf5", skip_key="robot0_joint_vel")
    with pytest.raises(SpotError, match=r"mh\.hdf5': missing key 'data/demo_0/obs/robot0_joint_vel'"):
        formats.read_robomimic_hdf5(path)
    raw = formats.read_robomimic_hdf5(path, obs_keys=("robot0_eef_pos", "object"))
    assert raw.observations.shape[1] == 13
    assert raw.observations[0, 0] == 5 and raw.observations[0, 3] == 0
    no_args = _write_robomimic(tmp_path / "noargs.hdf5", env_args=False)
    with pytest.raises(SpotError, match=r"noargs\.hdf5': missing attribute 'data.attrs\[env_args\]'"):
        formats.read_robomimic_hdf5(no_args)
    with h5py.File(path, "a") as f:
        del f["data/demo_2/rewards"]
        f["data/demo_2/rewards"] = np.zeros(7)
    with pytest.raises(SpotError, match=r"'data/demo_2' has rows .*'rewards': 7"):
        formats.read_robomimic_hdf5(path, obs_keys=("object",))


# robomimic's Can "object" block as robosuite <= 1.4 (robomimic v0.1 / v1.4.1 files) writes it,
# and as robosuite 1.5.1 (the evaluation env) does.
_CAN_V01 = ("Can_pos", 3), ("Can_quat", 4), ("Can_to_robot0_eef_pos", 3), ("Can_to_robot0_eef_quat", 4)
_CAN_V15 = ("Can_to_robot0_eef_pos", 3), ("Can_to_robot0_eef_quat", 4), ("Can_pos", 3), ("Can_quat", 4)


def _write_robomimic_can(path, obs_steps, env_version=None):
    """A Can file in robomimic's low_dim layout: one demo per list of per-step observation dicts
    (robosuite observable names), ``object`` concatenated in robomimic v0.1's order."""
    env_args = {
        "env_name": "PickPlaceCan",
        "type": 1,
        "env_kwargs": {"robots": ["Panda"], "control_freq": 20, "reward_shaping": False},
    }
    if env_version is not None:
        env_args["env_version"] = env_version
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps(env_args)
        data.attrs["total"] = sum(len(steps) - 1 for steps in obs_steps)
        for n, steps in enumerate(obs_steps):
            demo = data.create_group(f"demo_{n}")
            rows = {k: np.stack([s[k] for s in steps]) for k in formats.ROBOMIMIC_OBS_KEYS[1:]}
            rows["object"] = np.stack([np.concatenate([s[k] for k, _ in _CAN_V01]) for s in steps])
            for key, value in rows.items():
                demo.create_dataset(f"obs/{key}", data=value[:-1])
                demo.create_dataset(f"next_obs/{key}", data=value[1:])
            t = len(steps) - 1
            demo.create_dataset("actions", data=np.zeros((t, 7)))
            demo.create_dataset("rewards", data=np.eye(t)[-1])
            demo.create_dataset("dones", data=np.eye(t, dtype=np.int64)[-1])
            demo.create_dataset("states", data=np.zeros((t, 71)))
            demo.attrs["num_samples"] = t
    return path


def _can_step(i):
    """Observation dict of step ``i`` with every entry distinct: column c of key k = 100*i + 10*k + c."""
    dims = dict(_CAN_V01) | dict(zip(formats.ROBOMIMIC_OBS_KEYS[1:], (7, 7, 7, 7, 3, 4, 2, 2), strict=True))
    return {k: 100.0 * i + 10 * j + np.arange(d) for j, (k, d) in enumerate(dims.items())}


def test_robomimic_can_object_block_is_reordered_to_robosuite_15(tmp_path):
    steps = [[_can_step(i) for i in range(4)], [_can_step(i) for i in range(10, 13)]]
    raw = formats.read_robomimic_hdf5(_write_robomimic_can(tmp_path / "can_ph.hdf5", steps))
    assert raw.observations.shape == (5, 53) and raw.metadata["object_reordered"]
    expected = [
        np.concatenate([s[k] for k, _ in _CAN_V15] + [s[k] for k in formats.ROBOMIMIC_OBS_KEYS[1:]])
        for demo in steps
        for s in demo[:-1]
    ]
    np.testing.assert_array_equal(raw.observations, np.float32(expected))
    np.testing.assert_array_equal(raw.next_observations[0], raw.observations[1])
    # Can_pos sits at object[7:10], where the robosuite recipe's scripts read it.
    np.testing.assert_array_equal(raw.observations[0, 7:10], steps[0][0]["Can_pos"])
    # Recorded with robosuite 1.4.1 (robomimic's v141 files): same old order, reordered.
    old = formats.read_robomimic_hdf5(_write_robomimic_can(tmp_path / "v141.hdf5", steps, "1.4.1"))
    np.testing.assert_array_equal(old.observations, raw.observations)
    # Regenerated with robosuite 1.5 (robomimic's v15 files): already in order, kept as written.
    v15 = formats.read_robomimic_hdf5(_write_robomimic_can(tmp_path / "v15.hdf5", steps, "1.5.0"))
    assert not v15.metadata["object_reordered"]
    np.testing.assert_array_equal(v15.observations[0, :14], np.concatenate([steps[0][0][k] for k, _ in _CAN_V01]))
    # Other tasks are never reordered.
    lift = formats.read_robomimic_hdf5(_write_robomimic(tmp_path / "lift.hdf5"))
    assert not lift.metadata["object_reordered"]


def test_robomimic_can_with_a_wrong_object_block_or_version_fails_naming_it(tmp_path):
    path = _write_robomimic_can(tmp_path / "can.hdf5", [[_can_step(i) for i in range(3)]])
    with h5py.File(path, "a") as f:
        for group in ("obs", "next_obs"):
            obj = f[f"data/demo_0/{group}/object"][()]
            del f[f"data/demo_0/{group}/object"]
            f[f"data/demo_0/{group}/object"] = obj[:, :10]
    with pytest.raises(SpotError, match=r"can\.hdf5': 'data/demo_0/obs/object' has 10 columns; expected 14"):
        formats.read_robomimic_hdf5(path)
    odd = _write_robomimic_can(tmp_path / "odd.hdf5", [[_can_step(i) for i in range(3)]], "dev")
    with pytest.raises(SpotError, match=r"odd\.hdf5'.*env_version 'dev'"):
        formats.read_robomimic_hdf5(odd)


@pytest.mark.slow
def test_robomimic_v01_can_file_reads_as_the_evaluation_env_observes(tmp_path):
    """Observables of the real robosuite 1.5.1 PickPlaceCan, written as robomimic v0.1 would,
    read back equal to the evaluation env's flat observation."""
    pytest.importorskip("robosuite")
    from spot.envs import make_env

    env = make_env("can-ph", 0)
    try:
        flat, dicts = [], []
        env.reset(seed=3)
        for t in range(3):  # after a step robosuite fills the object-to-eef observables
            flat.append(env.step(np.full(7, 0.3 * (-1) ** t))[0])
            dicts.append({k: np.asarray(v) for k, v in env.unwrapped._env._get_observations().items()})
    finally:
        env.close()
    assert np.abs(dicts[-1]["Can_to_robot0_eef_pos"]).max() > 0
    raw = formats.read_robomimic_hdf5(_write_robomimic_can(tmp_path / "can.hdf5", [dicts]))
    np.testing.assert_allclose(raw.observations, np.float32(flat[:-1]), rtol=1e-6)


# --------------------------------------------------------------------------- Minari
class _DictObs(gym.ObservationWrapper):
    """Pendulum with a Dict observation {"b": obs[1:], "a": obs[:1]}."""

    def __init__(self, env):
        super().__init__(env)
        box = env.observation_space
        self.observation_space = gym.spaces.Dict(
            {
                "b": gym.spaces.Box(box.low[1:], box.high[1:]),
                "a": gym.spaces.Box(box.low[:1], box.high[:1]),
            }
        )

    def observation(self, obs):
        return {"b": obs[1:], "a": obs[:1]}


def _collect(env, dataset_id, steps=50):
    import minari

    env = minari.DataCollector(env)
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    env.create_dataset(dataset_id, algorithm_name="random")
    env.close()


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_minari_dataset_round_trip(tmp_path, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    _collect(gym.make("CartPole-v1", max_episode_steps=15), "cartpole/random-v0")
    raw = formats.read_minari("cartpole/random-v0")
    source = minari.load_dataset("cartpole/random-v0")
    episodes = list(source.iterate_episodes())
    assert len(raw) == sum(len(ep) for ep in episodes) == 50
    assert raw.observations.shape[1] == 4 and raw.actions.shape[1] == 1
    np.testing.assert_allclose(raw.observations[: len(episodes[0])], episodes[0].observations[:-1])
    np.testing.assert_allclose(raw.next_observations[: len(episodes[0])], episodes[0].observations[1:])
    ends = np.cumsum([len(ep) for ep in episodes]) - 1
    np.testing.assert_array_equal(np.flatnonzero(raw.terminals | raw.timeouts), ends)
    np.testing.assert_array_equal(raw.terminals[ends], [ep.terminations[-1] for ep in episodes])
    assert raw.name == "cartpole/random-v0"
    # by folder, through the dispatcher
    folder = tmp_path / "cartpole" / "random-v0"
    assert formats.detect_format(folder) == "minari"
    assert len(formats.load_dataset_file(folder)) == 50
    with pytest.raises(SpotError, match="Minari dataset 'cartpole/none-v0' could not be loaded"):
        formats.read_minari("cartpole/none-v0")


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_minari_dict_observations_flatten_in_sorted_key_order(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    _collect(_DictObs(gym.make("Pendulum-v1", max_episode_steps=10)), "pendulum/dict-v0", steps=20)
    raw = formats.read_minari("pendulum/dict-v0")
    assert raw.observations.shape == (20, 3)
    # sorted keys a, b give back Pendulum's own order (cos, sin, velocity): cos^2 + sin^2 = 1
    np.testing.assert_allclose(raw.observations[:, 0] ** 2 + raw.observations[:, 1] ** 2, 1, rtol=1e-5)
    np.testing.assert_array_equal(np.flatnonzero(raw.timeouts), [9, 19])


# --------------------------------------------------------------------------- dispatch
def test_load_dataset_file_detects_format(tmp_path):
    d4rl = _write_d4rl(tmp_path / "a.hdf5")
    robo = _write_robomimic(tmp_path / "b.hdf5")
    assert formats.detect_format(d4rl) == "d4rl" and formats.detect_format(robo) == "robomimic"
    assert len(formats.load_dataset_file(d4rl)) == 10
    assert formats.load_dataset_file(robo).metadata["env_name"] == "Lift"
    assert len(formats.load_dataset_file(robo, format="robomimic")) == 14
    with pytest.raises(SpotError, match=r"b\.hdf5': missing key 'observations'"):
        formats.load_dataset_file(robo, format="d4rl")
    other = tmp_path / "c.hdf5"
    with h5py.File(other, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(SpotError, match=r"c\.hdf5': top-level keys \['x'\]"):
        formats.load_dataset_file(other)
    with pytest.raises(SpotError, match="unknown dataset format 'csv'"):
        formats.load_dataset_file(d4rl, "csv")
    with pytest.raises(SpotError, match="does not exist"):
        formats.load_dataset_file(tmp_path / "missing.hdf5")
