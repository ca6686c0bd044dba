"""The two controls of the claims report: random-state subgoals and a constant bonus of the same mean."""

import jax.numpy as jnp
import numpy as np
import pytest

from spot import config as config_lib
from spot.subgoal import extract, shaping


def test_constant_bonus_is_the_dataset_mean_of_the_cosine_term():
    next_obs = jnp.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    g_hat = jnp.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    # cosines 1, 0, -1 -> cosine term (cos + 1) / 2 = 1, 0.5, 0 -> mean 0.5 on every transition
    cos = shaping.shape_reward("cosine", next_obs, g_hat)
    np.testing.assert_allclose(cos, [1.0, 0.5, 0.0])
    const = shaping.shape_reward("constant", next_obs, g_hat)
    np.testing.assert_allclose(const, [0.5, 0.5, 0.5])


def test_random_subgoals_keep_s_and_a_and_draw_dataset_states():
    s = np.arange(6, dtype=np.float32).reshape(3, 2)
    t = extract.Triplets(s, np.ones((3, 1), np.float32), s + 100)
    observations = np.array([[7.0, 7.0], [8.0, 8.0]], np.float32)
    out = extract.random_subgoals(t, observations, np.random.default_rng(0))
    np.testing.assert_array_equal(out.s, t.s)
    np.testing.assert_array_equal(out.a, t.a)
    assert out.g.shape == t.g.shape
    assert all(any((g == o).all() for o in observations) for g in out.g)
    again = extract.random_subgoals(t, observations, np.random.default_rng(0))
    np.testing.assert_array_equal(out.g, again.g)


def test_control_keys_resolve_and_need_pt():
    cfg = config_lib.resolve({"method": "spot", "subgoal.source": "random"})
    assert cfg.subgoal.source == "random" and cfg.shaping.kind == "cosine"
    cfg = config_lib.resolve({"method": "spot", "shaping.kind": "constant"})
    assert cfg.shaping.kind == "constant"
    with pytest.raises(Exception, match="reward.kind=pt"):
        config_lib.resolve({"method": "mr", "shaping.kind": "constant"})
