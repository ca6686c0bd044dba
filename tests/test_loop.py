"""spot.loop: chunk sizes, the masked last chunk, reductions, padding, the host loop (NaN check,
keep-best, callbacks), and the step rule on IQL and the CVAE: a run does exactly its steps."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from spot import NonFiniteError, SpotError, loop
from spot.batches import Transitions
from spot.config import CVAEConfig, IQLConfig
from spot.policy import iql
from spot.subgoal import cvae


def counter_update(state, scale):
    """Toy learner: ``x += scale`` per update; reports the value before the update as its loss."""
    x, step = state
    return (x + scale, step + 1), {"loss": x, "double": 2.0 * x}


def test_chunk_sizes_by_hand():
    assert loop.chunk_sizes(1500, 1000) == [1000, 500]
    assert loop.chunk_sizes(2000, 1000) == [1000, 1000]
    assert loop.chunk_sizes(25, 10) == [10, 10, 5]
    assert loop.chunk_sizes(7, 10) == [7]
    assert loop.chunk_length(7, 10) == 7 and loop.chunk_length(1500, 1000) == 1000
    with pytest.raises(SpotError, match="chunk=0"):
        loop.chunk_sizes(10, 0)


@pytest.mark.parametrize("reduce", ["stack", "mean", "sum"])
def test_short_chunk_runs_n_updates_with_one_program(reduce):
    chunk = loop.make_chunk(counter_update, 4, reduce)
    state = (jnp.float32(0.0), jnp.int32(0))
    state, full = chunk(state, 4, jnp.float32(1.0))  # x: 0, 1, 2, 3 -> 4
    state, tail = chunk(state, 3, jnp.float32(1.0))  # x: 4, 5, 6 -> 7; the 4th update is skipped
    assert chunk._cache_size() == 1
    assert float(state[0]) == 7.0 and int(state[1]) == 7
    if reduce == "stack":
        np.testing.assert_array_equal(tail["active"], [True, True, True, False])
        np.testing.assert_array_equal(tail["loss"], [4.0, 5.0, 6.0, 0.0])  # skipped updates report zeros
        np.testing.assert_array_equal(full["loss"], [0.0, 1.0, 2.0, 3.0])
    else:  # means over the updates that ran
        assert float(full["loss"]) == 1.5 and float(tail["loss"]) == 5.0 and float(tail["double"]) == 10.0


def test_vmapped_chunk_shares_n():
    chunk = loop.make_chunk(counter_update, 4, "sum", vmap_axes=(0, 0))
    state = (jnp.zeros(2), jnp.zeros(2, jnp.int32))
    state, metrics = chunk(state, 3, jnp.array([1.0, 2.0]))
    np.testing.assert_array_equal(state[0], [3.0, 6.0])
    np.testing.assert_array_equal(metrics["loss"], [1.0, 2.0])  # means of (0, 1, 2) and (0, 2, 4)


def test_pad_minibatches_by_hand():
    tree = {"a": np.arange(5), "b": np.arange(10).reshape(5, 2)}
    padded, weight = loop.pad_minibatches(tree, 2)
    np.testing.assert_array_equal(padded["a"], [[0, 1], [2, 3], [4, 0]])
    np.testing.assert_array_equal(padded["b"][2], [[8, 9], [0, 1]])
    np.testing.assert_array_equal(weight, [[1, 1], [1, 1], [1, 0]])


def test_check_finite_names_step_and_metric():
    with pytest.raises(NonFiniteError) as err:
        loop.check_finite({"iql/critic_loss": jnp.array([1.0, jnp.nan]), "iql/q_mean": jnp.array([0.0, 0.0])}, 400)
    assert (err.value.step, err.value.loss_name) == (400, "iql/critic_loss")
    assert loop.check_finite({"a/value_loss": jnp.float32(1.0), "a/adv_max": jnp.inf}, 1)  # not a loss
    with pytest.raises(NonFiniteError):
        loop.check_finite({"x": jnp.inf}, 3, names=["x"])


def test_run_does_exactly_steps_keeps_best_and_calls_back():
    chunk = loop.make_chunk(counter_update, 4, "stack")
    seen = []

    def evaluate(state):  # a held-out loss (x - 5)^2: lowest after the first chunk (x = 4)
        return {"eval_loss": (float(state[0]) - 5.0) ** 2}

    out = loop.run(
        chunk,
        (jnp.float32(0.0), jnp.int32(0)),
        (jnp.float32(1.0),),
        steps=10,
        length=4,
        losses={"loss": "toy/loss"},
        evaluate=evaluate,
        eval_loss=("eval_loss", "toy/eval"),
        best_by="eval_loss",
        params_of=lambda s: {"x": s[0]},
        on_chunk=lambda row, state: seen.append((row["step"], float(state[0]))),
    )
    assert [row["step"] for row in out.rows] == [4, 8, 10] and int(out.state[1]) == 10
    assert seen == [(4, 4.0), (8, 8.0), (10, 10.0)]
    # chunk means over the updates that ran: (0+1+2+3)/4, (4+..+7)/4, (8+9)/2
    assert [row["loss"] for row in out.rows] == [1.5, 5.5, 8.5]
    assert out.best["step"] == 4 and float(out.best_params["x"]) == 4.0  # (4 - 5)^2 = 1 is the lowest


def test_run_names_the_failing_update():
    def update(state, _):
        x, step = state
        return (x + 1.0, step + 1), {"loss": jnp.where(step == 6, jnp.nan, x)}

    with pytest.raises(NonFiniteError) as err:
        loop.run(
            loop.make_chunk(update, 4, "stack"),
            (jnp.float32(0.0), jnp.int32(0)),
            (0,),
            steps=10,
            length=4,
            losses={"loss": "toy/loss"},
        )
    assert (err.value.step, err.value.loss_name) == (6, "toy/loss")
    with pytest.raises(NonFiniteError) as err:  # chunk means: the chunk's end
        loop.run(loop.make_chunk(update, 4, "mean"), (jnp.float32(0.0), jnp.int32(0)), (0,), steps=10, length=4)
    assert (err.value.step, err.value.loss_name) == (8, "loss")
    with pytest.raises(NonFiniteError) as err:  # a held-out loss
        loop.run(
            loop.make_chunk(counter_update, 4, "stack"),
            (jnp.float32(0.0), jnp.int32(0)),
            (jnp.float32(1.0),),
            steps=10,
            length=4,
            evaluate=lambda s: {"eval_loss": np.inf},
            eval_loss=("eval_loss", "toy/eval"),
        )
    assert (err.value.step, err.value.loss_name) == (4, "toy/eval")


# --------------------------------------------------------------------------- the step rule
def test_iql_runs_exactly_steps_when_not_a_multiple_of_the_chunk():
    """iql.steps=15, iql.chunk=10 (as 1500 / 1000): 15 updates, not 20; the actor's cosine schedule
    reaches 0 at the last update; evaluations before the first update, after 10 and at the end."""
    cfg = IQLConfig(hidden=(8,), batch_size=16, steps=15, chunk=10)
    rng = np.random.default_rng(0)
    data = Transitions(
        *(jnp.asarray(rng.normal(size=shape).astype(np.float32)) for shape in ((50, 3), (50, 2), (50,), (50, 3), (50,)))
    )
    state = iql.init_state(jax.random.key(0), 3, 2, cfg)
    logged = []
    curve = iql.train(
        iql.make_train_chunk(cfg),
        state,
        lambda c: (data, jax.random.key(c)),
        cfg,
        10,
        lambda params, step: float(step),
        log=lambda metrics, step: logged.append(step),
    )
    assert int(curve.state.step) == 15 and int(curve.state.actor.step) == 15
    assert logged == [10, 15] and curve.steps == [0, 10, 15] and curve.scores == [0.0, 10.0, 15.0]
    actor_lr = optax.cosine_decay_schedule(cfg.lr, cfg.steps)
    assert float(actor_lr(15)) == 0.0 and float(actor_lr(14)) > 0.0  # the last update used the last lr > 0
    assert iql.make_train_chunk(cfg)._cache_size() == 1  # the 5-update chunk reused the program


def test_cvae_runs_exactly_steps():
    rng = np.random.default_rng(0)
    s = rng.normal(size=(64, 3)).astype(np.float32)
    a = rng.uniform(-1, 1, (64, 2)).astype(np.float32)
    cfg = CVAEConfig(latent_dim=2, hidden=(8,), batch_size=16, steps=12)
    _, history = cvae.train_cvae(jax.random.key(0), s, a, s + 1.0, cfg, cvae.obs_stats(s), progress=False, log_every=5)
    assert [row["step"] for row in history] == [5, 10, 12]
