"""Issue 40, compile counts of the Table 1 smoke sweep's trials (spot/compiles.py).

A sweep process (a reused Ray actor) runs trials of several environments one after another, so
every program whose shapes follow the observation size is compiled again for each new env. The
IQL state's construction and the evaluation policy's parameters did that with one small program
per parameter shape (the optimizer's zero moments, the target critic's copy, the example inputs,
the params' leading axis); they now build the same arrays without them. Checked here: the arrays
equal bit for bit those of the eager construction (written out in the test), the programs a new
observation size compiles, and a second whole run in a process on another dataset of the same
shapes (and another seed) that compiles nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from spot import compiles, config, evaluation
from spot.nets import create_train_state
from spot.policy import iql
from spot.reward import hpl, models, update
from spot.run import pipeline, policy_stages

EAGER = ("jit(broadcast_in_dim)", "jit(copy)", "jit(convert_element_type)", "jit(expand_dims)")


def _cfg(hidden=(32, 32)):
    return config.resolve({"budget": "tiny", "iql.hidden": list(hidden)}).iql


def _eager_state(key, obs_dim, act_dim, cfg):
    """The IQL state as iql.init_state built it before (eager zeros, train states and copy)."""
    actor_key, critic_key, value_key = jax.random.split(key, 3)
    actor_def, critic_def, value_def = iql._nets(cfg, act_dim)
    obs, act = jnp.zeros((1, obs_dim), jnp.float32), jnp.zeros((1, act_dim), jnp.float32)
    critic_params = jax.jit(critic_def.init)(critic_key, obs, act)
    actor_tx, critic_tx, value_tx = iql._optimizers(cfg)

    def state(module, params, tx):
        return create_train_state(module, params, tx).replace(step=jnp.zeros((), jnp.int32))

    return iql.IQLState(
        actor=state(actor_def, jax.jit(actor_def.init)(actor_key, obs), actor_tx),
        critic=state(critic_def, critic_params, critic_tx),
        value=state(value_def, jax.jit(value_def.init)(value_key, obs), value_tx),
        target_critic_params=jax.tree.map(jnp.copy, critic_params),
        step=jnp.zeros((), jnp.int32),
    )


def _assert_same_tree(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b) and len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype and x.weak_type == y.weak_type  # the same signature
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_iql_state_equals_the_eager_construction_and_compiles_no_program_per_shape():
    cfg = _cfg((24, 24))  # shapes no other test uses: these programs are new to the process
    key = jax.random.key(7)
    iql.init_state(key, 19, 5, cfg)  # the programs a process compiles once (the key's split)
    with compiles.counting() as first:  # a new observation size, as a sweep process meets a new env
        state = iql.init_state(key, 23, 5, cfg)
    _assert_same_tree(state, _eager_state(key, 23, 5, cfg))
    # each network's init and its train state (params, zero moments, step): two programs per network
    assert dict(first.programs) == {"jit(init)": 3, "jit(<lambda>)": 3}
    assert not any(first.programs[name] for name in EAGER)
    # its own buffers: the target critic is not the critic's params (the state is donated)
    for x, y in zip(jax.tree.leaves(state.critic.params), jax.tree.leaves(state.target_critic_params), strict=True):
        assert x is not y and x.unsafe_buffer_pointer() != y.unsafe_buffer_pointer()
    with compiles.counting() as again:  # another seed: nothing new
        other = iql.init_state(jax.random.key(8), 23, 5, cfg)
    assert again.total == 0
    _assert_same_tree(other, _eager_state(jax.random.key(8), 23, 5, cfg))


def test_the_evaluation_policy_compiles_one_program_per_shape():
    cfg = _cfg((24, 24))
    params = iql.init_state(jax.random.key(0), 29, 5, cfg).actor.params
    obs = np.random.default_rng(0).normal(size=(3, 29)).astype(np.float32)
    with compiles.counting() as count:
        actions = policy_stages.eval_policy(params, cfg)(obs)
    assert dict(count.programs) == {"jit(each)": 1}
    want = np.stack([np.asarray(iql.act(params, o[None], cfg))[0] for o in obs])
    np.testing.assert_array_equal(actions, want)
    with compiles.counting() as again:
        policy_stages.eval_policy(iql.init_state(jax.random.key(1), 29, 5, cfg).actor.params, cfg)(obs)
    assert again.total == 0


@pytest.mark.parametrize("kind", ["mr", "pt"])
def test_a_reward_models_state_equals_the_eager_construction_and_compiles_two_programs(kind):
    """MR's and PT's state: params (their init program, example inputs on the host) and the
    optimizer's state as one program, the zeros of the eager ``optimizer(steps).init`` bit for bit."""
    cfg = config.resolve({"method": kind, "budget": "tiny", "mr.hidden": [24, 24], "pt.embd_dim": 24})
    model = models.from_config(cfg)
    update.init_state(model, jax.random.key(0), 19, 5, 37)  # what a process compiles once
    with compiles.counting() as count:  # a new observation size
        state = update.init_state(model, jax.random.key(3), 23, 5, 37)
    assert count.total == 2 and not any(count.programs[name] for name in EAGER), count.programs
    params = model.init(jax.random.key(3), 23, 5)
    eager = update.RewardState(params, model.optimizer(37).init(params), jnp.zeros((), jnp.int32))
    _assert_same_tree(state, eager)


def test_hpls_adam_state_equals_the_eager_one():
    params = {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.ones(3, jnp.bfloat16)}
    _assert_same_tree(hpl.adam_init(3e-4)(params), optax.adam(3e-4).init(params))
    with compiles.counting() as count:
        hpl.adam_init(3e-4)({"w": jnp.zeros((2, 3)), "b": jnp.zeros(3, jnp.bfloat16)})
    assert count.total == 0  # kept per learning rate


@pytest.mark.usefixtures("spot_dirs")
def test_a_second_run_of_a_method_in_a_process_compiles_nothing(tmp_path):
    """Oracle on drawer-open, then on plate-slide (the same observation and action sizes) with
    another seed, in one process as a reused sweep actor runs them: the second run compiles or
    loads no program."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"

    def run(data, seed):
        cfg = config.resolve(
            {
                "method": "oracle",
                "budget": "tiny",
                "data.name": data,
                "data.size": "tiny",
                "seed": seed,
                "tracking.uri": uri,
                "tracking.experiment": "compiles",
            }
        )
        with compiles.counting() as count:
            out = pipeline.run(cfg, progress=False)
        return out, count

    first, _ = run("drawer-open", 0)
    second, count = run("plate-slide", 1)
    assert count.total == 0, dict(count.programs)
    assert np.isfinite(first["eval/score_final"]) and np.isfinite(second["eval/score_final"])
    evaluation.clear_env_pool()
