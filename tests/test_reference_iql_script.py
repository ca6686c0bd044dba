"""scripts/reference_iql/run.py: the data it hands the reference IQL (the reference itself is not
installed here; experiments/oracle-iql/NOTES.md has the cross-check it ran)."""

import importlib.util
from pathlib import Path

import h5py
import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "reference_iql" / "run.py"


def _script():
    spec = importlib.util.spec_from_file_location("reference_iql_run", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_load_splits_episodes_and_scales_rewards_by_the_return_range(tmp_path):
    # episode A: 2 steps ending in a fall (terminal), and B starts where A's last step led, so only
    # the terminal ends A; episode B: 3 steps, cut off (no terminal), so only the next row's jump
    # marks where B ends; a one-step episode C follows.
    obs = np.array([[0.0], [1.0], [2.0], [3.0], [4.0], [20.0]], np.float32)
    nxt = np.array([[1.0], [2.0], [3.0], [4.0], [5.0], [21.0]], np.float32)
    rewards = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 0.5], np.float32)
    terminals = np.array([0, 1, 0, 0, 0, 0], bool)
    actions = np.array([[0.5], [1.0], [-1.0], [0.0], [0.2], [-0.3]], np.float32)
    path = tmp_path / "hopper-medium-replay.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in dict(
            observations=obs, next_observations=nxt, rewards=rewards, terminals=terminals, actions=actions
        ).items():
            f[key] = value
    o, a, r, masks, n = _script().load(str(path))
    # returns: A = 3, B = 12, C = 0.5 -> range 11.5; each reward x 1000 / 11.5
    np.testing.assert_allclose(r, rewards * 1000 / 11.5, rtol=1e-6)
    np.testing.assert_array_equal(masks, [1, 0, 1, 1, 1, 1])
    assert a.max() == pytest.approx(1 - 1e-5) and a.min() == pytest.approx(-1 + 1e-5)
    np.testing.assert_array_equal(o, obs)
    np.testing.assert_array_equal(n, nxt)


def test_a_file_of_another_env_is_refused_before_anything_runs(tmp_path):
    # the file's name picks the evaluation env; any other env must not fall through to Walker2d
    with pytest.raises(SystemExit, match="expected a hopper-\\* or walker2d-\\* file"):
        _script().main(str(tmp_path), str(tmp_path / "halfcheetah-medium.hdf5"), 0, 10, str(tmp_path / "out.csv"))
