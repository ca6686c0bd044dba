"""Shared flax.linen building blocks: the MLP, the pre-LN GPT-2 block, and train-state helpers.

* :class:`MLP` serves every fully connected network in spot: MR's ``r(s, a)`` (PT repo
  ``JaxPref/model.py``: 256-256 ReLU, output init ``variance_scaling(1e-2, fan_in, uniform)``),
  the IQL actor/critics/value (ikostrikov IQL ``common.py``: 256-256 ReLU, orthogonal init
  sqrt(2), optional dropout) and the CVAE's encoder, prior and decoder (paper Table 6).
* :class:`TransformerBlock` is the GPT-2 block of the Preference Transformer's causal stack
  (reference/algorithms.md §1.1 step 3): ``x += Drop(Dense(Attn(LN(x))))``;
  ``x += Drop(Dense(act(Dense_4D(LN(x)))))``, attention scaled by ``sqrt(head_dim)`` and
  dropout on the attention probabilities. It can compute outputs for a subset of query
  positions (keys and values still cover the whole sequence), which gives exactly the same
  numbers at those positions for a fraction of the cost.
* :class:`Dropout` is inverted dropout with a cheap counter-based keep mask (see its docstring);
  the MLP and the transformer use it.
* :func:`create_train_state` is the one way spot builds a ``flax.training.train_state.TrainState``
  (STYLE.md rule 9); :func:`param_count` counts parameters; :func:`jit_init` initialises a module in
  one cheaply compiled program.

Mixed precision: :class:`TransformerBlock` takes a compute ``dtype`` for its matmuls; its
parameters and residual stream stay float32 and its softmax runs in float32.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

Initializer = Callable[..., jax.Array]
Activation = Callable[[jax.Array], jax.Array]
Params = Any

LN_EPS = 1e-5  # GPT-2 layer_norm_epsilon, also PT's embedding LayerNorm
MASKED_LOGIT = -1e9  # attention logit of a masked key (finite, so a fully masked row stays finite)


def default_init() -> Initializer:
    """flax's ``nn.Dense`` default kernel init (LeCun normal), which the PT repo uses."""
    return nn.initializers.lecun_normal()


def orthogonal_init(scale: float = math.sqrt(2.0)) -> Initializer:
    """Orthogonal kernel init; ``sqrt(2)`` is the IQL reference's hidden-layer scale."""
    return nn.initializers.orthogonal(scale)


def hash_bits(shape: tuple[int, ...], seed: jax.Array) -> jax.Array:
    """Pseudo-random uint32 per element: murmur3's ``fmix32`` finalizer of ``index * phi32 + seed``.

    A counter-based generator (one multiply-add and the five-step avalanche of MurmurHash3 per
    element) that XLA:CPU vectorises, much cheaper than drawing threefry bits per element on CPU
    (docs/benchmarks.md). Statistical quality is ample for dropout masks;
    the randomness still comes from the explicit JAX key that draws ``seed``.
    """
    h = jax.lax.iota(jnp.uint32, math.prod(shape)).reshape(shape) * jnp.uint32(0x9E3779B9) + seed
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * jnp.uint32(0xC2B2AE35)
    return h ^ (h >> 16)


class Dropout(nn.Module):
    """Inverted dropout (drop with probability ``rate``, scale kept values by ``1/(1 - rate)``).

    The keep mask is :func:`hash_bits` with a 32-bit seed drawn from the module's ``"dropout"`` rng
    (so masks differ across modules and steps exactly as with ``nn.Dropout``); the drop
    probability is ``round(rate * 2**32) / 2**32``.
    """

    rate: float

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool) -> jax.Array:
        if deterministic or self.rate == 0.0:
            return x
        if not 0.0 < self.rate < 1.0:
            raise ValueError(f"dropout rate {self.rate} must be in [0, 1)")
        seed = jax.random.bits(self.make_rng("dropout"), (), jnp.uint32)
        keep = hash_bits(x.shape, seed) >= jnp.uint32(round(self.rate * 2**32))
        return jnp.where(keep, x / (1.0 - self.rate), 0.0).astype(x.dtype)


class MLP(nn.Module):
    """Fully connected network ``[*hidden, out_dim]``.

    Every layer but the last is followed by ``activation`` (and dropout if set); the last layer
    gets them only when ``activate_final``. With ``out_dim=None`` the last hidden layer is the
    output (a trunk). The output layer uses ``output_kernel_init`` when given.

    Attributes:
      hidden: hidden layer sizes.
      out_dim: size of the output layer, or None for none.
      activation: elementwise non-linearity.
      activate_final: also activate (and drop out) the last layer.
      kernel_init: kernel init of the hidden layers (and of the output layer by default).
      output_kernel_init: kernel init of the output layer.
      dropout: dropout rate after each activation; needs a ``"dropout"`` rng when
        ``deterministic=False``.
    """

    hidden: Sequence[int]
    out_dim: int | None = None
    activation: Activation = nn.relu
    activate_final: bool = False
    kernel_init: Initializer = default_init()
    output_kernel_init: Initializer | None = None
    dropout: float | None = None

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool = True) -> jax.Array:
        sizes = [*self.hidden] + ([self.out_dim] if self.out_dim is not None else [])
        if not sizes:
            raise ValueError("MLP needs at least one layer (hidden or out_dim)")
        for i, size in enumerate(sizes):
            last = i == len(sizes) - 1
            init = self.output_kernel_init if (last and self.output_kernel_init is not None) else self.kernel_init
            x = nn.Dense(size, kernel_init=init)(x)
            if not last or self.activate_final:
                x = self.activation(x)
                if self.dropout:
                    x = Dropout(self.dropout)(x, deterministic=deterministic)
        return x


class TransformerBlock(nn.Module):
    """Pre-LN GPT-2 block (PT repo ``flaxmodels/gpt2``; reference/algorithms.md §1.1 step 3).

    Attributes:
      embd_dim: model width D (divisible by ``n_head``).
      n_head: attention heads; logits are scaled by ``1/sqrt(D / n_head)``.
      dropout: rate on the attention probabilities and on both residual branches.
      activation: MLP non-linearity (PT uses relu, overriding GPT-2's gelu).
      mlp_ratio: MLP inner width / D (4 in GPT-2).
      dtype: compute dtype of the matmuls; parameters stay float32.
    """

    embd_dim: int
    n_head: int
    dropout: float = 0.0
    activation: Activation = nn.relu
    mlp_ratio: int = 4
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(
        self, x: jax.Array, mask: jax.Array, *, deterministic: bool = True, query_index: np.ndarray | None = None
    ) -> jax.Array:
        """Apply the block.

        Args:
          x: ``[B, L, D]`` token sequence (the residual stream).
          mask: bool ``[B or 1, Lq, L]``, True where query row q may attend to key k (causal and
            padding masks combined by the caller); ``Lq = len(query_index)`` or ``L``.
          deterministic: turn dropout off.
          query_index: static positions whose outputs are computed (default: all). Keys and
            values always cover all ``L`` tokens, so the outputs at these positions equal those of
            the full block.

        Returns:
          ``[B, Lq, D]``.
        """
        batch, length, width = x.shape
        if width != self.embd_dim or width % self.n_head:
            raise ValueError(f"width {width} must equal embd_dim {self.embd_dim} and divide by n_head {self.n_head}")
        head_dim = width // self.n_head
        dense = lambda n, name: nn.Dense(n, dtype=self.dtype, name=name)  # noqa: E731
        drop = lambda y: Dropout(self.dropout)(y, deterministic=deterministic)  # noqa: E731

        h = nn.LayerNorm(epsilon=LN_EPS, dtype=self.dtype, name="ln_attn")(x)
        x_q = x if query_index is None else x[:, query_index]
        h_q = h if query_index is None else h[:, query_index]
        n_q = x_q.shape[1]
        if mask.shape[-2:] != (n_q, length):
            raise ValueError(f"mask has shape {mask.shape}; expected [B, {n_q}, {length}]")
        q = dense(width, "query")(h_q).reshape(batch, n_q, self.n_head, head_dim)
        k, v = jnp.split(dense(2 * width, "key_value")(h), 2, axis=-1)
        k = k.reshape(batch, length, self.n_head, head_dim)
        v = v.reshape(batch, length, self.n_head, head_dim)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, k).astype(jnp.float32) / math.sqrt(head_dim)
        logits = jnp.where(mask[:, None], logits, MASKED_LOGIT)
        probs = drop(jax.nn.softmax(logits, axis=-1).astype(self.dtype))
        attn = jnp.einsum("bhqk,bkhd->bqhd", probs, v).reshape(batch, n_q, width)
        x = x_q + drop(dense(width, "attn_out")(attn))

        h = nn.LayerNorm(epsilon=LN_EPS, dtype=self.dtype, name="ln_mlp")(x)
        h = self.activation(dense(self.mlp_ratio * width, "mlp_in")(h))
        return x + drop(dense(width, "mlp_out")(h))


def jit_init(module: nn.Module, *example_args: Any) -> Callable[[jax.Array], Params]:
    """``key -> module.init(key, *example_args)`` as one jitted program without backend optimisation.

    Eager ``init`` compiles every primitive separately (seconds for a transformer); one program at
    optimisation level 0 compiles in about half the time of a default one and runs once anyway.
    """
    return jax.jit(lambda key: module.init(key, *example_args), compiler_options={"xla_backend_optimization_level": 0})


def create_train_state(module: nn.Module, params: Params, tx: optax.GradientTransformation) -> TrainState:
    """``TrainState`` with ``apply_fn = module.apply`` (a static field, so states can be donated)."""
    return TrainState.create(apply_fn=module.apply, params=params, tx=tx)


def param_count(params: Params) -> int:
    """Number of scalars in a parameter pytree."""
    return int(sum(np.prod(p.shape) for p in jax.tree.leaves(params)))
