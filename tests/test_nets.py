"""The shared building blocks (spot/nets.py) on their own: MLP, dropout, transformer block, helpers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spot import nets


def _fmix32(x: int) -> int:
    """MurmurHash3's 32-bit finaliser, written out with Python integers."""
    m = 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x85EBCA6B) & m
    x ^= x >> 13
    x = (x * 0xC2B2AE35) & m
    return x ^ (x >> 16)


def test_hash_bits_is_fmix32_of_index_times_phi_plus_seed():
    seed = 12345
    got = np.asarray(nets.hash_bits((2, 3), jnp.uint32(seed)))
    want = [_fmix32((i * 0x9E3779B9 + seed) & 0xFFFFFFFF) for i in range(6)]
    np.testing.assert_array_equal(got.ravel(), np.array(want, np.uint32))


def test_mlp_matches_a_hand_computed_forward_pass():
    mlp = nets.MLP(hidden=[2], out_dim=1)
    params = {
        "params": {
            "Dense_0": {"kernel": jnp.array([[1.0, -1.0], [2.0, 0.5]]), "bias": jnp.array([0.0, 1.0])},
            "Dense_1": {"kernel": jnp.array([[3.0], [-2.0]]), "bias": jnp.array([0.5])},
        }
    }
    # x = (1, 1): hidden pre-activations (1+2+0, -1+0.5+1) = (3, 0.5) -> relu (3, 0.5)
    # output 3*3 - 2*0.5 + 0.5 = 8.5;  x = (-1, 0): (-1, 1+1) = (-1, 2) -> (0, 2) -> -4 + 0.5 = -3.5
    out = mlp.apply(params, jnp.array([[1.0, 1.0], [-1.0, 0.0]]))
    np.testing.assert_allclose(np.asarray(out), [[8.5], [-3.5]])


def test_mlp_param_count_by_hand():
    mlp = nets.MLP(hidden=[4], out_dim=2)
    params = mlp.init(jax.random.key(0), jnp.zeros((1, 3)))
    assert nets.param_count(params) == 3 * 4 + 4 + 4 * 2 + 2


def test_mlp_without_layers_is_an_error():
    with pytest.raises(ValueError, match="at least one layer"):
        nets.MLP(hidden=[]).init(jax.random.key(0), jnp.zeros((1, 3)))


def test_dropout_drops_at_the_rate_and_rescales_kept_values():
    x = jnp.ones((200, 100))
    y = np.asarray(nets.Dropout(0.25).apply({}, x, deterministic=False, rngs={"dropout": jax.random.key(1)}))
    kept = y != 0
    assert abs(kept.mean() - 0.75) < 0.01  # 20k draws: std of the mean ~0.003
    np.testing.assert_allclose(y[kept], 1 / 0.75, rtol=1e-6)
    np.testing.assert_array_equal(nets.Dropout(0.25).apply({}, x, deterministic=True), x)


def _block_and_params(width=8, heads=2, length=5):
    block = nets.TransformerBlock(embd_dim=width, n_head=heads)
    x = jax.random.normal(jax.random.key(0), (2, length, width))
    causal = jnp.tril(jnp.ones((length, length), bool))[None]
    params = block.init(jax.random.key(1), x, causal)
    return block, params, x, causal


def test_transformer_block_is_causal():
    block, params, x, causal = _block_and_params()
    out = block.apply(params, x, causal)
    changed = x.at[:, 3:].add(1.0)  # change only the last two tokens
    out2 = block.apply(params, changed, causal)
    np.testing.assert_allclose(out[:, :3], out2[:, :3], atol=1e-6)
    assert not np.allclose(out[:, 3:], out2[:, 3:])


def test_transformer_block_query_subset_equals_the_full_block_there():
    block, params, x, causal = _block_and_params()
    full = block.apply(params, x, causal)
    idx = np.array([1, 4])
    part = block.apply(params, x, causal[:, idx], query_index=idx)
    np.testing.assert_allclose(part, full[:, idx], atol=1e-5)


def test_transformer_block_rejects_a_mask_of_the_wrong_shape():
    block, params, x, causal = _block_and_params()
    with pytest.raises(ValueError, match="mask has shape"):
        block.apply(params, x, causal[:, :2])
